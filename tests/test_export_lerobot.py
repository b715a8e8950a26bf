"""`dvla-harness export lerobot` in the main environment (no LeRobot): the v3 layout it
writes, LeRobot's statistics on their edge cases, and bad input refused with nothing
written. LeRobot's own reader reads the exports back in tests/lerobot/ (tox -e lerobot)."""

from __future__ import annotations

import json
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from harness.export_lerobot import column_stats, histogram_quantile, pooled_stats
from tests.lerobot_demos import LENGTHS, demos, frame_number, smooth_frames


def test_the_v3_layout_with_fps_from_the_suite_and_the_sidecar(cli, tmp_path):
    demos(tmp_path / "demos")
    code, out, err = cli("export", "lerobot", str(tmp_path / "demos"), "--out", str(tmp_path / "ds"))
    assert code == 0, err
    assert "4 episodes, 25 frames, 2 tasks at 80 fps" in out
    root = tmp_path / "ds"
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 80 and info["splits"] == {"train": "0:4"}
    assert info["features"]["observation.state"]["shape"] == [4]  # the manifest's proprio_dims
    assert info["features"]["observation.environment_state"]["shape"] == [39]
    data = pq.read_table(root / "data" / "chunk-000" / "file-000.parquet")
    assert data.column("episode_index").to_pylist() == [e for e, n in enumerate(LENGTHS) for _ in range(n)]
    assert data.column("index").to_pylist() == list(range(sum(LENGTHS)))
    episodes = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pydict()
    assert episodes["length"] == list(LENGTHS)
    assert episodes["dataset_to_index"] == np.cumsum(LENGTHS).tolist()
    sidecar = json.loads((root / "meta" / "dvla_harness.json").read_text())
    assert sidecar["source"]["suite"] == "metaworld/mt10" and sidecar["source"]["steps_sha256"] == "ab" * 32
    assert not (tmp_path / "ds.partial").exists()


def test_quantiles_follow_lerobots_histogram_on_ties_all_equal_and_tiny_columns():
    ramp = np.arange(101, dtype=np.float64)
    assert histogram_quantile(ramp, 0.5) == pytest.approx(50, abs=0.03)  # 5,000 bins over [0, 100]
    equal = np.full(10, 3.0, np.float32)
    # one value: every count sits in the first bin, so the target lands inside it
    assert histogram_quantile(equal, 0.01) == pytest.approx(3.0, abs=1e-6)
    ties = np.array([0.0, 0.0, 0.0, 1.0])
    assert histogram_quantile(ties, 0.5) == pytest.approx(-1e-10, abs=1e-12)  # the first edge: bin 0 holds it
    assert histogram_quantile(ties, 0.99) == pytest.approx(1.0, abs=1e-3)
    one = column_stats(np.array([[2.0, -1.0]]))  # a single frame: every quantile is the mean
    assert one["q01"].tolist() == one["q99"].tolist() == [2.0, -1.0] and one["std"].tolist() == [0.0, 0.0]


def test_pooled_statistics_are_the_whole_datasets_mean_and_std():
    rng = np.random.default_rng(0)
    parts = [rng.normal(size=(n, 3)) for n in (5, 1, 9)]
    pooled = pooled_stats([column_stats(p) for p in parts])
    whole = np.concatenate(parts)
    np.testing.assert_allclose(pooled["mean"], whole.mean(axis=0))
    np.testing.assert_allclose(pooled["std"], whole.std(axis=0))
    assert pooled["count"].tolist() == [15]
    np.testing.assert_allclose(pooled["min"], whole.min(axis=0))


def test_bad_sources_are_refused_with_nothing_written(cli, tmp_path):
    out = tmp_path / "ds"
    code, _, err = cli("export", "lerobot", str(tmp_path), "--out", str(out))
    assert code == 2 and "is not a demonstrations folder" in err and not out.exists()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "episodes.parquet").write_bytes(b"")
    code, _, err = cli("export", "lerobot", str(tmp_path / "run"), "--out", str(out))
    assert code == 2 and "is a run folder" in err and not out.exists()
    demos(tmp_path / "demos")
    out.mkdir()
    code, _, err = cli("export", "lerobot", str(tmp_path / "demos"), "--out", str(out))
    assert code == 2 and "exists" in err and not any(out.iterdir())
    code, _, err = cli(
        "export", "lerobot", str(tmp_path / "demos"), "--out", str(tmp_path / "x"), "--repo-id", "a b"
    )
    assert code == 2 and "--repo-id" in err and not (tmp_path / "x").exists()


