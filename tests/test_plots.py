"""Plots from a real short sweep's rows and traces: valid files, clear exit-2 errors,
nothing half-written; the statistics and columns they rest on."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from results import plots
from results.store import TRACES, RunDir
from tests.real_sweep import real_sweep

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    return real_sweep(tmp_path_factory)


def _only(folder, name):
    """The folder holds exactly `name`: no temporary or half-written figure beside it."""
    assert sorted(p.name for p in folder.iterdir()) == [name]


# ---------------------------------------------------------------- statistics, columns


def test_intervals_wilson_for_success_t_for_means():
    est, low, high, n = plots.interval(pd.Series([True] * 8 + [False] * 2), is_success=True)
    assert (
        (est, n) == (0.8, 10)
        and low == pytest.approx(0.4902, abs=1e-3)
        and high == pytest.approx(0.9433, abs=1e-3)
    )
    est, low, high, n = plots.interval(pd.Series([1.0, 2.0, 3.0]), is_success=False)
    assert est == 2.0 and high - est == pytest.approx(4.303 * 1.0 / np.sqrt(3), rel=1e-3)
    assert low == 0.0  # clipped: a rate is never negative
    _, low, high, n = plots.interval(pd.Series([5.0]), is_success=False)
    assert n == 1 and np.isnan(low) and np.isnan(high)  # one episode: no interval drawn


def test_the_frontier_keeps_what_nothing_beats_on_both_axes():
    xs, ys = np.array([1.0, 2.0, 3.0, 2.5]), np.array([0.9, 0.8, 0.5, 0.4])
    assert plots._frontier(xs, ys, x_up=True, y_up=True) == [0, 1, 2]
    assert plots._frontier(xs, ys, x_up=False, y_up=True) == [0]


def test_labels_show_a_lone_configurations_non_default_parameters():
    """A pareto plot of one fast_dvla at tau_conf=0.3 must not call it plain fast_dvla."""
    frame = pd.DataFrame(
        {
            "policy_config_id": ["a", "b", "c", "d"],
            "policy": ["fast_dvla", "bidirectional", "bidirectional", "autoregressive"],
            "policy_params": [
                json.dumps({"tau_conf": 0.3}),
                json.dumps({"steps": 12}),
                json.dumps({"steps": 8}),
                json.dumps({}),
            ],
        }
    )
    assert plots.config_labels(frame) == {
        "a": "fast_dvla (tau_conf=0.3)",
        "b": "bidirectional (steps=12)",
        "c": "bidirectional (steps=8)",
        "d": "autoregressive",
    }
    default = frame.iloc[:1].assign(policy_params=json.dumps({"tau_conf": 0.5}))
    assert plots.config_labels(default) == {"a": "fast_dvla"}  # the default says nothing


def test_a_legend_names_a_default_configuration_as_the_tables_do():
    """fast_dvla at its default block size (0: the checkpoint's 4) plots at 4 but is `fast_dvla`."""
    frame = pd.DataFrame(
        {
            "policy_config_id": ["a", "b"],
            "policy": ["fast_dvla", "bidirectional"],
            "policy_params": [json.dumps({"block_size": 0, "tau_conf": 0.5}), json.dumps({"steps": 12})],
            "checkpoint": ["", ""],
        }
    )
    expanded = plots.plot_frame(frame, {"a": {"block_size": 4}, "b": {}})
    assert expanded["block_size"].iloc[0] == 4
    assert dict(zip(expanded["policy_config_id"], expanded["config_label"], strict=True)) == {
        "a": "fast_dvla",
        "b": "bidirectional",
    }


def test_columns_come_from_rows_parameters_and_checkpoint_headers(sweep):
    frame = plots.plot_frame(RunDir(sweep.path).read_episodes())
    assert set(frame["block_size"]) == {4, 8} and set(frame["param.tau_conf"]) == {0.5}
    assert set(frame["noise_schedule"]) == {"frontier"} and set(frame["checkpoint.recipe"]) == {"distill"}
    assert set(frame["config_label"]) == {"fast_dvla (block_size=4)", "fast_dvla (block_size=8)"}
    zero = frame.assign(policy_params=frame["policy_params"].str.replace('"block_size":4', '"block_size":0'))
    zero = zero.drop(columns=[c for c in zero if c.startswith(("param.", "checkpoint."))])
    assert set(plots.plot_frame(zero)["block_size"]) == {4, 8}  # 0 is the checkpoint's 4


# ---------------------------------------------------------------- figures from the real sweep


def test_ablation_png_and_svg(sweep, cli, tmp_path):
    out = tmp_path / "figs" / "ablation.png"
    code, _, err = cli(
        "plot", "ablation", str(sweep.path), "--x", "block_size", "--y", "success,tokens_per_s,nfe_per_chunk",
        "--out", str(out),
    )  # fmt: skip
    assert code == 0, err
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 10_000
    _only(out.parent, "ablation.png")
    svg = tmp_path / "ablation.svg"
    code, _, err = cli(
        "plot", "ablation", str(sweep.path), "--x", "block_size", "--y", "tokens_per_s", "--hue", "task",
        "--out", str(svg),
    )  # fmt: skip
    assert code == 0, err
    text = svg.read_text()
    assert text.startswith("<?xml") and "<svg" in text and "drawer-close-v3" in text


def test_pareto_has_one_marker_per_configuration(sweep, cli, tmp_path):
    episodes = RunDir(sweep.path).read_episodes()
    fig = plots.pareto_plot(episodes)  # the signature other outputs (the HTML report) use
    assert isinstance(fig, Figure)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert sum(label.startswith("fast_dvla (block_size=") for label in labels) == 2
    out = tmp_path / "pareto.svg"
    code, _, err = cli(
        "plot", "pareto", str(sweep.path), "--x", "tokens_per_s", "--y", "success", "--out", str(out)
    )
    assert code == 0, err
    assert "<svg" in out.read_text()
    again = tmp_path / "again.svg"
    plots.pareto_plot(episodes, out=again)
    assert again.read_bytes() == out.read_bytes()  # same rows, same file


def test_decoding_order_from_recorded_traces(sweep, cli, tmp_path):
    out = tmp_path / "order.png"
    code, _, err = cli("plot", "decoding-order", str(sweep.path), "--out", str(out))
    assert code == 0, err
    assert out.read_bytes()[:8] == PNG
    traces = RunDir(sweep.path).read_traces()
    from results.order_plot import decoding_order_plot

    fig = decoding_order_plot(traces)
    image = fig.axes[0].images[0].get_array()
    assert image.shape[1] == 32 and np.allclose(image.sum(), image.shape[1])  # each position once a chunk


@pytest.mark.parametrize(
    ("kind", "extra", "out_name", "message"),
    [
        ("ablation", ["--x", "block_size", "--y", "success,speed"], "f.png",
         "no numeric column 'speed' for y; valid choices are episode columns: .*tokens_per_s.*; policy parameters: block_size"),
        ("ablation", ["--x", "blocks", "--y", "success"], "f.png", "no column 'blocks' for x; valid choices are"),
        ("ablation", ["--x", "block_size", "--y", "success"], "f.jpg", r"use one of \.png, \.svg"),
        ("pareto", ["--y", "task"], "f.svg", "no numeric column 'task' for y"),
        ("decoding-order", [], "f.pdf", r"use one of \.png, \.svg"),
    ],
)  # fmt: skip
def test_bad_inputs_exit_2_with_the_valid_choices_and_write_nothing(
    sweep, cli, tmp_path, kind, extra, out_name, message
):
    import re

    out = tmp_path / "figs" / out_name
    code, _, err = cli("plot", kind, str(sweep.path), *extra, "--out", str(out))
    assert code == 2 and re.search(message, err), err
    assert len(err.strip().splitlines()) == 1
    assert not out.parent.exists() or not any(out.parent.iterdir())


def test_a_run_without_traces_or_no_run_at_all_exits_2(sweep, cli, tmp_path):
    copy = tmp_path / "untraced"
    shutil.copytree(sweep.path, copy)
    (copy / TRACES).unlink()
    out = tmp_path / "order.png"
    code, _, err = cli("plot", "decoding-order", str(copy), "--out", str(out))
    assert code == 2 and "no traces.jsonl" in err and "--traces" in err and not out.exists()
    code, _, err = cli("plot", "pareto", str(tmp_path / "nope"), "--out", str(out))
    assert code == 2 and "no such run folder" in err and not out.exists()


# ---------------------------------------------------------------- noise schedule via checkpoints


def test_a_noise_schedule_ablation_sweeps_checkpoints_and_plots_by_header(cli, tmp_path):
    """Two checkpoints whose headers differ in the training noise schedule: the sweep
    records each one's header fields in the manifest, and --hue noise_schedule uses them."""
    pytest.importorskip("metaworld")
    from policies.dvla.checkpoint import load, save
    from policies.dvla.policy import shipped

    ckpt = load(shipped("fast_dvla"))
    ckpt.meta["train_config"] = dict(ckpt.meta["train_config"], noise_schedule="linear")
    linear = save(ckpt, tmp_path / "linear.safetensors")
    run = tmp_path / "run"
    code, _, err = cli(
        "sweep", "--suite", "metaworld/mt10", "--tasks", "drawer-close-v3", "--episodes-per-task", "1",
        "--policy", "fast_dvla", "--grid", f"checkpoint={shipped('fast_dvla')},{linear}",
        "--grid", "block_size=4,8", "--quiet", "--out", str(run),
    )  # fmt: skip
    assert code == 0, err
    manifest = json.loads((run / "manifest.json").read_text())
    assert sorted(p["checkpoint_fields"]["noise_schedule"] for p in manifest["policies"]) == [
        "frontier", "frontier", "linear", "linear",
    ]  # fmt: skip
    out = tmp_path / "noise.png"
    code, _, err = cli(
        "plot", "ablation", str(run), "--x", "block_size", "--y", "success,tokens_per_s",
        "--hue", "noise_schedule", "--out", str(out),
    )  # fmt: skip
    assert code == 0, err
    assert out.read_bytes()[:8] == PNG


def test_experts_say_why_there_is_no_pareto_or_decoding_order(cli, tmp_path):
    out = tmp_path / "r"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "scripted", "--policy", "random",
        "--episodes-per-task", "1", "--traces", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    code, _, err = cli("plot", "pareto", str(out), "--out", str(tmp_path / "p.png"))
    assert code == 2 and "no numeric column 'tokens_per_s' for x" in err and "control_hz" in err
    code, _, err = cli("plot", "pareto", str(out), "--x", "control_hz", "--out", str(tmp_path / "p.png"))
    assert code == 0, err
    code, _, err = cli("plot", "decoding-order", str(out), "--out", str(tmp_path / "o.png"))
    assert code == 2 and "its policies (random, scripted) returned no decode trace" in err


def _two_decoders() -> pd.DataFrame:
    from tests.test_leaderboard import episodes

    rows = []
    for policy, config, block, tau in (
        ("fast_dvla", "fast04", 4, 0.5),
        ("fast_dvla", "fast08", 8, 0.5),
        ("block_diffusion", "bd04", 4, 0.5),
    ):
        params = json.dumps({"block_size": block, "tau_conf": tau})
        rows += episodes(policy, params, config, [1, 0, 1])
    return pd.DataFrame(rows)


def test_an_ablation_of_several_decoders_needs_a_hue_that_keeps_them_apart(tmp_path):
    frame = _two_decoders()
    with pytest.raises(plots.PlotInputError, match=r"2 policies \(fast_dvla, block_diffusion\) and no --hue"):
        plots.ablation_plot(frame, "block_size", ["success"])
    with pytest.raises(plots.PlotInputError, match="--hue tau_conf has values shared by several policies"):
        plots.ablation_plot(frame, "block_size", ["success"], hue="tau_conf")
    plots.ablation_plot(frame, "block_size", ["success"], hue="policy", out=tmp_path / "a.png")
    plots.ablation_plot(frame, "block_size", ["success"], hue="config_label", out=tmp_path / "b.png")
    one = frame[frame["policy"] == "fast_dvla"]
    plots.ablation_plot(one, "block_size", ["success"], out=tmp_path / "c.png")  # one decoder: no hue needed
    assert all((tmp_path / f).stat().st_size > 1000 for f in ("a.png", "b.png", "c.png"))


def test_labels_leave_out_parameters_a_configuration_does_not_use():
    """fast_dllm decoding by threshold never uses steps_per_block: a legend must not name it."""
    frame = pd.DataFrame(
        {
            "policy_config_id": ["t", "f"],
            "policy": ["fast_dllm", "fast_dllm"],
            "policy_params": [
                json.dumps({"threshold": 0.9, "steps_per_block": 4}),
                json.dumps({"threshold": 0.0, "steps_per_block": 2}),
            ],
        }
    )
    assert plots.config_labels(frame) == {
        "t": "fast_dllm (threshold=0.9)",
        "f": "fast_dllm (steps_per_block=2, threshold=0)",
    }


def _with_fast_dllm() -> pd.DataFrame:
    """fast_dvla at block sizes 4 and 8 beside fast_dllm at its default block_size 0 (the
    chunk cut into `blocks`: no block size of its own)."""
    from tests.test_leaderboard import episodes

    rows = []
    for policy, config, params in (
        ("fast_dvla", "fast04", {"block_size": 4}),
        ("fast_dvla", "fast08", {"block_size": 8}),
        ("fast_dllm", "dllm00", {"block_size": 0, "blocks": 1, "threshold": 0.3}),
    ):
        rows += episodes(policy, json.dumps(params), config, [1, 0, 1])
    return pd.DataFrame(rows)


def test_a_configuration_that_does_not_use_x_is_left_out_with_a_warning(tmp_path):
    frame = _with_fast_dllm()
    with pytest.warns(UserWarning, match=r"left out of the plot, as they do not use block_size: fast_dllm$"):
        fig = plots.ablation_plot(frame, "block_size", ["success"], hue="config_label")
    assert list(fig.axes[0].get_xticks()) == [4.0, 8.0]  # no point at x=0
    _, legend = fig.axes[0].get_legend_handles_labels()
    assert not any("fast_dllm" in label for label in legend)
    with pytest.warns(UserWarning, match="fast_dllm"):  # one decoder remains: no hue needed
        plots.ablation_plot(frame, "block_size", ["success"], out=tmp_path / "a.png")
    assert (tmp_path / "a.png").stat().st_size > 1000


def test_an_ablation_over_a_parameter_no_configuration_uses_is_refused_naming_its_users(tmp_path):
    frame = _with_fast_dllm()
    only = frame[frame["policy"] == "fast_dllm"]
    with pytest.raises(plots.PlotInputError) as err:
        plots.ablation_plot(only, "block_size", ["success"], out=tmp_path / "a.png")
    message = str(err.value)
    assert "no configuration in these rows uses block_size (fast_dllm)" in message
    assert "valid users: block_diffusion, fast_dllm (not at its default block_size=0), fast_dvla" in message
    assert not (tmp_path / "a.png").exists()
    # set, fast_dllm's block_size is one: it is plotted, and its unused `blocks` leaves the legend
    sized = frame[frame["policy"] == "fast_dllm"].assign(
        policy_params=json.dumps({"block_size": 4, "blocks": 8})
    )
    fig = plots.ablation_plot(sized, "block_size", ["success"])
    assert list(fig.axes[0].get_xticks()) == [4.0]


def test_the_cli_names_the_dropped_configuration_on_stderr_and_exits_2_when_none_remain(cli, tmp_path):
    from tests.test_leaderboard import write_run

    rows = _with_fast_dllm().to_dict("records")
    both = write_run(tmp_path / "both", rows)
    code, _, err = cli(
        "plot", "ablation", str(both), "--x", "block_size", "--y", "success", "--out", str(tmp_path / "a.png")
    )
    assert code == 0, err
    assert "warning: left out of the plot, as they do not use block_size: fast_dllm" in err
    alone = write_run(tmp_path / "alone", [r for r in rows if r["policy"] == "fast_dllm"])
    code, _, err = cli(
        "plot",
        "ablation",
        str(alone),
        "--x",
        "block_size",
        "--y",
        "success",
        "--out",
        str(tmp_path / "b.png"),
    )
    assert code == 2 and "valid users: block_diffusion" in err and not (tmp_path / "b.png").exists()


def test_fast_dllms_block_size_and_blocks_are_named_only_where_they_apply():
    """block_size 0 cuts the chunk into `blocks`; a block_size set overrides `blocks`."""
    frame = pd.DataFrame(
        {
            "policy_config_id": ["cut", "sized"],
            "policy": ["fast_dllm", "fast_dllm"],
            "policy_params": [
                json.dumps({"block_size": 0, "blocks": 2}),
                json.dumps({"block_size": 4, "blocks": 8}),
            ],
        }
    )
    assert plots.config_labels(frame) == {"cut": "fast_dllm (blocks=2)", "sized": "fast_dllm (block_size=4)"}
