"""Sweeps: grid parsing and validation (nothing written on bad input), decode block
size, trace persistence, and a real resumable sweep on Meta-World."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from harness.config import PolicyChoice, RunConfig
from harness.errors import UsageError
from harness.run.runner import run
from harness.run.sweep import expand, parse_grid
from policies.base import ChunkBatch
from results.store import TRACES, RunDir
from tests.fakes import ChunkPolicy, fake_resolved
from tests.real_sweep import INTERRUPT_AFTER, SWEEP_ARGS, real_sweep
from tests.test_plugins import installed_plugin  # noqa: F401  (a fixture)

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

MT1 = ["--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--quiet"]


def _config(*policies: PolicyChoice) -> RunConfig:
    return RunConfig(suite="metaworld/mt1/reach-v3", policies=policies or (PolicyChoice("fast_dvla"),))


def test_the_grid_is_the_cartesian_product_in_the_order_given():
    grid = parse_grid(["block_size=4,8,16", "tau_conf=0.3,0.5"])
    config = expand(_config(PolicyChoice("fast_dvla", {"n": "3"})), grid)
    points = [(p.params["block_size"], p.params["tau_conf"]) for p in config.policies]
    assert points == [(b, t) for b in ("4", "8", "16") for t in ("0.3", "0.5")]
    assert all(p.name == "fast_dvla" and p.params["n"] == "3" for p in config.policies)


def test_a_checkpoint_grid_is_a_grid_over_a_parameter(tmp_path):
    from policies.dvla.policy import shipped

    a, b = shipped("fast_dvla"), str(tmp_path / "b.safetensors")
    shutil.copy(a, b)
    config = expand(_config(), parse_grid([f"checkpoint={a},{b}", "block_size=4,8"]))
    assert [p.params["checkpoint"] for p in config.policies] == [a, a, b, b]


@pytest.mark.parametrize(
    ("items", "message"),
    [
        ([], "no --grid given"),
        (["block_size"], "expected KEY=V1,V2"),
        (["block_size="], "no values"),
        (["block_size=4,4"], "value '4' is listed twice"),
        (["block_size=4", "block_size=8"], "given twice"),
    ],
)
def test_malformed_grids_are_refused(items, message):
    with pytest.raises(UsageError, match=message):
        parse_grid(items)


@pytest.mark.parametrize(
    ("grid", "message"),
    [
        ("steps=3,4", "policy 'fast_dvla' has no parameter 'steps'; grid keys are its parameters: checkpoint"),
        ("tau_conf=0.5,1.5", r"--grid tau_conf=1.5: .*tau_conf=1.5 is out of range; valid range \[0.0, 1.0\]"),
        ("block_size=4,x", "--grid block_size=x: .*parameter 'block_size' must be int, got 'x'"),
        ("confidence=max_prob,best", "confidence='best' is not valid; choose one of max_prob, margin"),
        ("block_size=4,5", r"block_size=5 does not divide the chunk's 32 action tokens; valid: 0 \(the checkpoint's, 4\), 1, 2, 4, 8, 16, 32"),
        ("tau_add=0.2,0.5 tau_act=0.4,0.9", r"--grid point tau_add=0.5,tau_act=0.4: .*tau_add \(0.5\) must be <= tau_act \(0.4\)"),
    ],
)  # fmt: skip
def test_invalid_grid_values_exit_2_before_anything_is_written(cli, tmp_path, grid, message):
    out = tmp_path / "run"
    grids = [arg for g in grid.split() for arg in ("--grid", g)]
    code, _, err = cli("sweep", *MT1, "--policy", "fast_dvla", *grids, "--out", str(out))
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err), err
    assert not out.exists()


def test_the_issues_noise_schedule_example_teaches_the_right_command(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli(
        "sweep", *MT1, "--policy", "fast_dvla", "--grid", "block_size=4,8,16",
        "--grid", "noise_schedule=linear,cosine", "--out", str(out),
    )  # fmt: skip
    assert code == 2 and not out.exists()
    assert "fixed when a checkpoint is trained" in err
    assert "--grid checkpoint=a.safetensors,b.safetensors" in err and "--hue noise_schedule" in err
    assert "--policy block_diffusion --grid schedule=linear,cosine" in err
    code, _, err = cli(
        "sweep", *MT1, "--policy", "block_diffusion", "--grid", "noise_schedule=linear,cosine",
        "--out", str(out),
    )  # fmt: skip
    assert code == 2 and "block_diffusion's inference-time unmasking schedule is `--grid schedule" in err


def test_a_key_set_both_in_policy_and_grid_and_a_missing_policy_are_refused(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli("sweep", *MT1, "--policy", "fast_dvla:block_size=4", "--grid", "block_size=4,8")
    assert code == 2 and "both set block_size" in err
    code, _, err = cli("sweep", *MT1, "--grid", "block_size=4,8", "--out", str(out))
    assert code == 2 and "sweep needs the policy to vary: --policy NAME" in err and not out.exists()


def test_decode_block_size_changes_the_mask_and_the_blocks(tmp_path):
    """block_diffusion decodes (32 / block_size) blocks of steps_per_block passes each."""
    import gymnasium as gym

    from policies.base import EpisodeContext
    from policies.registry import get_policy, parse_params

    spec = get_policy("block_diffusion")
    ctx = EpisodeContext(
        "metaworld/mt10", "reach-v3", "reach the goal", gym.spaces.Box(-1, 1, (4,)),
        gym.spaces.Box(-np.inf, np.inf, (39,)), 500, 0,
    )  # fmt: skip
    for block_size, blocks in ((0, 8), (4, 8), (8, 4), (32, 1)):
        policy = spec.build(parse_params(spec, {"block_size": str(block_size), "steps_per_block": "2"}))
        assert policy.model.cfg.block == 32 // blocks
        policy.reset([ctx])
        batch = policy.act([np.zeros(39)])
        passes = batch.trace[0]["committed"]
        assert len(passes) == blocks * 2
        assert sorted(p for step in passes for p in step) == list(range(32))
        assert all(len({p // (32 // blocks) for p in step}) == 1 for step in passes)  # one block a pass
    with pytest.raises(
        ValueError, match=r"block_size=12 does not divide .* valid: 0 \(the checkpoint's, 4\)"
    ):
        spec.build(parse_params(spec, {"block_size": "12"}))


class TracingPolicy(ChunkPolicy):
    def act(self, observations):
        batch = super().act(observations)
        return ChunkBatch(batch.actions, batch.action_tokens, trace=[{"committed": [[0], [1, 2]]}])


def test_traces_are_written_per_chunk_only_when_asked(tmp_path):
    run(fake_resolved(TracingPolicy(chunk=2), episodes=2, succeed_at=5), tmp_path / "plain")
    assert not (tmp_path / "plain" / TRACES).exists()
    out = tmp_path / "traced"
    run(fake_resolved(TracingPolicy(chunk=2), episodes=2, succeed_at=5), out, traces=True)
    run_dir = RunDir(out)
    rows, traces = run_dir.read_episodes(), run_dir.read_traces()
    assert len(traces) == rows["chunks"].sum() == 6
    first = traces.iloc[0]
    assert first["committed"] == [[0], [1, 2]] and first["chunk"] == 0 and first["step"] == 0
    assert traces.iloc[1]["step"] == 2  # env steps executed before that chunk
    assert set(traces["policy_config_id"]) == {"fakeconfig01"} and set(traces["run_id"]) == set(
        rows["run_id"]
    )
    assert json.loads((out / "manifest.json").read_text())["traces"] is True


def test_a_retraced_episode_keeps_its_latest_attempt_and_a_cut_line_is_dropped(tmp_path):
    out = tmp_path / "run"
    run(fake_resolved(TracingPolicy(chunk=2), episodes=1, succeed_at=3), out, traces=True)
    run_dir = RunDir(out)
    old = run_dir.read_traces().iloc[0].to_dict()
    run_dir.append_traces([old | {"started_at": "9999-01-01T00:00:00+00:00", "committed": [[7]]}])
    with open(out / TRACES, "a") as fh:
        fh.write('{"run_id": "cut sho')  # killed mid-write
    traces = run_dir.read_traces()
    assert len(traces) == 1 and traces.iloc[0]["committed"] == [[7]]


# ---------------------------------------------------------------- the real sweep


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    return real_sweep(tmp_path_factory)


def test_a_real_sweep_resumes_and_its_rows_carry_each_grid_point(sweep):
    assert sweep.executed_before_interrupt == INTERRUPT_AFTER and sweep.resume_exit == 0
    rows = RunDir(sweep.path).read_episodes()
    assert len(rows) == 2 * 2 * 2 and rows["run_id"].nunique() == 1 and rows["failure_reason"].isna().all()
    params = rows["policy_params"].map(json.loads)
    assert sorted(params.map(lambda p: p["block_size"]).value_counts().items()) == [(4, 4), (8, 4)]
    assert rows.groupby("policy_config_id")["policy_params"].nunique().eq(1).all()
    assert rows["policy_config_id"].nunique() == 2
    nfe = rows.groupby(params.map(lambda p: p["block_size"]))["nfe_per_chunk"].mean()
    assert nfe[8] < nfe[4]  # bigger blocks, fewer passes
    manifest = json.loads((sweep.path / "manifest.json").read_text())
    assert len(manifest["resumed_at"]) == 1 and manifest["status"] == "finished"
    fields = [p["checkpoint_fields"] for p in manifest["policies"]]
    assert all(f["recipe"] == "distill" and f["noise_schedule"] == "frontier" for f in fields)
    assert all(f["block_size"] == 4 and f["action_tokens"] == 32 for f in fields)


def test_the_real_sweeps_traces_cover_every_chunk_and_forward_pass(sweep):
    run_dir = RunDir(sweep.path)
    rows, traces = run_dir.read_episodes(), run_dir.read_traces()
    per_episode = traces.groupby(["policy_config_id", "task", "episode_index"])
    for row in rows.itertuples():
        chunks = per_episode.get_group((row.policy_config_id, row.task, row.episode_index))
        assert len(chunks) == row.chunks
        assert sum(len(c) for c in chunks["committed"]) == row.nfe_total  # one entry per pass
        for passes in chunks["committed"]:
            assert sorted(p for step in passes for p in step) == list(range(32))


def test_resuming_a_finished_sweep_runs_nothing_and_another_grid_is_refused(sweep, cli, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(sweep.path, copy)
    before = RunDir(copy).read_episodes()
    code, _, err = cli("sweep", *SWEEP_ARGS, "--out", str(copy), "--resume")
    assert code == 0 and "8 episode(s) already recorded, 0 to run" in err
    assert len(RunDir(copy).read_episodes()) == len(before)
    args = [a if a != "block_size=4,8" else "block_size=4,16" for a in SWEEP_ARGS]
    code, _, err = cli("sweep", *args, "--out", str(copy), "--resume")
    assert code == 2 and "belongs to a different config" in err


@pytest.mark.usefixtures("installed_plugin")  # a sweep of a simulator-free plugin suite
def test_a_sweeps_summary_names_each_point_by_the_label_its_rows_hold(cli, tmp_path):
    out = tmp_path / "sweep"
    code, stdout, _ = cli(
        "sweep", "--suite", "line/walk", "--policy", "constant", "--grid", "value=0.5,1.0",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0
    labels = set(RunDir(out).read_episodes()["config_label"])
    assert labels == {"constant (value=0.5)", "constant (value=1)"}
    for label in labels:
        assert label in stdout
    assert "constant value=" not in stdout  # the sweep's own `name k=v` format is gone
    code, shown, _ = cli("show", str(out))
    assert code == 0 and all(label in shown for label in labels)
