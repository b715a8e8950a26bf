"""A sweep carries its baseline: `--reference bidirectional` runs the teacher beside a
block-size grid, interleaved episode by episode, and `plot ablation|pareto` show speedup
over it (a ratio of mean tokens/s over paired episodes, with the ratio estimator's
interval), on real Meta-World episodes."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from results import plots
from results.plot_speedup import BASELINE_TOKENS, speedup_interval, with_speedup
from results.runs import load_run
from results.store import RunDir
from results.summary import t_quantile

GRID = ["--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "2", "--quiet"]
GRID += ["--policy", "fast_dvla", "--grid", "block_size=4,8"]


@pytest.fixture(scope="module")
def blocks(tmp_path_factory):
    """The block-size ablation with its baseline, through the CLI a user types."""
    from harness.cli import main

    out = tmp_path_factory.mktemp("blocks") / "run"
    assert main(["sweep", *GRID, "--reference", "bidirectional", "--out", str(out)]) == 0
    return out


@pytest.mark.metaworld
def test_a_policy_without_the_grid_key_is_pointed_to_reference(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli("sweep", *GRID, "--policy", "bidirectional", "--out", str(out))
    assert code == 2 and not out.exists()
    assert "policy 'bidirectional' has no parameter 'block_size'" in err
    assert "pass --reference bidirectional" in err
    code, _, err = cli("sweep", *GRID, "--reference", "nope", "--out", str(out))
    assert code == 2 and "--reference nope" in err and not out.exists()


@pytest.mark.metaworld
def test_the_reference_runs_interleaved_with_the_grid_and_the_summary_has_speedups(blocks, capsys):
    rows = RunDir(blocks).read_episodes().sort_values("started_at")
    assert list(dict.fromkeys(rows["config_label"])) == [
        "bidirectional",
        "fast_dvla (block_size=4)",
        "fast_dvla (block_size=8)",
    ]
    # episode by episode: every configuration finishes episode 0 before any starts episode 1
    first_of_one = rows.index.get_loc(rows.index[rows["episode_index"] == 1][0])
    assert set(rows.iloc[:first_of_one]["episode_index"]) == {0} and first_of_one == 3
    from harness.cli import main

    capsys.readouterr()
    assert main(["show", str(blocks)]) == 0
    out = capsys.readouterr().out
    all_rows = [line for line in out.splitlines() if "ALL" in line]
    assert all_rows[0].rstrip(" │").endswith("1.00x")
    assert all(line.rstrip(" │").endswith("x") and "n/a" not in line for line in all_rows)


@pytest.mark.metaworld
def test_speedup_is_the_ratio_of_mean_tokens_per_s_on_paired_episodes(blocks):
    episodes = load_run(blocks).episodes
    frame = with_speedup(plots.plot_frame(episodes), "bidirectional")
    base = episodes[episodes["policy"] == "bidirectional"].set_index(["task", "episode_index"])
    for _, part in frame[frame["policy"] == "fast_dvla"].groupby("policy_config_id"):
        mine = part.set_index(["task", "episode_index"])["tokens_per_s"]
        expected = mine.mean() / base.loc[mine.index, "tokens_per_s"].mean()
        est, low, high, n = speedup_interval(part)
        assert n == 2 and est == pytest.approx(expected) and low <= est <= high
    teacher = frame[frame["policy"] == "bidirectional"]
    assert speedup_interval(teacher)[:3] == (1.0, 1.0, 1.0)  # against itself: exactly 1, no width


@pytest.mark.metaworld
def test_ablation_draws_the_baseline_and_speedup_panels(blocks, tmp_path, cli):
    episodes = plots.plot_frame(load_run(blocks).episodes)
    fig = plots.ablation_plot(episodes, "block_size", ["success", "speedup"])
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["bidirectional (baseline, n=2)"]
    speed_panel = fig.axes[1]
    dashed = [line for line in speed_panel.get_lines() if line.get_linestyle() == "--"]
    assert len(dashed) == 1 and list(dashed[0].get_ydata()) == [1.0, 1.0]  # the baseline at 1.0x
    assert speed_panel.get_ylabel() == "speedup over bidirectional (x)"
    out = tmp_path / "blocks.png"
    code, _, err = cli(
        "plot", "ablation", str(blocks), "--x", "block_size", "--y", "success,speedup", "--out", str(out)
    )
    assert code == 0 and out.stat().st_size > 10_000, err
    assert "left out of the plot" not in err  # the baseline is drawn, not dropped
    svg = tmp_path / "pareto.svg"
    code, _, err = cli("plot", "pareto", str(blocks), "--x", "speedup", "--out", str(svg))
    assert code == 0, err
    text = svg.read_text()
    assert "bidirectional (n=2)" in text and "fast_dvla (block_size=4) (n=2)" in text


@pytest.mark.metaworld
def test_speedup_without_a_baseline_in_the_rows_names_the_fix(blocks, cli, tmp_path):
    code, _, err = cli(
        "plot", "ablation", str(blocks), "--x", "block_size", "--y", "speedup", "--baseline", "fast_dllm",
        "--out", str(tmp_path / "f.png"),
    )  # fmt: skip
    assert code == 2 and not (tmp_path / "f.png").exists()
    assert "speedup needs fast_dllm rows" in err and "--reference fast_dllm" in err


def _pairs(a: list[float], b: list[float]) -> pd.DataFrame:
    return pd.DataFrame({"tokens_per_s": a, BASELINE_TOKENS: b})


def test_the_ratio_estimators_interval_on_edge_cases():
    est, low, high, n = speedup_interval(_pairs([300.0, 200.0, 250.0], [100.0, 80.0, 120.0]))
    a, b = np.array([300.0, 200.0, 250.0]), np.array([100.0, 80.0, 120.0])
    ratio = a.mean() / b.mean()
    half = t_quantile(2) * np.std(a - ratio * b, ddof=1) / (np.sqrt(3) * b.mean())
    assert (est, n) == (pytest.approx(2.5), 3) and (low, high) == pytest.approx((ratio - half, ratio + half))
    est, low, high, _ = speedup_interval(_pairs([2.0, 4.0, 6.0], [1.0, 2.0, 3.0]))  # every pair 2x
    assert est == low == high == 2.0
    est, low, high, n = speedup_interval(_pairs([3.0], [2.0]))
    assert (est, n) == (1.5, 1) and math.isnan(low) and math.isnan(high)  # one pair: no interval
    assert speedup_interval(_pairs([], []))[3] == 0
    assert speedup_interval(_pairs([3.0, None], [None, 2.0]))[3] == 0  # no complete pair
    assert speedup_interval(_pairs([3.0, 3.0], [0.0, 0.0]))[3] == 0  # a baseline that decodes nothing
