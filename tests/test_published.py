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
    (block,) = paper_blocks(paper_table([load_run(write_run(tmp_path / "r", rows))]))
    published = block.rows[block.published_from :]
    assert [r[-1].text for r in published] == [f"published: {p.source}" for p in LIBERO.rows]
    assert not any("swap" in n for n in block.notes)
