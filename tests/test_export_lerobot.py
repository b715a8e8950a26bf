"""`dvla-harness export lerobot` in the main environment (no LeRobot): the v3 layout it
writes, LeRobot's statistics on their edge cases, and bad input refused with nothing
written. LeRobot's own reader reads the exports back in tests/lerobot/ (tox -e lerobot)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from harness.export_lerobot import column_stats, histogram_quantile, pooled_stats
from tests.lerobot_demos import LENGTHS, demos


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
