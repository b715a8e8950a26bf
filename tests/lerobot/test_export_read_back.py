"""`dvla-harness export lerobot` read back by LeRobot's own reader (LeRobotDataset v3), frame
by frame, and its statistics against the ones LeRobot's own writer computes for the same
frames. Runs in the LeRobot environment (tox -e lerobot)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("lerobot", reason="LeRobot's environment only: tox -e lerobot (docs/lerobot.md)")

from harness.export_lerobot import ENV_STATE, STATE, export_demos
from tests.lerobot_demos import INSTRUCTIONS, LENGTHS, demos, lerobot_writes


@pytest.mark.parametrize("cameras", [(), ("corner",)])
def test_lerobots_reader_gives_back_every_frame(tmp_path, cameras):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    frames = demos(tmp_path / "demos", cameras)
    summary = export_demos(tmp_path / "demos", tmp_path / "ds", "local/ds")
    assert summary == {
        "codebase_version": "v3.0",
        "total_episodes": 4,
        "total_frames": sum(LENGTHS),
        "total_tasks": 2,
        "fps": 80,  # Meta-World's control rate
    }
    dataset = LeRobotDataset("local/ds", root=tmp_path / "ds")
    assert len(dataset) == sum(LENGTHS) and dataset.meta.total_episodes == 4 and dataset.fps == 80
    starts = np.cumsum((0, *LENGTHS))
    for i in range(len(dataset)):
        frame = dataset[i]
        episode = int(np.searchsorted(starts, i, side="right") - 1)
        assert int(frame["episode_index"]) == episode and int(frame["frame_index"]) == i - starts[episode]
        assert frame["task"] == INSTRUCTIONS[episode % 2]
        assert float(frame["timestamp"]) == pytest.approx((i - starts[episode]) / 80)
        assert np.array_equal(frame[ENV_STATE].numpy(), frames["state"][i])
        assert np.array_equal(frame[STATE].numpy(), frames["state"][i][:4])
        assert np.array_equal(frame["action"].numpy(), frames["action"][i])
        assert int(frame["harness.seed"]) == 1000 + episode and int(frame["harness.init_state_id"]) == episode
        if cameras:  # LeRobot gives images as float CHW in [0, 1]
            image = (frame["observation.images.corner"].numpy() * 255).round().astype(np.uint8)
            assert np.array_equal(image.transpose(1, 2, 0), frames["image"][i])
    sidecar = json.loads((tmp_path / "ds" / "meta" / "dvla_harness.json").read_text())
    assert sidecar["source"]["steps_sha256"] == "ab" * 32 and sidecar["source"]["suite"] == "metaworld/mt10"


def test_statistics_are_lerobots_own_for_the_same_frames(tmp_path):
    """The same frames written by LeRobot's writer (add_frame, save_episode, finalize):
    every statistic of every feature agrees, quantiles and single-frame episodes included."""

    frames = demos(tmp_path / "demos", ("corner",))
    export_demos(tmp_path / "demos", tmp_path / "ours", "local/ours")
    ours = json.loads((tmp_path / "ours" / "meta" / "info.json").read_text())["features"]
    features = {
        k: v
        for k, v in ours.items()
        if k not in ("timestamp", "frame_index", "episode_index", "index", "task_index")
    }

    def frame(episode: int, i: int) -> dict:
        return {
            STATE: frames["state"][i][:4],
            ENV_STATE: frames["state"][i],
            "observation.images.corner": frames["image"][i],
            "action": frames["action"][i],
            "harness.seed": np.array([1000 + episode]),
            "harness.init_state_id": np.array([episode]),
            "harness.episode_index": np.array([10 + episode]),
        }

    lerobot_writes(tmp_path / "theirs", features, frame)
    expected = json.loads((tmp_path / "theirs" / "meta" / "stats.json").read_text())
    got = json.loads((tmp_path / "ours" / "meta" / "stats.json").read_text())
    assert set(got) == set(expected)
    for feature, stats in expected.items():
        assert set(got[feature]) == set(stats), feature
        for key, value in stats.items():
            np.testing.assert_allclose(
                got[feature][key], value, rtol=1e-5, atol=1e-6, err_msg=f"{feature} {key}"
            )
