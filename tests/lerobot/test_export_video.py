"""`dvla-harness export lerobot --video` read back by LeRobot's own reader, frame by frame, on
Meta-World's rendered camera, and set beside what LeRobot's own writer makes of the same
frames in video mode. Runs in the LeRobot environment (tox -e lerobot)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

pytest.importorskip("lerobot", reason="LeRobot's environment only: tox -e lerobot (docs/lerobot.md)")
pytest.importorskip("imageio_ffmpeg", reason="video mode's encoder: the `video` extra")

from harness.export_lerobot import ENV_STATE, STATE, export_demos
from tests.lerobot_demos import (
    INSTRUCTIONS,
    LENGTHS,
    demos,
    frame_number,
    lerobot_writes,
    marked,
    rendered_frames,
    smooth_frames,
)

KEY = "observation.images.corner"
FPS = 80  # Meta-World's control rate


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    root = tmp_path_factory.mktemp("video")
    frames = demos(root / "demos", ("corner",), marked(rendered_frames()))
    export_demos(root / "demos", root / "ds", "local/ds", video=True)
    return root, frames


def decoded_errors(dataset, images: np.ndarray) -> np.ndarray:
    """|decoded - source| per pixel and channel, frame by frame, as LeRobot's reader gives
    the frames (float CHW in [0, 1])."""
    out = []
    for i in range(len(dataset)):
        image = (dataset[i][KEY].numpy() * 255).round().astype(np.int16).transpose(1, 2, 0)
        assert frame_number(image) == i  # the frame of this index, not a neighbour
        out.append(np.abs(image - images[i]))
    return np.stack(out)


def test_lerobots_reader_decodes_every_frame_at_its_timestamp(exported):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.video_utils import get_video_info

    root, frames = exported
    dataset = LeRobotDataset("local/ds", root=root / "ds")  # its reader: 1e-4 s timestamp tolerance
    assert dataset.meta.video_keys == [KEY] and len(dataset) == sum(LENGTHS)
    starts = np.cumsum((0, *LENGTHS))
    for i in range(len(dataset)):
        frame = dataset[i]
        episode = int(np.searchsorted(starts, i, side="right") - 1)
        assert int(frame["episode_index"]) == episode and int(frame["frame_index"]) == i - starts[episode]
        assert float(frame["timestamp"]) == pytest.approx((i - starts[episode]) / FPS)
        assert frame["task"] == INSTRUCTIONS[episode % 2]
        assert np.array_equal(frame[ENV_STATE].numpy(), frames["state"][i])
        assert np.array_equal(frame[STATE].numpy(), frames["state"][i][:4])
        assert np.array_equal(frame["action"].numpy(), frames["action"][i])
        assert int(frame["harness.seed"]) == 1000 + episode
    errors = decoded_errors(dataset, frames["image"])
    per_frame = errors.mean(axis=(1, 2, 3))
    assert per_frame.max() < 4, per_frame  # AV1 at CRF 30, 4:2:0: ~2.4 levels of 255 (docs/lerobot.md)
    # the stream is what info.json says, as LeRobot's own probe reads it
    info = json.loads((root / "ds" / "meta" / "info.json").read_text())["features"][KEY]["info"]
    probed = get_video_info(root / "ds" / "videos" / KEY / "chunk-000" / "file-000.mp4")
    assert {k: info[k] for k in probed} == probed


def test_as_close_as_lerobots_own_video_writer_on_the_same_frames(exported, tmp_path):
    """LeRobot's writer (add_frame, save_episode, finalize, use_videos=True) on the same
    frames: the same episode timeline, the same statistics, and a decoded error no worse
    than its own by more than a tenth."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root, frames = exported
    features = json.loads((root / "ds" / "meta" / "info.json").read_text())["features"]
    features = {KEY: {k: v for k, v in features[KEY].items() if k != "info"}, "action": features["action"]}
    lerobot_writes(
        tmp_path / "theirs",
        features,
        lambda episode, i: {KEY: frames["image"][i], "action": frames["action"][i]},
        video=True,
    )
    ours_meta, their_meta = (
        pq.read_table(next((folder / "meta" / "episodes").rglob("*.parquet"))).to_pydict()
        for folder in (root / "ds", tmp_path / "theirs")
    )
    for column in (c for c in their_meta if c.startswith(f"videos/{KEY}/")):
        assert ours_meta[column] == pytest.approx(their_meta[column], abs=1e-9), column
    for stat in ("min", "max", "mean", "std", "q01", "q50", "q99"):
        column = f"stats/{KEY}/{stat}"
        np.testing.assert_allclose(
            ours_meta[column], their_meta[column], rtol=1e-5, atol=1e-6, err_msg=column
        )
    ours = decoded_errors(LeRobotDataset("local/ds", root=root / "ds"), frames["image"]).mean()
    their = decoded_errors(LeRobotDataset("local/theirs", root=tmp_path / "theirs"), frames["image"]).mean()
    assert ours <= 1.1 * their, (ours, their)


def test_episodes_split_over_files_read_back_from_each(tmp_path, monkeypatch):
    """A new file at every episode's start (as past 200 MB): each episode's chunk, file and
    timeline restart there, and LeRobot's reader finds every frame in its file."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    import harness.export_lerobot_video as video

    monkeypatch.setattr(video, "file_full", lambda path: True)
    frames = demos(tmp_path / "demos", ("corner",), smooth_frames())
    export_demos(tmp_path / "demos", tmp_path / "ds", "local/ds", video=True)
    episodes = pq.read_table(
        tmp_path / "ds" / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    ).to_pydict()
    assert episodes[f"videos/{KEY}/file_index"] == [0, 1, 2, 3]
    assert episodes[f"videos/{KEY}/from_timestamp"] == [0.0] * 4
    assert episodes[f"videos/{KEY}/to_timestamp"] == pytest.approx([n / FPS for n in LENGTHS])
    dataset = LeRobotDataset("local/ds", root=tmp_path / "ds")
    for i in range(len(dataset)):
        image = (dataset[i][KEY].numpy() * 255).round().astype(np.int16).transpose(1, 2, 0)
        assert frame_number(image) == i and np.abs(image - frames["image"][i]).mean() < 4