def decoded(path) -> list[np.ndarray]:
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    width, height = next(reader)["size"]
    return [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]


def test_video_mode_writes_lerobots_video_layout(cli, tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    source = demos(tmp_path / "demos", ("corner",), smooth_frames())
    code, _, err = cli("export", "lerobot", str(tmp_path / "demos"), "--out", str(tmp_path / "ds"), "--video")
    assert code == 0, err
    root, key = tmp_path / "ds", "observation.images.corner"
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    feature = info["features"][key]
    assert feature["dtype"] == "video" and feature["shape"] == [64, 96, 3]
    assert {k: feature["info"][k] for k in ("video.codec", "video.pix_fmt", "video.fps", "video.g")} == {
        "video.codec": "av1",
        "video.pix_fmt": "yuv420p",
        "video.fps": 80,
        "video.g": 2,
    }
    # the parquet holds no image column: the frames live in the video only
    assert key not in pq.read_table(root / "data" / "chunk-000" / "file-000.parquet").column_names
    episodes = pq.read_table(root / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pydict()
    ends = np.cumsum(LENGTHS)
    assert episodes[f"videos/{key}/from_timestamp"] == pytest.approx((np.r_[0, ends[:-1]] / 80).tolist())
    assert episodes[f"videos/{key}/to_timestamp"] == pytest.approx((ends / 80).tolist())
    assert (
        episodes[f"videos/{key}/file_index"] == [0] * 4 and episodes[f"videos/{key}/chunk_index"] == [0] * 4
    )
    assert len(episodes[f"stats/{key}/mean"][0]) == 3  # per channel, from the frames before encoding
    frames = decoded(root / "videos" / key / "chunk-000" / "file-000.mp4")
    assert [frame_number(f) for f in frames] == list(range(sum(LENGTHS)))  # every frame, in order
    error = np.abs(np.stack(frames).astype(int) - source["image"]).mean(axis=(1, 2, 3))
    assert error.max() < 4, error  # lossy: a few levels of 255 (docs/lerobot.md)


def test_video_mode_refuses_what_it_cannot_encode(cli, tmp_path, monkeypatch):
    out = tmp_path / "ds"
    demos(tmp_path / "state")
    code, _, err = cli("export", "lerobot", str(tmp_path / "state"), "--out", str(out), "--video")
    assert code == 2 and "no camera images" in err and not out.exists()
    demos(tmp_path / "odd", ("corner",), [np.zeros((5, 6, 3), np.uint8)] * sum(LENGTHS))
    code, _, err = cli("export", "lerobot", str(tmp_path / "odd"), "--out", str(out), "--video")
    assert code == 2 and "even height and width" in err and not out.exists()
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # the `video` extra not installed
    demos(tmp_path / "camera", ("corner",), smooth_frames())
    code, _, err = cli("export", "lerobot", str(tmp_path / "camera"), "--out", str(out), "--video")
    assert code == 2 and '".[video]"' in err and not out.exists()


def test_an_episode_spec_without_an_initial_state_id_exports_minus_one(tmp_path):
    """LIBERO's fresh initial states have no id (null in steps.parquet): -1, not a cast NaN."""
    import pyarrow as pa

    from harness.export_lerobot import export_demos

    demos(tmp_path / "demos")
    steps = pq.read_table(tmp_path / "demos" / "steps.parquet")
    column = steps.schema.get_field_index("init_state_id")
    nulls = pa.nulls(steps.num_rows, steps.schema.field(column).type)
    pq.write_table(steps.set_column(column, "init_state_id", nulls), tmp_path / "demos" / "steps.parquet")
    export_demos(tmp_path / "demos", tmp_path / "ds", "local/ds")
    data = pq.read_table(tmp_path / "ds" / "data" / "chunk-000" / "file-000.parquet")
    assert set(data.column("harness.init_state_id").to_pylist()) == {-1}
    assert data.column("harness.seed").to_pylist()[0] == 1000
