"""Speed in the CI gate (results/gate.py): tokens/s judged only relative to a reference
decoder measured in the same run, never across machines.

Each configuration's tokens/s over the reference's, on the episodes both ran, against
the same ratio in the other run (SpeedDiff). Which pair is the reference, and why there
may be none (only one run holds it, it changed, it is ambiguous), is decided here; so
are the manifests' reasons not to compare speed at all (different torch thread counts,
different CPU models) and, when both runs were benched, the replay benchmark's verdicts
(results/replay.py), which then decide speed in place of the closed-loop ratio.

The ratio cancels a machine's speed and load, not its CPU model: the smoke config's
fast_dvla / bidirectional replay ratio moved 13% from an AMD EPYC to an Intel Xeon, both
idle (docs/ci-gate.md), more than a 10% gate allows. So runs from different CPUs are
compared only when the caller asks (`speed_across_cpus`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import pandas as pd

from results.cpu_identity import cpu_difference, describe_cpu
from results.gate_measures import side_measures, tokens_per_s
from results.gate_result import GateResult, SpeedDiff
from results.pairing import PAIR_KEY, ConfigPair
from results.runs import Run

DEFAULT_REFERENCE = "bidirectional"  # the teacher: every decoder config can run beside it


def is_reference(df: pd.DataFrame, reference: str | None) -> pd.Series:
    return (df["policy"] == reference) | (df["policy_config_id"] == reference)


def one_sided_reference(
    baseline: pd.DataFrame, candidate: pd.DataFrame, reference: str | None
) -> tuple[str, pd.DataFrame] | None:
    """(side, its table) when only that side holds the reference decoder, else None."""
    if not reference:
        return None
    held = {
        side: bool(is_reference(df, reference).any())
        for side, df in (("baseline", baseline), ("candidate", candidate))
    }
    if held["baseline"] == held["candidate"]:
        return None
    return ("baseline", baseline) if held["baseline"] else ("candidate", candidate)


def reference_pair(
    pairs: list[ConfigPair], baseline: pd.DataFrame, reference: str | None
) -> tuple[ConfigPair | None, str]:
    """The pair of the reference decoder's configurations, or (None, why there is none)."""
    if not reference:
        return None, "no reference decoder given"
    found = list(dict.fromkeys(baseline.loc[is_reference(baseline, reference), "policy_config_id"]))
    if not found:
        return None, (
            f"neither run has {reference} rows to time against (a run needs the reference "
            "decoder beside the others: docs/ci-gate.md)"
        )
    if len(found) > 1:
        return (
            None,
            f"the baseline has {len(found)} configurations of {reference} (pass --reference CONFIG_ID)",
        )
    pair = next(p for p in pairs if p.baseline_id == found[0])
    if pair.rule != "same policy and params":
        what = pair.changes or f"{pair.baseline} -> {pair.candidate}"
        return None, f"the reference {reference} differs between the runs ({what})"
    return pair, ""


def pair_speed(
    pair: ConfigPair, merged: pd.DataFrame, reference: pd.DataFrame, max_slowdown: float
) -> SpeedDiff | str:
    """The pair's tokens/s against the reference's over the episodes both ran, or why not."""
    keys = list(PAIR_KEY)
    common = merged[keys].merge(reference[keys])
    if common.empty:
        return "not comparable: it shares no episodes with the reference"
    mine, ref = merged.merge(common), reference.merge(common)
    tps = [tokens_per_s(side_measures(df, side)) for df in (mine, ref) for side in ("b", "c")]
    if tps[0] is None or tps[1] is None:
        return "no action tokens decoded on both sides"
    if tps[2] is None or tps[3] is None:
        return "not comparable: the reference decoded no tokens on these episodes"
    return SpeedDiff(pair.label, tps[0], tps[1], tps[2], tps[3], max_slowdown)


def torch_threads(manifest: dict[str, Any]) -> int | None:
    """The torch thread count a run's policies ran with, if its manifest recorded it."""
    threads = ((manifest or {}).get("calibration") or {}).get("torch_threads")
    return int(threads) if threads is not None else None


def _environment(manifest: dict[str, Any] | None) -> dict[str, Any]:
    return (manifest or {}).get("environment") or {}


