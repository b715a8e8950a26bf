"""Chain suites in every report: the CALVIN layout in `leaderboard` (terminal, Markdown,
CSV, HTML), `report paper-table` (published CALVIN rows beneath, labelled as another
benchmark) and `report html`, and `gate` paired on subtasks completed per chain. All from
hand-made rows written through results.store, so each number can be checked by hand."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pandas as pd
import pytest

from results.gate import gate
from results.leaderboard import leaderboards
from results.paper_table import NOT_CALVIN, paper_blocks, paper_table
from results.runs import load_run
from tests.test_gate import episodes as gate_episodes
from tests.test_gate import write_run as write_gate_run
from tests.test_leaderboard import BIDI, FAST, MANIFEST, row, write_run

SUITE = "chains/all"
# Ten chains per policy over two scenes: 1/5 .. 5/5 and the average length by hand.
TEACHER = [5, 5, 3, 0, 1, 5, 2, 4, 5, 0]  # reach 8, 7, 6, 5, 4 of 10; avg 3.0
STUDENT = [5, 5, 3, 1, 1, 5, 2, 4, 5, 1]  # reach 10, 7, 6, 5, 4; avg 3.2


def chain_rows(policy: str, params: str, config: str, lengths: list[int], tokens_per_s: float) -> list[dict]:
    out = []
    for i, n in enumerate(lengths):
        scene = "libero_goal" if i < 5 else "living_room_scene3"
        r = row(
            policy,
            params,
            config,
            suite=SUITE,
            task=scene,
            task_index=0 if i < 5 else 1,
            episode_index=i % 5,
            init_state_id=i % 5,
            success=n == 5,
            tokens_per_s=tokens_per_s,
            started_at=datetime(2026, 1, 1, tzinfo=UTC) + timedelta(seconds=i),
        )
        out.append(r | {"subtasks_completed": n, "chain_id": f"{scene}/{i % 5}"})
    return out


@pytest.fixture
def chain_run(tmp_path: Path) -> Path:
    manifest = MANIFEST | {"suite": MANIFEST["suite"] | {"name": SUITE, "tasks": ["libero_goal"]}}
    rows = chain_rows("bidirectional", BIDI, "bidi000001", TEACHER, 100.0)
    rows += chain_rows("fast_dvla", FAST, "fast000001", STUDENT, 250.0)
    return write_run(tmp_path / "chains", rows, manifest)


def test_the_leaderboard_of_a_chain_suite_is_calvins_table(chain_run):
    (board,) = leaderboards([load_run(chain_run)])
    assert board.is_chain
    headers, rows = board.cells()
    assert headers[1:9] == [
        "libero_goal avg len",
        "living_room_scene3 avg len",
        "1/5",
        "2/5",
        "3/5",
        "4/5",
        "5/5",
        "avg len (95%)",
    ]
    teacher, student = ([c.text for c in r] for r in rows)
    # teacher: libero_goal chains 5,5,3,0,1 -> 2.8; the tray chains 5,2,4,5,0 -> 3.2
    assert teacher[1].startswith("2.80 [") and teacher[2].startswith("3.20 [")
    assert teacher[3] == "80.0 [49, 94]" and teacher[7] == "40.0 [17, 69]"  # Wilson 8/10, 4/10
    assert teacher[8].startswith("3.00 [") and student[3].startswith("100.0 [")
    assert student[-1] == "2.50x"  # tokens/s over the teacher's, same machine
    frame = board.frame().set_index("policy")
    assert frame.loc["bidirectional", "reach_2"] == pytest.approx(0.7)
    assert frame.loc["fast_dvla", "avg_len"] == pytest.approx(3.2)
    assert frame.loc["bidirectional", "avg_len[living_room_scene3]"] == pytest.approx(3.2)
    low, high = frame.loc["bidirectional", ["avg_len_low", "avg_len_high"]]
    assert 0 <= low < 3.0 < high <= 5


def test_a_single_instruction_suite_keeps_its_success_columns(tmp_path):
    run = write_run(tmp_path / "r", [row()])
    (board,) = leaderboards([load_run(run)])
    headers, _ = board.cells()
    assert not board.is_chain and "success (Wilson 95%)" in headers and "1/5" not in headers


def test_paper_table_gives_chains_calvins_layout_with_published_rows_labelled(chain_run):
    table = paper_table([load_run(chain_run)])
    assert table.suites == () and len(table.chain_boards) == 1  # no LIBERO block to average into
    block, paper = paper_blocks(table)  # measured, then the published rows in their own section
    assert block.headers[:7] == ["method", "1/5", "2/5", "3/5", "4/5", "5/5", "avg len"]
    assert [r[0].text for r in block.rows] == ["bidirectional", "fast_dvla"]
    assert block.rows[1][7].text == "250" and block.rows[1][8].text == "2.50x"
    assert block.headers[7:9] == ["tokens/s (measured)", "speedup vs bidirectional (measured)"]
    assert paper.headers[7:9] == ["tokens/s (published)", "speedup vs UD-VLA (published)"]
    published = paper.rows
    assert published[0][0].text == "UD-VLA (published, CALVIN: not comparable)"
    assert [c.text for c in published[0][1:8]] == ["99.2", "96.8", "93.6", "90.4", "84.0", "4.64", "67.3"]
    assert any(NOT_CALVIN in n for n in block.notes)


def test_a_chain_suite_beside_libero_gets_its_own_table(chain_run, tmp_path):
    libero = [
        r | {"suite": "libero/spatial:obs=upstream"} for r in [row(), row("fast_dvla", FAST, "fast000001")]
    ]
    runs = [load_run(chain_run), load_run(write_run(tmp_path / "lib", libero))]
    table = paper_table(runs)
    assert table.suites == ("libero/spatial:obs=upstream",)
    titles = [b.title for b in paper_blocks(table)]
    assert titles == [
        "measured", "published: LIBERO", f"{SUITE} (CALVIN layout)", "published: CALVIN ABCD->D"
    ]  # fmt: skip
    fast = next(r for r in table.rows if r.label == "fast_dvla")
    assert list(fast.success) == ["libero/spatial:obs=upstream"]  # the chain suite is not averaged in


def test_leaderboard_and_reports_print_the_calvin_table(cli, chain_run, tmp_path):
    code, out, _ = cli("leaderboard", str(chain_run), "--format", "md")
    assert code == 0 and "| 1/5 | 2/5 | 3/5 | 4/5 | 5/5 | avg len (95%) |" in out
    code, out, _ = cli("report", "paper-table", str(chain_run))
    assert code == 0 and "chains/all (CALVIN layout)" in out and "not comparable" in out
    code, _, _ = cli("report", "html", str(chain_run), "--out", str(tmp_path / "report"))
    page = (tmp_path / "report" / "index.html").read_text()
    assert code == 0 and "CALVIN layout" in page and "80.0 [49, 94]" in page
    code, out, _ = cli("leaderboard", str(chain_run), "--format", "csv")
    assert code == 0 and "reach_5" in out.splitlines()[0]


def _chains(lengths: list[int], **kw) -> pd.DataFrame:
    df = gate_episodes({"libero_goal": [n == 5 for n in lengths]}, suite="chains/libero_goal", **kw)
    return df.assign(subtasks_completed=lengths)


def test_the_gate_catches_chains_that_stop_earlier_while_5_of_5_holds():
    base = [5, 5, 4, 4, 4, 4, 3, 3, 3, 2]
    shorter = [5, 5, 2, 2, 2, 2, 1, 1, 1, 0]  # same two full chains, 8 shorter
    result = gate(_chains(base), _chains(shorter), reference=None)
    _, overall = result.tasks
    assert overall.baseline_successes == overall.candidate_successes == 2  # 5/5 cannot see it
    assert (overall.length_drops, overall.length_gains) == (8, 0)
    assert overall.length_p == pytest.approx(1 / 256) and overall.alpha == pytest.approx(0.025)
    assert overall.baseline_length == pytest.approx(3.7) and overall.candidate_length == pytest.approx(2.1)
    assert not result.passed and any(
        "subtasks completed per chain 3.70 -> 2.10" in f for f in result.failures
    )


def test_the_gate_passes_chains_that_moved_by_chance_or_got_longer():
    base = [5, 4, 3, 2, 1, 0, 5, 4, 3, 2]
    noisy = [4, 5, 3, 2, 0, 1, 5, 3, 4, 2]  # 3 shorter, 3 longer
    assert gate(_chains(base), _chains(noisy), reference=None).passed
    assert gate(_chains(base), _chains([5] * 10), reference=None).passed
    plain = gate_episodes({"a": [True, False]})  # other suites carry no length test
    assert all(t.length_p is None for t in gate(plain, plain, reference=None).tasks)


def test_the_gate_cli_shows_the_chain_column(cli, tmp_path):
    base = write_gate_run(tmp_path / "base", _chains([5, 5, 4, 4, 4, 4, 3, 3, 3, 2]))
    cand = write_gate_run(tmp_path / "cand", _chains([5, 5, 2, 2, 2, 2, 1, 1, 1, 0]))
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 1
    assert "subtasks/chain" in out and "3.70 -> 2.10 (8/0" in out
    assert "chain length" in out and "subtasks completed per chain" in err
