"""Demonstrations through the ordinary episode loop, on layouts disjoint from evaluation."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq

from adapters.registry import load_suite


def test_collect_keeps_successful_episodes_from_the_train_split(cli, tmp_path):
    out = tmp_path / "demos"
    code, stdout, _ = cli(
        "collect",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        "reach-v3,drawer-close-v3",
        "--policy",
        "scripted",
        "--episodes-per-task",
        "2",
        "--out",
        str(out),
        "--quiet",
    )
    assert code == 0 and "2 / 2" in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["split"] == "train" and manifest["episodes_kept"] == {"reach-v3": 2, "drawer-close-v3": 2}
    assert manifest["observation_dim"] == 39 and manifest["action_dim"] == 4
    df = pq.read_table(out / "steps.parquet").to_pandas()
    assert df["episode_id"].nunique() == 4 and len(df) == manifest["steps"]
    assert (df.groupby("episode_id")["step"].min() == 0).all()
    actions = np.stack(df["action"].to_numpy())
    assert actions.min() >= -1.0 and actions.max() <= 1.0  # the expert's own go beyond; the env clips
    assert (np.abs(actions[:, :3]) == 1.0).any()  # saturated steps are kept at the bound
    eval_seeds = {t.episodes[0].seed for t in load_suite("metaworld/mt10").tasks}
    assert not set(df["seed"]) & eval_seeds  # never an evaluation layout
    assert not (tmp_path / "demos.tmp").exists()


def test_collect_refuses_to_overwrite_and_saves_nothing_without_successes(cli, tmp_path):
    out = tmp_path / "demos"
    args = [
        "collect",
        "--suite",
        "metaworld/mt1/reach-v3",
        "--episodes-per-task",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    assert cli(*args, "--policy", "scripted")[0] == 0
    code, _, err = cli(*args, "--policy", "scripted")
    assert code == 2 and "pass --overwrite" in err
    empty = tmp_path / "none"
    code, _, err = cli(
        "collect",
        "--suite",
        "metaworld/mt1/pick-place-v3",
        "--episodes-per-task",
        "1",
        "--policy",
        "random",
        "--out",
        str(empty),
        "--quiet",
    )
    assert code == 2 and "no episode succeeded" in err and not empty.exists()
