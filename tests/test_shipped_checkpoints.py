"""The reference checkpoints this repository ships: small, loadable, and skilled."""

from __future__ import annotations

import pytest

from policies.checkpoint import load
from policies.dvla import SHIPPED
from results.store import RunDir

EXPECTED = {
    "bidirectional": "bidirectional",
    "fast_dvla": "block_causal",
    "block_diffusion": "block_causal",
    "autoregressive": "causal",
}


def test_shipped_checkpoints_load_with_their_provenance():
    files = {name: SHIPPED / f"metaworld-mt10-{name}.safetensors" for name in EXPECTED}
    assert sum(f.stat().st_size for f in files.values()) < 40 * 2**20
    for name, path in files.items():
        ckpt = load(path)
        assert ckpt.model.cfg.pattern == EXPECTED[name]
        assert ckpt.meta["data_sha256"] and ckpt.meta["recipe"]
    teacher, student = load(files["bidirectional"]), load(files["fast_dvla"])
    assert student.meta["recipe"] == "distill" and student.vocab == teacher.vocab


@pytest.mark.parametrize("policy", ["bidirectional", "fast_dvla"])
def test_shipped_policy_solves_easy_mt10_tasks_with_no_arguments(cli, tmp_path, policy):
    code, _, err = cli(
        "run",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        "door-open-v3,drawer-close-v3",
        "--episodes-per-task",
        "3",
        "--policy",
        policy,
        "--out",
        str(tmp_path / "r"),
        "--quiet",
    )
    assert code == 0, err
    per_task = RunDir(tmp_path / "r").read_episodes().groupby("task")["success"].sum()
    assert (per_task >= 2).all(), per_task.to_dict()
