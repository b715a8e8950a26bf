"""The `playback` policy on real Meta-World episodes: played back on the episodes they were
recorded on, they end as recorded (same success, same steps); an episode it holds no
recording of, or one from another start, fails naming why."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("metaworld")

from policies.base import EpisodeContext
from policies.playback import PlaybackParams, PlaybackPolicy

pytestmark = pytest.mark.metaworld


TASKS = "reach-v3,drawer-close-v3"


@pytest.fixture(scope="module")
def evaluation_demos(tmp_path_factory):
    """The scripted expert's episodes 0-1 of two MT10 tasks, on the evaluation's layouts."""
    from harness.cli import main

    out = tmp_path_factory.mktemp("demos") / "eval"
    argv = [
        "collect",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        TASKS,
        "--policy",
        "scripted",
        "--split",
        "eval",
    ]
    assert main([*argv, "--episodes-per-task", "2", "--out", str(out), "--quiet"]) == 0
    return out


def _run(cli, demos, out) -> pd.DataFrame:
    code, _, err = cli(
        "run", "--suite", "metaworld/mt10", "--tasks", TASKS, "--episodes-per-task", "3",
        "--policy", f"playback:demos={demos},chunk_length=5", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 1, err  # some episodes fail (below)
    return pd.read_parquet(out / "episodes.parquet").set_index(["task", "episode_index"])


def test_played_back_demonstrations_end_as_they_were_recorded(cli, evaluation_demos, demos, tmp_path):
    recorded = pd.read_parquet(evaluation_demos / "steps.parquet")
    rows = _run(cli, evaluation_demos, tmp_path / "run")
    for (task, index), steps in recorded.groupby(["task", "episode_index"]).size().items():
        assert rows.loc[(task, index), "success"] and rows.loc[(task, index), "steps"] == steps
        assert rows.loc[(task, index), "nfe_total"] == 0
    for task in TASKS.split(","):  # episode 2 was never recorded
        reason = rows.loc[(task, 2), "failure_reason"]
        assert (
            f"holds no episode 2 of task {task}" in reason and "only successful episodes are kept" in reason
        )
    # the train split's demonstrations started elsewhere: every episode fails, saying so
    rows = _run(cli, demos, tmp_path / "train")
    assert not rows.success.any()
    assert rows.failure_reason.str.contains("was recorded with seed").sum() == 4


def test_a_playback_from_another_start_is_refused_and_sign_binarises_the_gripper(demos):
    recorded = pd.read_parquet(demos / "steps.parquet")
    first = recorded[(recorded.task == "reach-v3") & (recorded.episode_index == 0)]
    policy = PlaybackPolicy(PlaybackParams(demos=str(demos), chunk_length=len(first) + 3, gripper="sign"))
    import gymnasium as gym

    box = gym.spaces.Box(-1, 1, (4,), np.float32)
    context = EpisodeContext(
        "metaworld/mt10", "reach-v3", "reach", box, box, 500, 0, int(first.seed.iloc[0]), 0
    )
    policy.reset([context])
    chunk = policy.act([None]).actions[0]
    actions = np.stack(first.action.to_numpy())
    np.testing.assert_array_equal(chunk[: len(first), :3], actions[:, :3])
    np.testing.assert_array_equal(chunk[: len(first), 3], np.where(actions[:, 3] < 0, -1.0, 1.0))
    hold = chunk[len(first) :]
    assert (hold[:, :3] == 0).all() and (
        hold[:, 3] == chunk[len(first) - 1, 3]
    ).all()  # holds still after the end
    with pytest.raises(ValueError, match=r"was recorded with seed .* this one has seed 12345"):
        policy.reset([context.__class__(**{**context.__dict__, "seed": 12345})])
    with pytest.raises(ValueError, match="not a demonstrations folder"):
        PlaybackPolicy(PlaybackParams(demos=str(demos / "missing")))
