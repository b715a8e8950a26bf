"""Published rows say where their numbers come from, and reports print it beside them."""

from __future__ import annotations

import re

import pytest

from results.paper_table import paper_blocks, paper_table
from results.published import CALVIN, FAST_DVLA, LIBERO, SIMPLERENV, TABLES
from results.runs import load_run
from tests.test_leaderboard import BIDI, FAST, episodes, write_run


@pytest.mark.parametrize("table", TABLES, ids=lambda t: t.name)
def test_every_published_row_names_its_paper_table_and_row(table):
    assert re.fullmatch(rf"{re.escape(FAST_DVLA)}, Table \d \(.+\)", table.source)
    for row in table.rows:
        assert row.source.startswith(f"{table.source}, row '"), row
        assert set(row.values) == set(table.columns)
    assert "swap" not in table.note and "not stated" not in table.note  # no transcription doubts
    assert len({r.source for r in table.rows}) == len(table.rows)  # each row its own


def test_the_rows_are_the_papers_tables():
    """Spot checks against Tables 1, 2 and 4 as printed: column order (Table 1 prints
    Spatial, Goal, Object, Long), and the rows each table has."""
    assert LIBERO.columns == ("Spatial", "Goal", "Object", "Long", "Avg")
    dream = LIBERO.rows[0]
    assert (dream.values["Goal"], dream.values["Object"]) == (92.0, 88.0)
    assert [r.speedup for r in CALVIN.rows] == [1.0, 2.0, 1.9, 2.8]
    assert [(r.values["Avg"], r.tokens_per_s) for r in SIMPLERENV.rows] == [
        (51.0, 100.1),
        (41.7, 214.2),
        (55.2, 226.4),
        (59.3, 366.4),
    ]


def test_paper_table_prints_each_published_rows_own_source(tmp_path):
    rows = [
        r | {"suite": "libero/spatial:obs=upstream"} for r in episodes("bidirectional", BIDI, "b1", [1, 0])
    ]
    rows += [r | {"suite": "libero/spatial:obs=upstream"} for r in episodes("fast_dvla", FAST, "f1", [1, 1])]
    block, paper = paper_blocks(paper_table([load_run(write_run(tmp_path / "r", rows))]))
    assert [r[-1].text for r in paper.rows] == [f"published: {p.source}" for p in LIBERO.rows]
    assert not any("swap" in n for n in block.notes + paper.notes)


def test_every_libero_pro_row_names_its_source_table_and_row():
    from results.published import LIBERO_PRO, LIBERO_PRO_ROWS, PRO_PERTURBATIONS

    for row in LIBERO_PRO_ROWS:
        assert row.source.startswith(f"{LIBERO_PRO}, README of github.com/Zxy-MLlab/LIBERO-PRO (commit ")
        assert f", row '{row.method}', LIBERO-" in row.source and row.kind == "published"
        assert set(row.values) <= {"standard", *PRO_PERTURBATIONS}
        assert all(v is None or 0 <= v <= 100 for v in row.values.values())
    assert len({r.source for r in LIBERO_PRO_ROWS}) == len(LIBERO_PRO_ROWS)


def test_the_libero_pro_rows_are_the_readmes_tables():
    """Spot checks against the README as printed (fractions there, % here)."""
    from results.published import LIBERO_PRO_LEADERBOARD, LIBERO_PRO_MOTIVATION, libero_pro_rows

    pi05_goal = next(r for r in LIBERO_PRO_LEADERBOARD if r.method == "Pi0.5" and r.suite == "goal")
    assert pi05_goal.values == {"object": 97.0, "swap": 38.0, "lan": 97.0, "task": 0.0, "env": 46.0}
    nora_10 = next(r for r in LIBERO_PRO_LEADERBOARD if r.method == "NORA" and r.suite == "10")
    assert nora_10.values["env"] is None and nora_10.values["lan"] == 74.0
    univla = next(r for r in LIBERO_PRO_MOTIVATION if r.method == "UniVLA" and r.suite == "10")
    assert univla.values == {"standard": 61.0, "task": 0.0, "swap": 0.0}
    assert len(libero_pro_rows("libero/spatial:seeding=openvla")) == 4 + 6
    assert libero_pro_rows("libero/90") == () and libero_pro_rows("plugin/spatial:perturb=swap") == ()
