"""The CI regression gate: does a candidate run hold up against a baseline run?

Pure functions on episode tables (and manifests, for the timing reference), so a
notebook can call `gate(base_df, cand_df)` and get the same verdict as the CLI.
docs/ci-gate.md explains the rules; in short:

* Configurations are paired by policy name + params + checkpoint hash (a checkpoint is
  its content, not its path, so runs from two clones still pair); then, among the
  unpaired, by policy name when that is unambiguous; then, if exactly one is left on
  each side, those two. Anything still unpaired is refused (results/pairing.py).
* Episodes are paired by (suite, task, episode_index, seed, init_state_id), and a
  configuration pair must hold exactly the same episodes on both sides, else refused.
* Success: McNemar's exact test, one-sided. Paired episodes whose outcome is the same
  carry no evidence; of the n discordant pairs, under "no change" the drops are
  Binomial(n, 1/2), so p = P(X >= drops). Exact because CI evaluations are small, where
  the chi-square approximation is poor. Gated overall at alpha and per task at
  alpha / tasks (Bonferroni), so one collapsed task is caught without every task
  being another chance of a false alarm.
* Instruction chains (CALVIN-like suites): besides full-chain success, the subtasks
  completed per chain, paired chain by chain: a chain that completes fewer subtasks is a
  drop, more a gain, equal carries no evidence, and p is the same exact one-sided sign
  test. A policy that still finishes its 5/5 chains but stops earlier in the others is
  caught here and by nothing else. The two tests of a chain row are each at alpha / 2
  (Bonferroni), so a chain suite is no likelier to raise a false alarm than another.
* NFE per chunk (total passes / total chunks) is deterministic for deterministic
  decoders: any increase fails.
* Counted work per chunk (total FLOPs / total chunks, harness/episode/work.py) is as exact as
  NFE and checked the same way: any increase fails (a wider cached range, a bigger
  pass). Not measured on either side (null in any of the rows) means not compared,
  said in a note.
* tokens/s is compared only as a paired ratio: each configuration's tokens/s over a
  reference decoder's (default `bidirectional`) measured interleaved, episode by
  episode, in the same run, against the same ratio in the other run. A machine that is
  faster, slower or busier scales both alike; a different CPU model does not (the ratio
  moved 13% between two idle CPUs), so runs whose manifests name different CPUs are not
  compared unless asked. Where no such reference exists on both sides, or the CPUs
  differ, the check says "not comparable: <reason>" and passes.
* When both runs were benched (`dvla-harness bench`, replay.json), the replay benchmark
  decides speed instead (results/replay.py): the same ratio round by round, failing only
  when its whole bootstrap interval lies beyond the allowed slowdown, "inconclusive"
  (a warning, no failure) when it straddles it; the closed-loop ratio is then reported.

Here: the success, chain-length, NFE and counted-work tests. The records they fill and
the verdict those add up to (GateResult.failures) are results/gate_result.py; the
per-side measures of a pair's episodes, results/gate_measures.py; the speed rules
(reference decoder, manifests, replay), results/gate_speed.py.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pandas as pd

from results.board_warnings import out_of_space_gate_warnings
from results.gate_measures import (
    merged_pair,
    nfe_per_chunk,
    side_measures,
    tokens_per_s,
    work_per_chunk,
    work_unmeasured,
)
from results.gate_result import GateResult, SpeedDiff, TaskDiff
from results.gate_speed import (
    DEFAULT_REFERENCE,
    is_reference,
    machine_notes,
    one_sided_reference,
    pair_speed,
    reference_pair,
    speed_comparable,
    with_replay,
)
from results.pairing import (
    GateInputError as GateInputError,  # raised from here; callers catch it by this name
)
from results.pairing import check_episodes_match, episode_keys, pair_configs
from results.runs import Run, batch_sizes
from results.simulator_versions import suspect as simulator_suspect


def mcnemar_drop_p(drops: int, gains: int) -> float:
    """One-sided exact McNemar p-value that `drops` this large arose by chance."""
    n = drops + gains
    if drops <= 0:
        return 1.0
    return sum(math.comb(n, k) for k in range(drops, n + 1)) / 2**n


def _chain_lengths(b: pd.DataFrame, c: pd.DataFrame) -> dict[str, Any]:
    """The sign test on subtasks completed, for chain rows; {} for other suites. A chain
    row without a count (it raised before the runner could count) completed none."""
    if not (b["subtasks_completed"].notna().any() or c["subtasks_completed"].notna().any()):
        return {}
    base = b["subtasks_completed"].astype(float).fillna(0).to_numpy()
    cand = c["subtasks_completed"].astype(float).fillna(0).to_numpy()
    drops, gains = int((cand < base).sum()), int((cand > base).sum())
    return {
        "baseline_length": float(base.mean()) if len(base) else None,
        "candidate_length": float(cand.mean()) if len(cand) else None,
        "length_drops": drops,
        "length_gains": gains,
        "length_p": mcnemar_drop_p(drops, gains),
    }


def _task_diff(
    pair: str, task: str, merged: pd.DataFrame, alpha: float, gate_nfe: bool, gate_work: bool = True
) -> TaskDiff:
    b, c = side_measures(merged, "b"), side_measures(merged, "c")
    base, cand = b["success"].astype(bool), c["success"].astype(bool)
    drops, gains = int((base & ~cand).sum()), int((~base & cand).sum())
    lengths = _chain_lengths(b, c)
    if lengths:
        alpha /= 2  # two tests on one row: full-chain success and length (Bonferroni)
    return TaskDiff(
        pair=pair,
        task=task,
        episodes=len(merged),
        baseline_successes=int(base.sum()),
        candidate_successes=int(cand.sum()),
        drops=drops,
        gains=gains,
        p_value=mcnemar_drop_p(drops, gains),
        alpha=alpha,
        baseline_nfe=nfe_per_chunk(b),
        candidate_nfe=nfe_per_chunk(c),
        nfe_gated=gate_nfe,
        baseline_work=work_per_chunk(b),
        candidate_work=work_per_chunk(c),
        work_gated=gate_work,
        **lengths,
    )


def gate(
    baseline: pd.DataFrame,
    candidate: pd.DataFrame,
    *,
    alpha: float = 0.05,
    max_slowdown: float = 0.10,
    allow_nfe_increase: bool = False,
    allow_work_increase: bool = False,
    reference: str | None = DEFAULT_REFERENCE,
    speed_skipped: str = "",
) -> GateResult:
    """Compare two episode tables. Speed is each configuration's tokens/s over the
    `reference` decoder's (a policy name or config id) in the same run, against that
    ratio in the other run; `speed_skipped` ("not comparable: why") skips it.

    Raises GateInputError when the runs cannot be compared (nothing is judged then).
    """
    one_sided = one_sided_reference(baseline, candidate, reference)
    if one_sided:  # a run without the reference is still gated on success and NFE
        side, df = one_sided
        keep = ~is_reference(df, reference)
        baseline, candidate = (
            (baseline[keep], candidate) if side == "baseline" else (baseline, candidate[keep])
        )
    pairs = pair_configs(baseline, candidate)
    for pair in pairs:
        check_episodes_match(baseline, candidate, pair)
    if speed_skipped:
        ref_pair, why = None, speed_skipped
    elif one_sided:
        other = "candidate" if one_sided[0] == "baseline" else "baseline"
        ref_pair, why = (
            None,
            (
                f"the {other} has no {reference} rows to time against (only the {one_sided[0]}'s "
                f"{reference}, left out of the comparison)"
            ),
        )
    else:
        ref_pair, why = reference_pair(pairs, baseline, reference)
    if why and not why.startswith("not comparable"):
        why = f"not comparable: {why}"
    notes = [f"speed {why}"] if why else []
    ref_rows = merged_pair(baseline, candidate, ref_pair) if ref_pair else None
    tasks: list[TaskDiff] = []
    speed: list[SpeedDiff] = []
    skipped: list[tuple[str, str]] = []
    errors: list[str] = []
    for pair in pairs:
        b = episode_keys(baseline[baseline["policy_config_id"] == pair.baseline_id])
        c = episode_keys(candidate[candidate["policy_config_id"] == pair.candidate_id])
        merged = merged_pair(baseline, candidate, pair)
        order = list(dict.fromkeys(merged.sort_values("task_index_b", kind="stable")["task"]))
        gated = (not allow_nfe_increase, not allow_work_increase)
        for task in order:
            rows = merged[merged["task"] == task]
            tasks.append(_task_diff(pair.label, task, rows, alpha / len(order), *gated))
        tasks.append(_task_diff(pair.label, "ALL", merged, alpha, *gated))
        if (unmeasured := work_unmeasured(merged)) is not None:
            notes.append(f"{pair.label}: counted work not compared (not measured in the {unmeasured})")
        raised = {
            side: int(rows["failure_reason"].notna().sum())
            for side, rows in (("baseline", b), ("candidate", c))
        }
        for side, count in raised.items():
            if count:
                notes.append(f"{pair.label}: {count} {side} episode(s) raised; counted as failures")
        if raised["candidate"] > raised["baseline"]:
            # Episodes that raise decode nothing, so NFE and speed cannot catch them, and a
            # baseline with few successes leaves McNemar's test no room to: fail outright.
            errors.append(
                f"{pair.label}: {raised['candidate']} candidate episode(s) raised, "
                f"{raised['baseline']} in the baseline (failure_reason in the rows)"
            )
        if pair == ref_pair:
            continue
        decodes = (
            tokens_per_s(side_measures(merged, "b")) is not None
            and tokens_per_s(side_measures(merged, "c")) is not None
        )
        if not decodes:
            notes.append(f"{pair.label}: tokens/s not compared (no action tokens decoded on both sides)")
            continue
        if ref_rows is None:
            skipped.append((pair.label, why))
            continue
        diff = pair_speed(pair, merged, ref_rows, max_slowdown)
        if isinstance(diff, SpeedDiff):
            speed.append(diff)
        else:
            skipped.append((pair.label, diff))
            notes.append(f"{pair.label}: speed {diff}")
    if ref_pair is not None:
        notes.append(
            f"speed: tokens/s relative to {ref_pair.label}'s in the same run (the reference; "
            "its own speed is the unit, so it is not judged)"
        )
    if allow_nfe_increase:
        notes.append("NFE increases reported but allowed (--allow-nfe-increase)")
    if allow_work_increase:
        notes.append("counted work increases reported but allowed (--allow-work-increase)")
    return GateResult(
        tuple(pairs),
        tuple(tasks),
        tuple(speed),
        tuple(notes),
        tuple(errors),
        not_comparable=tuple(skipped),
        reference=ref_pair.label if ref_pair else "",
    )


def gate_runs(baseline: Run, candidate: Run, **options: Any) -> GateResult:
    """`gate` on two loaded runs: thread counts, CPUs, calibration drift and simulator
    versions from their manifests, and the replay benchmark's figures (replay.json) when
    both runs have them. Runs from different CPUs have their speed compared only with
    `speed_across_cpus=True` (success, NFE and counted work always are); an inconclusive
    replay verdict fails the gate with `inconclusive="fail"`."""
    manifests = {"baseline": baseline.manifest, "candidate": candidate.manifest}
    across = bool(options.pop("speed_across_cpus", False))
    inconclusive = options.pop("inconclusive", "pass")
    skipped = options.pop("speed_skipped", "") or speed_comparable(manifests, across)
    result = gate(baseline.episodes, candidate.episodes, speed_skipped=skipped, **options)
    run_warnings = tuple(
        f"{side} {run.label}: speed figures unreliable: {run.speed_warning}"
        for side, run in (("baseline", baseline), ("candidate", candidate))
        if run.speed_warning
    )
    warnings = run_warnings
    sizes = {
        side: batch_sizes(run.episodes) for side, run in (("baseline", baseline), ("candidate", candidate))
    }
    if len({size for side in sizes.values() for size in side}) > 1:
        warnings += (
            f"batch sizes differ (--batch-envs: baseline {sizes['baseline']}, candidate "
            f"{sizes['candidate']}): speed, and an adaptive decoder's NFE (a batched row is charged "
            "the passes its batch ran), are compared across batch sizes; run both at one batch size",
        )
    warnings += out_of_space_gate_warnings(baseline.episodes, candidate.episodes)
    notes = result.notes + tuple(machine_notes(manifests, across))
    suspect = simulator_suspect(manifests)
    moved = [t for t in result.tasks if t.task == "ALL" and (t.drops or t.gains)]
    if suspect and moved and not any(t.success_regressed for t in result.tasks):
        notes = (f"success moved ({_moves(moved)}); first suspect: {suspect}", *notes)
    elif suspect and not moved:
        notes = (suspect, *notes)
    result = dataclasses.replace(result, notes=notes, warnings=warnings, simulator_suspect=suspect)
    result = dataclasses.replace(result, inconclusive=inconclusive)
    result = with_replay(result, baseline, candidate, options)
    return _closed_loop_warnings_as_notes(result, run_warnings)


def _closed_loop_warnings_as_notes(result: GateResult, run_warnings: tuple[str, ...]) -> GateResult:
    """A run's "speed figures unreliable" is about its episodes' timings (the calibration,
    starved episodes). When the replay judged the speed of every pair that was judged,
    those figures decided nothing: the warning becomes a note saying so, and the replay
    verdict's own line says how far its figure can be trusted."""
    replayed = {r.pair for r in result.replay}
    if not run_warnings or not replayed or not {s.pair for s in result.speed} <= replayed:
        return result
    notes = tuple(
        f"{w.replace('speed figures unreliable', 'closed-loop speed figures unreliable', 1)}; "
        "not used for the verdict: the replay judged speed"
        for w in run_warnings
    )
    warnings = tuple(w for w in result.warnings if w not in run_warnings)
    return dataclasses.replace(result, warnings=warnings, notes=(*result.notes, *notes))


def _moves(tasks: list[TaskDiff]) -> str:
    return "; ".join(f"{t.pair}: {t.drops} drops, {t.gains} gains" for t in tasks)
