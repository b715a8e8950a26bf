"""Rollout videos (harness/episode/video.py): off by default, a frame after the reset and
after every step, held steps marked under an inference latency, failures-only keeps
only what failed, and rows identical with and without video (timings aside) on real
Meta-World episodes; `report html` links the videos."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from adapters.base import EpisodeSpec
from harness.episode.latency import LatencyPlan, parse_latency
from harness.episode.loop import run_episode
from harness.episode.plan import ExecutionPlan
from harness.episode.timed import TimedPolicy
from harness.episode.video import VideoPlan, parse_video, video_path
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS
from tests.fakes import CountdownEnv, context
from tests.test_latency import HZ, PassingPolicy

SIZE = 32


class FilmedEnv(CountdownEnv):
    """The fake env with a camera: frame t is grey level 4 t (a step counter to read back)."""

    def video_frame(self) -> np.ndarray:
        return np.full((SIZE, SIZE, 3), min(255, 4 * self.t), np.uint8)


def frames(data: bytes, tmp_path: Path) -> list[np.ndarray]:
    import imageio_ffmpeg

    path = tmp_path / "v.mp4"
    path.write_bytes(data)
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    return [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]


def red_border(frame: np.ndarray) -> bool:
    r, g, b = (int(v) for v in frame[1, SIZE // 2])
    return r > 150 and g < 90 and b < 90


def filmed(video: VideoPlan | None, mode: str = "none", succeed_at: int | None = None, index: int = 0):
    env = FilmedEnv(succeed_at)
    latency = parse_latency(mode)
    plan = ExecutionPlan(
        latency=None if latency.kind == "none" else LatencyPlan(latency, "sync", HZ), video=video
    )
    timed = TimedPolicy(PassingPolicy(), "fake")
    try:
        return run_episode(env, timed, context(12), EpisodeSpec(index, 1), plan), env
    finally:
        timed.close_counter()


def test_a_recorded_episode_has_a_frame_per_step_and_its_holds_marked(tmp_path):
    out, env = filmed(VideoPlan(episodes=1), "passes:100")  # 2 passes x 100 ms at 10 Hz: holds
    assert out.hold_steps > 0 and out.video_mp4 is not None
    shown = frames(out.video_mp4, tmp_path)
    assert len(shown) == out.steps + 1  # the reset's frame, then one per step
    centre = [int(f[SIZE // 2, SIZE // 2, 0]) for f in shown]
    assert all(abs(c - min(255, 4 * t)) <= 6 for t, c in enumerate(centre))  # in step order
    held = [t for t, a in enumerate(env.actions, start=1) if a[0] == 0]  # the steps that held
    assert [t for t, f in enumerate(shown) if red_border(f)] == held


def test_no_video_unless_asked_and_failures_keeps_only_what_failed(tmp_path, monkeypatch):
    import tempfile

    scratch = tmp_path / "scratch"  # where the encoder writes before the run's writer takes it
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    out, _ = filmed(None)
    assert out.video_mp4 is None
    out, _ = filmed(VideoPlan(episodes=1), index=1)  # only the first episode of a task
    assert out.video_mp4 is None
    out, _ = filmed(VideoPlan(failures=True), succeed_at=3)
    assert out.success and out.video_mp4 is None
    out, _ = filmed(VideoPlan(failures=True))
    assert not out.success and len(frames(out.video_mp4, tmp_path)) == out.steps + 1
    assert list(scratch.iterdir()) == []  # no temporary left behind, kept or dropped


def test_the_video_flag_and_its_paths():
    assert parse_video("3") == VideoPlan(episodes=3) and parse_video("failures") == VideoPlan(failures=True)
    for bad in ("0", "-1", "some", ""):
        with pytest.raises(ValueError, match="--video"):
            parse_video(bad)
    assert video_path("abc123", "pick up/the bowl", 7) == "videos/abc123/pick_up_the_bowl/episode-007.mp4"


RUN = [
    "run",
    "--suite",
    "metaworld/mt1/push-v3",
    "--policy",
    "scripted",
    "--episodes-per-task",
    "2",
    "--quiet",
]


@pytest.fixture(scope="module")
def twin_runs(tmp_path_factory):
    """The same two real Meta-World episodes, without and with video."""
    from harness.cli import main

    root = tmp_path_factory.mktemp("video")
    assert main([*RUN, "--out", str(root / "plain")]) == 0
    assert main([*RUN, "--video", "2", "--out", str(root / "filmed")]) == 0
    return root / "plain", root / "filmed"


@pytest.mark.metaworld
def test_rows_are_identical_with_and_without_video(twin_runs, tmp_path):
    plain, filmed_run = (pd.read_parquet(p / "episodes.parquet") for p in twin_runs)
    skip = TIMING_COLUMNS | PROVENANCE_COLUMNS | {"video", "overhead_s"}
    kept = [c for c in plain.columns if c not in skip]
    pd.testing.assert_frame_equal(plain[kept], filmed_run[kept])
    assert plain["video"].isna().all() and filmed_run["video"].notna().all()
    for row in filmed_run.itertuples():
        assert re.fullmatch(
            rf"videos/{row.policy_config_id}/push-v3/episode-00{row.episode_index}\.mp4", row.video
        )
        shown = frames((twin_runs[1] / row.video).read_bytes(), tmp_path)
        assert len(shown) == row.steps + 1 and shown[0].shape == (256, 256, 3)
        assert shown[0].std() > 10  # a rendered scene, not a blank frame


@pytest.mark.metaworld
def test_report_html_links_each_video(twin_runs, tmp_path, cli):
    out = tmp_path / "report"
    code, _, err = cli("report", "html", str(twin_runs[1]), "--out", str(out))
    assert code == 0, err
    page = (out / "index.html").read_text()
    links = re.findall(r"<a href='([^']+\.mp4)'>", page)
    assert len(links) == 2 and "Rollout videos" in page
    assert all((out / link).resolve().is_file() for link in links)


@pytest.mark.metaworld
def test_a_bad_video_flag_is_refused_before_anything_is_written(cli, tmp_path):
    out = tmp_path / "r"
    code, _, err = cli(*RUN[:-1], "--video", "sometimes", "--out", str(out))
    assert code == 2 and "--video 'sometimes'" in err and not out.exists()


def test_an_env_without_a_camera_is_named():
    from harness.episode.video import VideoUnavailable, check_frames

    check_frames([FilmedEnv(None)])
    with pytest.raises(VideoUnavailable, match="renders no video frames"):
        check_frames([FilmedEnv(None), CountdownEnv(None)])


def test_a_version_4_table_reads_with_no_video(tmp_path):
    import pyarrow.parquet as pq

    from results.schema import SCHEMA_VERSION_KEY
    from results.store import read_table, rows_to_table
    from tests.test_leaderboard import row

    table = rows_to_table([row()]).drop_columns(["video"])
    old = table.replace_schema_metadata({SCHEMA_VERSION_KEY: b"4"})
    pq.write_table(old, tmp_path / "e.parquet")
    read = read_table(tmp_path / "e.parquet")
    assert read.column("video").null_count == 1 and "video" in read.column_names


def test_a_run_folders_videos_are_the_harness_own_for_overwrite(tmp_path):
    from results.store import RunDir

    run_dir = RunDir(tmp_path)
    run_dir.write_video("videos/cfg/task/episode-000.mp4", b"mp4")
    assert (tmp_path / "videos/cfg/task/episode-000.mp4").read_bytes() == b"mp4"
    assert run_dir.foreign_files() == []  # --overwrite may replace the folder
    (tmp_path / "notes").mkdir()
    assert run_dir.foreign_files() == ["notes/"]
    run_dir.remove_recorded()
    assert not (tmp_path / "videos").exists() and (tmp_path / "notes").exists()
