"""The generalization-gap table from hand-made rows: pairing, intervals, layout."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from results.generalization import (
    gap_tables,
    newcombe_drop,
    paired_drop,
    split_perturbation,
)
from results.summary import Success

BASE = "libero/spatial:seeding=openvla"


def _rows(suite: str, outcomes: list[bool], cid: str = "c1", tasks: int = 2) -> list[dict]:
    per = len(outcomes) // tasks
    return [
        {
            "suite": suite,
            "task": f"t{i // per}",
            "episode_index": i % per,
            "success": ok,
            "policy": "libero_scripted",
            "policy_config_id": cid,
        }
        for i, ok in enumerate(outcomes)
    ]


def test_suite_names_split_into_standard_and_perturbation():
    name = "libero/spatial:perturb=swap+lan,instruction={},seeding=openvla"
    assert split_perturbation(name.format("filename")) == (BASE, "swap+lan")
    assert split_perturbation(name.format("bddl")) == (BASE, "swap+lan (instruction=bddl)")
    assert split_perturbation(BASE) == (BASE, "standard")
    assert split_perturbation("libero/goal:perturb=env,instruction=filename") == ("libero/goal", "env")
    # the standard suite under the BDDL's words is another standard suite
    bddl = "libero/spatial:instruction=bddl,seeding=openvla"
    assert split_perturbation(bddl) == (bddl, "standard")
    # a name without the source: the BDDL's words under lan and task, the standard ones otherwise
    assert split_perturbation("libero/spatial:perturb=lan,seeding=openvla") == (
        BASE,
        "lan (instruction=bddl)",
    )
    assert split_perturbation("libero/goal:perturb=env") == ("libero/goal", "env")


def test_both_instruction_sources_pair_with_one_standard_run_and_only_filename_is_published():
    rows = _rows(BASE, [True] * 4)
    rows += _rows(
        "libero/spatial:perturb=lan,instruction=filename,seeding=openvla", [True, True, True, False]
    )
    rows += _rows("libero/spatial:perturb=lan,instruction=bddl,seeding=openvla", [True, False, False, False])
    (table,) = gap_tables(pd.DataFrame(rows))
    assert table.perturbations == ("lan", "lan (instruction=bddl)")
    (row,) = table.rows
    assert row.perturbed["lan"][1].drop == pytest.approx(0.25)
    assert row.perturbed["lan (instruction=bddl)"][1].drop == pytest.approx(0.75)
    headers, cells = table.cells()
    assert headers[2:4] == ["lan (Sem.)", "lan: drop (95%)"]
    published = [r for r in cells if "published" in r[0].text]
    assert published and all(r[4].text == "-" for r in published)  # no published bddl column


def test_matching_episodes_pair_and_count_discordant_pairs():
    standard = [True] * 8 + [False] * 2
    swap = [True, False, False, True, False, True, False, False, True, False]
    rows = _rows(BASE, standard) + _rows("libero/spatial:perturb=swap,seeding=openvla", swap)
    (table,) = gap_tables(pd.DataFrame(rows))
    assert table.suite == BASE and table.perturbations == ("swap",)
    (row,) = table.rows
    success, d = row.perturbed["swap"]
    assert row.standard == Success(8, 10) and success == Success(4, 10)
    assert d.paired and d.drop == pytest.approx(0.4)
    assert (d.standard_only, d.perturbed_only) == (5, 1)  # keys 1, 2, 4, 6, 7 against key 8
    assert d.low < 0.4 < d.high
    headers, cells = table.cells()
    assert headers[2:] == ["swap (Pos.)", "swap: drop (95%)"]
    assert "paired, 5/1 discordant" in cells[0][3].text and cells[0][3].text.startswith("+40.0 pts")


def test_episodes_that_do_not_match_are_unpaired_with_newcombes_interval():
    rows = _rows(BASE, [True] * 10) + _rows("libero/spatial:perturb=lan", [True, False] * 3, tasks=2)
    rows += _rows("libero/spatial:perturb=object", [False] * 10)
    tables = gap_tables(pd.DataFrame(rows))
    assert [t.suite for t in tables] == [
        "libero/spatial"
    ]  # other options, another suite; BASE has no perturbed rows
    # other tasks: neither side's keys contain the other's
    other_tasks = [
        dict(r, task="t" + r["task"]) for r in _rows(f"{BASE},perturb=object", [False] * 6, tasks=2)
    ]
    object_only = gap_tables(pd.DataFrame(_rows(BASE, [True] * 10) + other_tasks))
    (row,) = object_only[0].rows
    _, d = row.perturbed["object"]
    assert not d.paired and d.drop == pytest.approx(1.0)
    expected = newcombe_drop(Success(10, 10), Success(0, 6))
    assert (d.low, d.high) == (expected.low, expected.high)
    assert "(unpaired)" in object_only[0].cells()[1][0][3].text


def test_a_perturbation_run_on_fewer_starts_pairs_on_the_starts_both_ran():
    """The usual layout (the standard suite at 50 a task, a perturbation at 2): the drop
    pairs on the perturbed run's starts, where the standard run scored otherwise than on
    all of its own, and the success column keeps every standard episode."""
    standard = [True, True, False, False, False] * 2  # per task: starts 0-1 solved, 2-4 not
    perturbed = [True, False, False] * 2  # per task: starts 0-2; start 1 lost
    rows = _rows(BASE, standard) + _rows(f"{BASE},perturb=swap", perturbed)
    (table,) = gap_tables(pd.DataFrame(rows))
    (row,) = table.rows
    success, d = row.perturbed["swap"]
    assert row.standard == Success(4, 10) and success == Success(2, 6)
    # on the shared starts the standard run solved 4 of 6: a drop of 2/6, not 0.4 - 2/6
    assert d.paired and d.drop == pytest.approx(2 / 6)
    assert (d.standard_only, d.perturbed_only) == (2, 0)
    expected = paired_drop(np.array([True, True, False] * 2), np.array(perturbed))
    assert (d.low, d.high) == (expected.low, expected.high)
    assert "paired on 6 of 10 standard episodes, 2/0 discordant" in table.cells()[1][0][3].text
    # and the other way round: the perturbed run is the larger one
    (flipped,) = gap_tables(pd.DataFrame(_rows(BASE, perturbed) + _rows(f"{BASE},perturb=swap", standard)))
    _, d = flipped.rows[0].perturbed["swap"]
    assert d.paired and d.drop == pytest.approx(-2 / 6)
    assert d.shared == "6 of 10 perturbed episodes"


def test_newcombe_matches_the_published_worked_example():
    # Newcombe (1998), Statistics in Medicine 17:873, table II example (56/70 vs 48/80):
    # method 10 gives 0.0524 to 0.3339.
    d = newcombe_drop(Success(56, 70), Success(48, 80))
    assert d.drop == pytest.approx(0.2)
    assert d.low == pytest.approx(0.0524, abs=5e-4) and d.high == pytest.approx(0.3339, abs=5e-4)


def test_the_paired_interval_is_narrower_than_the_unpaired_one_when_outcomes_correlate():
    a = np.array([True] * 30 + [False] * 20)
    b = a.copy()
    b[:10] = False  # the perturbation breaks 10 of the 30 successes, nothing else changes
    paired = paired_drop(a, b)
    unpaired = newcombe_drop(Success(30, 50), Success(20, 50))
    assert paired.drop == pytest.approx(0.2) and unpaired.drop == pytest.approx(0.2)
    assert paired.high - paired.low < unpaired.high - unpaired.low
    concordant = paired_drop(np.ones(4, bool), np.ones(4, bool))
    assert concordant.drop == 0 and concordant.low < -0.4 and concordant.high > 0.4  # 4 pairs say little
    independent = paired_drop(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool))  # phi = 0
    expected = newcombe_drop(Success(2, 4), Success(2, 4))
    assert (independent.low, independent.high) == pytest.approx((expected.low, expected.high))


def test_a_configuration_without_standard_rows_gets_no_drop():
    rows = _rows(BASE, [True] * 4, cid="c1") + _rows(f"{BASE},perturb=env", [True] * 4, cid="c2")
    rows += _rows(f"{BASE},perturb=env", [False] * 4, cid="c1")
    (table,) = gap_tables(pd.DataFrame(rows))
    by_id = {r.policy_config_id: r for r in table.rows}
    assert math.isnan(by_id["c2"].perturbed["env"][1].drop)
    assert by_id["c1"].perturbed["env"][1].drop == pytest.approx(1.0)
    assert table.cells()[1][1][3].text == "-"
    frame = table.frame()
    assert list(frame["perturbation"]) == ["env", "env"] and frame["paired"].tolist() == [True, False]


def test_leaderboard_and_reports_add_the_gap_table(cli, tmp_path):
    from tests.test_leaderboard import episodes, write_run

    params = '{"steps": 1}'
    std = episodes("libero_scripted", params, "s0", [1, 1, 1, 0], suite=BASE)
    swap = episodes(
        "libero_scripted", params, "s0", [1, 0, 0, 0], suite="libero/spatial:perturb=swap,seeding=openvla"
    )
    run = write_run(tmp_path / "r", std + swap)
    code, out, err = cli("leaderboard", str(run), "--format", "md")
    assert code == 0, err
    assert f"## {BASE}: generalization gaps (LIBERO-PRO)" in out
    assert "+50.0 pts" in out and "paired, 2/0 discordant" in out
    code, out, err = cli("report", "paper-table", str(run), "--allow-privileged")
    assert code == 0, err
    assert "generalization gaps" in out
    code, _, err = cli("report", "html", str(run), "--out", str(tmp_path / "html"), "--allow-privileged")
    assert code == 0, err
    assert "generalization gaps (LIBERO-PRO)" in (tmp_path / "html" / "index.html").read_text()
    plain = write_run(tmp_path / "p", std)
    code, out, _ = cli("leaderboard", str(plain), "--format", "md")
    assert code == 0 and "generalization gaps" not in out


def test_published_libero_pro_rows_sit_beneath_labelled_not_comparable():
    from results.generalization import gap_blocks, gap_markdown
    from results.published import LIBERO_PRO_NOT_COMPARABLE

    rows = _rows(BASE, [True] * 4) + _rows("libero/spatial:perturb=swap,seeding=openvla", [True] * 4)
    (table,) = gap_tables(pd.DataFrame(rows))
    _, cells = table.cells()
    measured, published = cells[:1], cells[1:]
    assert measured[0][0].text == "libero_scripted" and len(published) == len(table.published) > 0
    assert all(r[0].text.endswith(LIBERO_PRO_NOT_COMPARABLE) for r in published)
    pi05 = next(r for r in published if r[0].text.startswith("Pi0.5 [motivation]"))
    assert [c.text for c in pi05[1:]] == ["96%", "20%", "+76.0 pts (published)"]  # README: 0.96, P2 0.2
    (block,) = gap_blocks([table])
    assert block.published_from == 1 and any("commit 2b910b5" in n for n in block.notes)
    assert "Pi0.5 [leaderboard] (published, LIBERO-PRO: not comparable) | - | 20% | -" in gap_markdown(
        [table]
    )
    upstream = "libero/spatial:obs=upstream"
    rows = _rows(upstream, [True] * 4) + _rows(f"{upstream},perturb=swap", [True] * 4)
    (table,) = gap_tables(pd.DataFrame(rows))
    assert table.cells()[1][1][0].text.endswith("(published, LIBERO-PRO)")  # same regime: images


def test_only_libero_suites_get_published_rows():
    rows = _rows("plugin/spatial", [True] * 4) + _rows("plugin/spatial:perturb=swap", [False] * 4)
    (table,) = gap_tables(pd.DataFrame(rows))
    assert table.published == () and len(table.cells()[1]) == 1 and len(table.notes()) == 1
