"""SimplerEnv-like variant runs in every report: canonical, variant-aggregated and
per-axis success, and ranking stability (MMRV, Pearson r, Kendall tau), from hand-made rows whose
numbers can be checked by hand."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np
import pandas as pd
import pytest

from results.leaderboard import leaderboards
from results.runs import load_run
from results.variant_table import kendall_tau, mmrv, ranking_stability, variant_stats
from tests.test_leaderboard import BIDI, FAST, MANIFEST, row, write_run

SUITE = "simpler/pick_cube:variants=simplerenv+lighting.warm+mass.heavy"


def rows(policy: str, params: str, config: str, outcomes: dict[str, list[int]], tokens: float = 100.0):
    """outcomes: variant label -> success of layouts 0, 1, ... (every variant replays them)."""
    out = []
    for v, (variant, wins) in enumerate(outcomes.items()):
        for j, ok in enumerate(wins):
            r = row(
                policy, params, config, suite=SUITE, task="pick_cube", episode_index=v * 24 + j, seed=100 + j,
                init_state_id=None, success=bool(ok), tokens_per_s=tokens,
                started_at=datetime(2026, 1, 1, tzinfo=UTC) + timedelta(seconds=v * 10 + j),
            )  # fmt: skip
            out.append(r | {"variant": variant})
    return out


# pick_cube follows SimplerEnv's pick coke can: 9 settings. lighting=warm is outside the set
# (extended aggregate only), mass=heavy a harness axis (in neither).
REST = (
    "table=dark",
    "table=white",
    "distractors=one",
    "distractors=three",
    "background=dark",
    "background=sand",
)
TEACHER = {
    "canonical": [1, 1, 1, 1],
    "lighting=dim": [1, 1, 0, 0],
    "lighting=bright": [1, 1, 1, 0],
    "lighting=warm": [0, 0, 0, 0],
    **{v: [1, 1, 1, 1] for v in REST},
    "mass=heavy": [0, 0, 0, 0],
}
STUDENT = {
    "canonical": [1, 1, 0, 0],
    "lighting=dim": [1, 1, 1, 1],
    "lighting=bright": [1, 0, 0, 0],
    "lighting=warm": [1, 1, 1, 1],
    **{v: [1, 1, 0, 0] for v in REST},
    "mass=heavy": [1, 0, 0, 0],
}


def test_canonical_aggregated_and_per_axis_success_by_hand():
    stats = variant_stats(pd.DataFrame(rows("bidirectional", BIDI, "b", TEACHER)))
    assert (stats.canonical.successes, stats.canonical.episodes) == (4, 4)
    assert stats.per_variant["lighting=dim"] == 0.5 and stats.per_variant["mass=heavy"] == 0.0
    # SimplerEnv's aggregate: the 9 settings of pick_cube's set, each once; warm is outside the
    # set and mass the harness's own axis
    assert stats.aggregated == pytest.approx((1.0 + 0.5 + 0.75 + 6) / 9)
    assert stats.extended == pytest.approx((1.0 + 0.5 + 0.75 + 0.0 + 6) / 10)
    assert stats.per_axis()["lighting"] == pytest.approx(1.25 / 3) and stats.per_axis()["mass"] == 0.0
    low, high = stats.aggregated_interval
    assert 0 <= low < stats.aggregated < high <= 1
    assert stats.axis_text("mass") == "0.0% (-100.0)"
    same = variant_stats(pd.DataFrame(rows("bidirectional", BIDI, "b", TEACHER)))
    assert same.aggregated_interval == stats.aggregated_interval  # fixed bootstrap seed


def test_mmrv_and_kendall_tau_by_hand():
    reference, other = np.array([0.9, 0.5, 0.2]), np.array([0.4, 0.6, 0.1])
    # policy 0 and 1 swap: each loses the 0.4 canonical gap; policy 2 keeps its place
    assert mmrv(reference, other) == pytest.approx((0.4 + 0.4 + 0.0) / 3)
    assert kendall_tau(reference, other) == pytest.approx((2 - 1) / 3)
    assert mmrv(reference, reference) == 0.0 and kendall_tau(reference, reference) == pytest.approx(1.0)
    assert kendall_tau(reference, -reference) == pytest.approx(-1.0)
    assert np.isnan(kendall_tau(reference, np.array([0.3, 0.3, 0.3])))  # one variant ties them all


def test_ranking_stability_on_the_aggregate_with_the_per_variant_diagnostic():
    t = variant_stats(pd.DataFrame(rows("bidirectional", BIDI, "b", TEACHER)))
    s = variant_stats(pd.DataFrame(rows("fast_dvla", FAST, "f", STUDENT)))
    r = ranking_stability({"teacher": t, "student": s})
    # canonical 1.0 vs 0.5; aggregated 0.917 vs 0.528: the same order, so SimplerEnv's MMRV
    # is 0 and r 1, although the dim lighting alone inverts them
    assert (r.mmrv, r.pearson, r.kendall_tau) == (0.0, pytest.approx(1.0, abs=1e-6), 1.0)
    assert r.per_task["pick_cube"] == (0.0, pytest.approx(1.0, abs=1e-6), 1.0)
    assert r.extended == (0.0, pytest.approx(1.0, abs=1e-6), 1.0)  # 0.825 vs 0.575
    # the diagnostic: dim and warm invert the pair (each loses the 0.5 gap), bright keeps it
    assert r.per_axis["lighting"] == (
        pytest.approx(1 / 3),
        pytest.approx(-1 / 3, abs=1e-6),
        pytest.approx(-1 / 3),
    )
    assert r.per_axis["mass"] == (pytest.approx(0.5), pytest.approx(-1.0), pytest.approx(-1.0))
    text = r.text()
    assert "MMRV 0.000" in text and "Pearson r 1.00" in text and "Kendall tau 1.00" in text
    assert "the harness's own axes, not in SimplerEnv's aggregate: mass 0.500 / -1.00 / -1.00" in text
    assert "lighting 0.333 / -0.33 / -0.33" in text
    assert "n/a" in ranking_stability({"teacher": t}).text()


def _two_policy_run(tmp_path):
    manifest = MANIFEST | {"suite": MANIFEST["suite"] | {"name": SUITE, "tasks": ["pick_cube"]}}
    return write_run(
        tmp_path / "v",
        rows("bidirectional", BIDI, "b", TEACHER) + rows("fast_dvla", FAST, "f", STUDENT, 250.0),
        manifest,
    )


def test_the_leaderboard_of_a_variant_run_is_simplerenvs_table(tmp_path, cli):
    run = _two_policy_run(tmp_path)
    (board,) = leaderboards([load_run(run)])
    headers, cells = board.cells()
    assert headers[1:9] == [
        "canonical scene (Wilson 95%)",
        "variant-aggregated, SimplerEnv's set per task (95%)",
        "extended aggregate, every level of its axes (95%)",
        "lighting (vs canonical)",
        "table (vs canonical)",
        "distractors (vs canonical)",
        "background (vs canonical)",
        "mass (harness axis, vs canonical)",
    ]
    teacher = [c.text for c in cells[0]]
    assert teacher[1] == "100.0% [51, 100] (4/4)" and teacher[2].startswith("91.7% [")
    assert teacher[3].startswith("82.5% [")
    assert board.ranking is not None and board.ranking.mmrv == 0.0
    frame = board.frame().set_index("policy")
    assert frame.loc["fast_dvla", "canonical_success"] == 0.5
    assert frame.loc["fast_dvla", "aggregated_success[pick_cube]"] == pytest.approx(4.75 / 9)
    assert frame.loc["fast_dvla", "extended_aggregated_success"] == pytest.approx(0.575)
    assert frame.loc["fast_dvla", "success[lighting=dim]"] == 1.0
    code, out, _ = cli("leaderboard", str(run), "--format", "md")
    assert (
        code == 0
        and "| canonical scene (Wilson 95%) |" in out
        and "ranking stability of the variant aggregate vs the canonical scene" in out
    )
    code, _, _ = cli("report", "html", str(run), "--out", str(tmp_path / "report"))
    page = (tmp_path / "report" / "index.html").read_text()
    assert (
        code == 0
        and "variant-aggregated" in page
        and "ranking stability of the variant aggregate vs the canonical scene" in page
    )
    # the canonical scene is never called visual matching; only the note saying it is not
    assert page.count("visual matching") == page.count("visual matching (docs/simpler.md)")
    assert "Pearson r" in page


def test_paper_table_gives_a_variant_run_simplerenvs_layout_never_a_pooled_rate(tmp_path, cli):
    run = _two_policy_run(tmp_path)
    code, out, err = cli("report", "paper-table", str(run))
    assert code == 0, err
    assert "(SimplerEnv layout)" in out and "| canonical scene (Wilson 95%) |" in out
    teacher = next(line for line in out.splitlines() if line.startswith("| bidirectional"))
    assert "100.0% [51, 100] (4/4)" in teacher and "91.7% [" in teacher  # canonical; aggregated
    assert "(published, SimplerEnv: not comparable)" in out and "59.3" in out
    assert (
        "ranking stability of the variant aggregate vs the canonical scene" in out
        and "not SimplerEnv's scenes" in out
    )
    assert "MMRV" in out and "Pearson r" in out and "Kendall tau" in out
    pooled = f"{100 * 33 / 44:.1f}%"  # the teacher's 33 of 44 episodes over all variants
    assert pooled not in teacher and "### measured" not in out  # no LIBERO-layout row pooling them