def run_cpus(manifests: dict[str, dict[str, Any]]) -> dict[str, str]:
    """Each side's CPU as its manifest names it (absent: not named)."""
    envs = {side: _environment(m) for side, m in manifests.items()}
    return {side: describe_cpu(e) for side, e in envs.items() if e.get("cpu")}


def cpu_difference_of(manifests: dict[str, dict[str, Any]]) -> str:
    """'' or how the two runs' CPUs differ: by identity (family, model, stepping,
    microcode, caches, flags) where both manifests recorded it, else by model name (the
    CPU count alone does not move a one-thread ratio)."""
    if len(manifests) != 2:
        return ""
    return cpu_difference(_environment(manifests.get("baseline")), _environment(manifests.get("candidate")))


def speed_comparable(manifests: dict[str, dict[str, Any]], speed_across_cpus: bool = False) -> str:
    """'' or "not comparable: why" from the manifests (bare tables say nothing: compared)."""
    threads = {side: torch_threads(m) for side, m in manifests.items()}
    if None not in threads.values() and len(set(threads.values())) > 1:
        return (
            "not comparable: torch threads differ (baseline {baseline}, candidate {candidate}); "
            "decoders gain unequally from threads, so their ratio moves (run both with "
            "OMP_NUM_THREADS=1)".format(**threads)
        )
    differ = cpu_difference_of(manifests)
    if differ and not speed_across_cpus:
        cpus = run_cpus(manifests)
        return (
            f"not comparable: the runs come from different CPUs ({differ}; baseline {cpus['baseline']}, "
            f"candidate {cpus['candidate']}); a decoder's speed over its reference moves with the "
            "CPU (docs/ci-gate.md): gate speed against a baseline run on the same runner, "
            "or pass --speed-across-cpus to judge it anyway"
        )
    return ""


def machine_notes(manifests: dict[str, dict[str, Any]], speed_across_cpus: bool = False) -> list[str]:
    differ = cpu_difference_of(manifests)
    if differ and speed_across_cpus:
        cpus = run_cpus(manifests)
        return [
            f"the runs come from different CPUs ({differ}; baseline {cpus['baseline']}, candidate "
            f"{cpus['candidate']}): speed compared anyway (--speed-across-cpus), through the "
            "in-run reference; the CPU model alone can move that ratio by more than 10%"
        ]
    return []


def with_replay(result: GateResult, baseline: Run, candidate: Run, options: dict[str, Any]) -> GateResult:
    """The replay benchmark's verdicts (results/replay.py) when both runs were benched
    against a comparable reference, and the work its decodes counted at the dispatcher
    whenever both were benched; the result unchanged otherwise. `options`: the gate's
    max_slowdown, allow_work_increase."""
    from results.replay import (
        load_replay,
        replay_comparable,
        replay_notes,
        replay_verdicts,
        replay_warnings,
        replay_work,
    )

    max_slowdown = options.get("max_slowdown", 0.10)

    benches = [load_replay(run.path) for run in (baseline, candidate)]
    if None not in benches:  # counted work needs no reference and no CPU in common
        work, notes = replay_work(
            result.pairs, benches[0], benches[1], not options.get("allow_work_increase")
        )
        result = dataclasses.replace(result, replay_work=tuple(work), notes=(*result.notes, *notes))
    reference = next((p for p in result.pairs if p.label == result.reference), None)
    if reference is None or None in benches:
        if reference is not None and any(benches):
            side = "baseline" if benches[0] is None else "candidate"
            note = f"replay: only one run was benched (not the {side}); closed-loop speed decides"
            return dataclasses.replace(result, notes=(*result.notes, note))
        return result
    why = replay_comparable(benches[0], benches[1])
    if why:
        return dataclasses.replace(result, notes=(*result.notes, f"replay not comparable: {why}"))
    speeds, notes = replay_verdicts(result.pairs, reference, benches[0], benches[1], max_slowdown)
    notes = replay_notes(benches[0], benches[1]) + notes
    if speeds:
        notes.append(
            "speed: judged on the replay benchmark (replay.json); the closed-loop tokens/s ratio is "
            "reported beside it, not judged"
        )
    return dataclasses.replace(
        result,
        replay=tuple(speeds),
        notes=(*result.notes, *notes),
        warnings=(*result.warnings, *replay_warnings(speeds)),
    )
