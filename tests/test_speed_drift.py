"""Calibration drift: a run whose machine load changed between its start and
end is flagged in its manifest, and `show`, `leaderboard` and `gate` say one line about it."""

from __future__ import annotations

import copy
import json

import pytest

import harness.run.manifest as manifest_module
from harness.run.manifest import record_end_calibration
from results.leaderboard import leaderboards
from results.runs import CALIBRATION_DRIFT_TOLERANCE, calibration_drift, load_run, speed_warning
from tests.test_leaderboard import BIDI, FAST, MANIFEST, episodes, write_run


def calibrated(start: float, end: float | None = None) -> dict:
    m = copy.deepcopy(MANIFEST)
    m["calibration"] = {
        "workload": {"name": "tiny-attention-block", "version": 1},
        "torch_threads": 1,
        "start": {"passes_per_s": start},
        "end": {"passes_per_s": end} if end else None,
    }
    return m


def drifted_and_steady(tmp_path, **kw):
    """Two run folders: one whose calibration halved during the run, one that held."""
    drifted = write_run(
        tmp_path / "busy",
        episodes("bidirectional", BIDI, "bidi000001", [1, 1], **kw),
        calibrated(10_355.0, 5_192.0),
    )
    steady = write_run(
        tmp_path / "idle",
        episodes("fast_dvla", FAST, "fast000001", [1, 0], **kw),
        calibrated(10_000.0, 9_900.0),
    )
    return drifted, steady


@pytest.mark.parametrize(
    ("end", "reliable"),
    [(10_000.0, True), (8_000.0, True), (12_400.0, True), (5_192.0, False), (13_000.0, False)],
)
def test_the_end_of_a_run_flags_drift_beyond_the_tolerance(monkeypatch, end, reliable):
    assert CALIBRATION_DRIFT_TOLERANCE == 0.25
    monkeypatch.setattr(manifest_module, "measure_calibration", lambda: {"passes_per_s": end})
    m = calibrated(10_000.0)
    record_end_calibration(m, "finished")
    assert m["calibration"]["drift"] == pytest.approx(end / 10_000.0 - 1)
    assert m["speed_reliable"] is reliable
    assert ("speed_warning" in m) is not reliable
    if not reliable:
        assert f"moved {end / 10_000.0 - 1:+.0%}" in m["speed_warning"]
        assert "the machine's load changed during the run" in speed_warning(m)


def test_an_interrupted_run_is_not_judged_and_old_manifests_are_judged_from_their_calibration(monkeypatch):
    monkeypatch.setattr(manifest_module, "measure_calibration", lambda: {"passes_per_s": 1.0})
    m = calibrated(10_355.0)
    record_end_calibration(m, "interrupted")
    assert "speed_reliable" not in m and speed_warning(m) == ""
    old = calibrated(10_355.0, 5_192.0)  # a run written before the flag existed
    assert calibration_drift(old) == pytest.approx(-0.4986, abs=1e-4)
    assert "moved -50% between the run's start and end (10,355 -> 5,192 passes/s" in speed_warning(old)
    assert speed_warning(MANIFEST) == ""  # no calibration: nothing to say


def test_show_and_leaderboard_warn_once_about_a_drifted_run(cli, tmp_path):
    drifted, steady = drifted_and_steady(tmp_path)
    code, out, _ = cli("show", str(drifted))
    lines = [line for line in out.splitlines() if line.startswith("warning:")]
    assert code == 0 and len(lines) == 1 and "speed figures of this run are unreliable" in lines[0]
    code, out, _ = cli("show", str(steady))
    assert code == 0 and "warning:" not in out
    (board,) = leaderboards([load_run(drifted), load_run(steady)])
    flagged = [w for w in board.warnings if "speed figures unreliable" in w]
    assert len(flagged) == 1 and flagged[0].startswith(f"{drifted}: ")
    code, _, err = cli("leaderboard", str(drifted), str(steady))
    assert code == 0 and err.count("speed figures unreliable") == 1  # warnings go to stderr


def test_the_flag_written_in_a_manifest_is_what_counts(tmp_path):
    m = calibrated(10_000.0, 10_000.0) | {"speed_reliable": False, "speed_warning": "probe saw a load"}
    assert speed_warning(m) == "probe saw a load"
    m = calibrated(10_000.0, 2_000.0) | {"speed_reliable": True}
    assert speed_warning(m) == ""
    path = write_run(
        tmp_path / "r", episodes("bidirectional", BIDI, "bidi000001", [1]), calibrated(9_000.0, 3_000.0)
    )
    assert json.loads((path / "manifest.json").read_text())["calibration"]["start"]["passes_per_s"] == 9_000.0
    assert "moved -67%" in load_run(path).speed_warning


def test_paper_table_and_html_report_warn_about_a_drifted_run_as_leaderboard_does(cli, tmp_path):
    # a suite with a published table to lay out, so paper-table has something to show
    drifted, steady = drifted_and_steady(tmp_path, suite="libero/spatial:obs=upstream")
    _, _, board_err = cli("leaderboard", str(drifted), str(steady))
    (want,) = [line for line in board_err.splitlines() if "speed figures unreliable" in line]
    assert want.endswith("the machine's load changed during the run")
    for argv in (["paper-table"], ["html", "--out", str(tmp_path / "report")]):
        code, _, err = cli("report", *argv, str(drifted), str(steady))
        assert code == 0, err
        assert [line for line in err.splitlines() if "speed figures unreliable" in line] == [want], argv
    page = (tmp_path / "report" / "index.html").read_text()
    assert "speed figures unreliable" in page and "moved -50%" in page


def test_a_drifted_run_marks_its_rows_and_a_steady_one_marks_them_reliable(monkeypatch, tmp_path):
    import torch  # noqa: F401  runs are calibrated only when their policies loaded torch

    from harness.run.runner import run
    from results.store import RunDir
    from tests.fakes import ChunkPolicy, fake_resolved

    for name, speeds, want in (("busy", [10_000.0, 5_000.0], False), ("idle", [10_000.0, 9_800.0], True)):
        readings = iter(speeds)
        monkeypatch.setattr(
            manifest_module, "measure_calibration", lambda r=readings: {"passes_per_s": next(r)}
        )
        run(fake_resolved(ChunkPolicy(chunk=2), episodes=3), tmp_path / name)
        rows = RunDir(tmp_path / name).read_episodes()
        assert len(rows) == 3 and rows["speed_reliable"].tolist() == [want] * 3
        assert RunDir(tmp_path / name).read_manifest()["speed_reliable"] is want
