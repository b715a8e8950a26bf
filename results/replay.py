"""The replay benchmark's figures and the speed verdict the gate draws from them.

`dvla-harness bench` (harness/bench.py) decodes a fixed set of recorded observations with
every configuration of a run, many rounds, configuration after configuration within each
round, and writes each configuration's mean seconds per chunk of every round into
RUN_DIR/replay.json. Closed-loop episodes are a poor instrument for a speed verdict (few,
of different lengths, each timed once, under whatever load came and went); rounds of the
same observations are many repeated, comparable measurements.

The verdict, pure functions so a notebook gets the gate's answer:

* within one run, each round gives a paired ratio: a configuration's seconds per chunk
  over the reference decoder's in the same round. A load that comes and goes between
  rounds hits both alike and cancels; one that changes within a round does not, which
  is why rounds are short and many.
* the speed change is  median(baseline ratios) / median(candidate ratios) - 1  (negative:
  the candidate got slower relative to its reference), the same sense as the closed-loop
  tokens/s change, so one `--max-slowdown` means the same for both.
* its interval is a percentile bootstrap over rounds (each run's rounds resampled on
  their own, seeded: the same files give the same interval). FAIL only when the whole
  interval lies beyond -max_slowdown, "inconclusive" when it straddles it, pass
  otherwise: a busy machine widens the interval, and then the gate says it cannot tell
  rather than crying wolf.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from results.replay_conditions import bench_conditions
from results.store import REPLAY, REPLAY_OBSERVATIONS  # the file names, beside the run folder's others

__all__ = ["REPLAY", "REPLAY_OBSERVATIONS", "ReplaySpeed", "load_replay", "replay_speed"]

REPLAY_VERSION = 1
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95


class ReplayFileError(ValueError):
    """A replay.json that cannot be used: unreadable, foreign, or of another version."""


# ---- one configuration's figures ---------------------------------------------------


def bootstrap_median_interval(
    values: Sequence[float], *, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> tuple[float, float]:
    """Percentile bootstrap interval (CONFIDENCE) of the median of `values`."""
    x = np.asarray(values, dtype=float)
    rng = np.random.default_rng(seed)
    medians = np.median(x[rng.integers(0, len(x), size=(resamples, len(x)))], axis=1)
    tail = (1 - CONFIDENCE) / 2 * 100
    low, high = np.percentile(medians, [tail, 100 - tail])
    return float(low), float(high)


def chunk_figures(round_chunk_s: Sequence[float]) -> dict[str, Any]:
    """Median and minimum seconds per chunk over the rounds, with the median's interval."""
    low, high = bootstrap_median_interval(round_chunk_s)
    return {
        "median_chunk_s": float(np.median(round_chunk_s)),
        "min_chunk_s": float(np.min(round_chunk_s)),
        "median_chunk_s_interval": [low, high],
    }


# ---- the verdict ----------------------------------------------------------------------


@dataclass(frozen=True)
class ReplaySpeed:
    """One configuration pair's replay speed relative to the reference, candidate vs baseline."""

    pair: str
    baseline_ratio: float  # median over rounds of (its s/chunk / the reference's s/chunk)
    candidate_ratio: float
    low: float  # the change's bootstrap interval (negative: slower)
    high: float
    max_slowdown: float
    rounds: tuple[int, int]  # (baseline, candidate)
    # How far the candidate's figure can be trusted (BenchConditions); None: not known
    conditions: Any = None

    @property
    def change(self) -> float:
        """Speed relative to the reference, candidate over baseline, minus 1 (negative: slower)."""
        return self.baseline_ratio / self.candidate_ratio - 1.0

    @property
    def verdict(self) -> str:
        """'fail' when the whole interval is a slowdown beyond max_slowdown, 'inconclusive'
        when the interval reaches past it, else 'pass'."""
        if self.high < -self.max_slowdown:
            return "fail"
        if self.low < -self.max_slowdown:
            return "inconclusive"
        return "pass"

    def trust(self) -> str:
        """The verdict in one line with how far its figure can be trusted: the rounds, and
        what the candidate's bench ran under (results/replay_conditions.py)."""
        line = f"{self.pair}: speed {self.verdict} on the replay, {self.change:+.1%} [{self.low:+.1%}, {self.high:+.1%}]"
        if self.conditions is None:
            return f"{line}, {self.rounds[1]} rounds"
        doubts = self.conditions.doubts()
        return f"{line}, {self.conditions.describe(self.rounds[1])}; " + (
            "figure doubtful: " + "; ".join(doubts) if doubts else "no sign of load in the bench"
        )

    def describe(self) -> str:
        return (
            f"{self.change:+.1%} [{self.low:+.1%}, {self.high:+.1%}] ({self.baseline_ratio:.3f} -> "
            f"{self.candidate_ratio:.3f}x the reference's s/chunk, {self.rounds[0]} and "
            f"{self.rounds[1]} rounds; allowed -{self.max_slowdown:.0%})"
        )


@dataclass(frozen=True)
class ReplayWork:
    """One configuration pair's counted work per chunk in the two benches: the FLOPs of
    every torch product its decodes ran, counted at the dispatcher (harness/episode/op_work.py),
    which sees a product wherever the decoder's code calls it."""

    pair: str
    baseline_flops: float
    candidate_flops: float
    gated: bool = True  # False: --allow-work-increase

    @property
    def increased(self) -> bool:
        return self.candidate_flops > self.baseline_flops * (1 + 1e-9) + 1e-12

    def describe(self) -> str:
        change = self.candidate_flops / self.baseline_flops - 1 if self.baseline_flops else float("inf")
        return (
            f"counted work of every torch product (replay) {self.baseline_flops / 1e9:.6g} -> "
            f"{self.candidate_flops / 1e9:.6g} GFLOP/chunk ({change:+.2%})"
        )


def paired_ratios(config_s: Sequence[float], reference_s: Sequence[float]) -> np.ndarray:
    """Round by round: a configuration's seconds per chunk over the reference's."""
    config, reference = np.asarray(config_s, dtype=float), np.asarray(reference_s, dtype=float)
    if config.shape != reference.shape:
        raise ReplayFileError(
            f"{len(config)} rounds of a configuration against {len(reference)} of the reference"
        )
    return config / reference


def replay_speed(
    pair: str,
    baseline_ratios: Sequence[float],
    candidate_ratios: Sequence[float],
    max_slowdown: float,
    *,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    confidence: float = CONFIDENCE,
) -> ReplaySpeed:
    """The verdict on per-round paired ratios (config / reference seconds per chunk) of two
    runs, at `confidence` (the gate's 95%; the bench's stopping rule asks at a higher one)."""
    b, c = np.asarray(baseline_ratios, dtype=float), np.asarray(candidate_ratios, dtype=float)
    rng = np.random.default_rng(seed)
    boot_b = np.median(b[rng.integers(0, len(b), size=(resamples, len(b)))], axis=1)
    boot_c = np.median(c[rng.integers(0, len(c), size=(resamples, len(c)))], axis=1)
    changes = boot_b / boot_c - 1.0
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(changes, [tail, 100 - tail])
    return ReplaySpeed(
        pair,
        float(np.median(b)),
        float(np.median(c)),
        float(low),
        float(high),
        max_slowdown,
        (len(b), len(c)),
    )


# ---- replay.json ----------------------------------------------------------------------


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not valid JSON")


def load_replay(run_path: str | Path) -> dict[str, Any] | None:
    """A run folder's replay.json, checked; None when the run was not benched."""
    path = Path(run_path) / REPLAY
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(), parse_constant=_reject_constant)
    except (OSError, ValueError) as exc:
        raise ReplayFileError(f"{path}: not readable as JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("replay_version") != REPLAY_VERSION:
        found = data.get("replay_version") if isinstance(data, dict) else None
        raise ReplayFileError(
            f"{path}: replay_version {found!r}; this harness reads {REPLAY_VERSION} (run `dvla-harness bench` again)"
        )
    configs = data.get("configurations")
    if not isinstance(configs, list) or not configs:
        raise ReplayFileError(f"{path}: no timed configurations")
    sequential, cap = data.get("sequential"), data.get("max_rounds")
    if not (sequential is None or isinstance(sequential, dict)) or not (cap is None or type(cap) is int):
        raise ReplayFileError(f"{path}: sequential must be an object or null, max_rounds a whole number")
    for entry in configs:
        rounds = entry.get("round_chunk_s") if isinstance(entry, dict) else None
        if (
            not isinstance(rounds, list)
            or len(rounds) < 2
            or not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in rounds)
        ):
            raise ReplayFileError(
                f"{path}: configuration {entry.get('policy_config_id') if isinstance(entry, dict) else entry!r} "
                "has no usable round_chunk_s (a list of at least 2 positive seconds)"
            )
        bad = _bad_optional(entry, len(rounds))
        if bad:
            raise ReplayFileError(f"{path}: configuration {entry.get('policy_config_id')!r}: {bad}")
    return data


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0


def _bad_optional(entry: Mapping[str, Any], rounds: int) -> str:
    """'' or what is wrong with a configuration's optional figures (absent or null: not measured)."""
    for key in ("flops_per_chunk", "module_flops_per_chunk"):
        if entry.get(key) is not None and not _number(entry[key]):
            return f"{key} is {entry[key]!r}, not a non-negative number"
    cpu = entry.get("round_cpu_chunk_s")
    if cpu is not None and not (isinstance(cpu, list) and len(cpu) == rounds and all(map(_number, cpu))):
        return f"round_cpu_chunk_s is not a list of {rounds} non-negative seconds, one per round"
    return ""


def _rounds_by_config(replay: Mapping[str, Any]) -> dict[str, list[float]]:
    return {str(c["policy_config_id"]): list(c["round_chunk_s"]) for c in replay["configurations"]}


def _not_timed(replay: Mapping[str, Any]) -> set[str]:
    return {str(e.get("policy_config_id")) for e in replay.get("not_timed") or [] if isinstance(e, dict)}


def replay_comparable(baseline: Mapping[str, Any], candidate: Mapping[str, Any]) -> str:
    """'' or why the two benches' ratios cannot be compared."""
    threads = (baseline.get("torch_threads"), candidate.get("torch_threads"))
    if None not in threads and threads[0] != threads[1]:
        return (
            f"torch threads differ (baseline {threads[0]}, candidate {threads[1]}); decoders gain "
            "unequally from threads (bench both with OMP_NUM_THREADS=1)"
        )
    return ""


def replay_notes(baseline: Mapping[str, Any], candidate: Mapping[str, Any]) -> list[str]:
    """What the gate says beside the replay verdict (different observation sets)."""
    sets = [((r.get("observations") or {}).get("sha256")) for r in (baseline, candidate)]
    if None not in sets and sets[0] != sets[1]:
        return [
            "replay: the runs decoded different recorded observations (bench the candidate with "
            "--observations BASELINE_DIR to decode the same ones); ratios compared anyway"
        ]
    return []


def replay_verdicts(
    pairs: Sequence[Any],
    reference: Any,
    baseline: Mapping[str, Any],
    candidate: Mapping[str, Any],
    max_slowdown: float,
) -> tuple[list[ReplaySpeed], list[str]]:
    """The replay verdict of every pair (results.pairing.ConfigPair) timed on both sides,
    against `reference` (the reference's ConfigPair); with notes on pairs left out."""
    b_rounds, c_rounds = _rounds_by_config(baseline), _rounds_by_config(candidate)
    if reference.baseline_id not in b_rounds or reference.candidate_id not in c_rounds:
        return [], [
            f"replay: the reference {reference.label} was not benched in both runs; closed-loop speed used"
        ]
    out, notes = [], []
    for pair in pairs:
        if pair == reference:
            continue
        missing = [
            side
            for side, rounds, skipped, config_id in (
                ("baseline", b_rounds, _not_timed(baseline), pair.baseline_id),
                ("candidate", c_rounds, _not_timed(candidate), pair.candidate_id),
            )
            if config_id not in rounds and config_id not in skipped
        ]
        if missing:
            notes.append(
                f"replay: {pair.label} is not in the {' and '.join(missing)} bench; closed-loop speed used"
            )
        if pair.baseline_id not in b_rounds or pair.candidate_id not in c_rounds:
            continue  # decodes no tokens (scripted), or benched on one side only: closed loop
        try:
            base = paired_ratios(b_rounds[pair.baseline_id], b_rounds[reference.baseline_id])
            cand = paired_ratios(c_rounds[pair.candidate_id], c_rounds[reference.candidate_id])
        except ReplayFileError as exc:
            notes.append(f"replay: {pair.label}: {exc}; closed-loop speed used")
            continue
        speed = replay_speed(pair.label, base, cand, max_slowdown)
        conditions = bench_conditions(baseline, candidate, reference.baseline_id, reference.candidate_id)
        out.append(dataclasses.replace(speed, conditions=conditions))
    return out, notes


def _flops_by_config(replay: Mapping[str, Any], key: str) -> dict[str, float]:
    return {
        str(c["policy_config_id"]): float(c[key])
        for c in replay["configurations"]
        if isinstance(c.get(key), (int, float)) and not isinstance(c.get(key), bool)
    }


def replay_work(
    pairs: Sequence[Any], baseline: Mapping[str, Any], candidate: Mapping[str, Any], gated: bool = True
) -> tuple[list[ReplayWork], list[str]]:
    """The dispatcher-counted work of every pair (the reference's too) benched on both
    sides, with notes on pairs left out and on work the module hooks do not see."""
    b_flops, c_flops = (
        _flops_by_config(baseline, "flops_per_chunk"),
        _flops_by_config(candidate, "flops_per_chunk"),
    )
    b_timed, c_timed = _rounds_by_config(baseline), _rounds_by_config(candidate)
    hooked = _flops_by_config(candidate, "module_flops_per_chunk")
    out, notes, unmeasured = [], [], []
    for pair in pairs:
        if pair.baseline_id not in b_timed or pair.candidate_id not in c_timed:
            continue
        if pair.baseline_id not in b_flops or pair.candidate_id not in c_flops:
            unmeasured.append(pair.label)
            continue
        out.append(ReplayWork(pair.label, b_flops[pair.baseline_id], c_flops[pair.candidate_id], gated))
        seen = hooked.get(pair.candidate_id)
        ops = c_flops[pair.candidate_id]
        if seen is not None and ops > seen * (1 + 1e-9) + 1e-12:
            notes.append(
                f"{pair.label}: {1 - seen / ops:.1%} of its bench's products ran outside the counted "
                f"modules ({ops / 1e9:.6g} GFLOP/chunk at the dispatcher, {seen / 1e9:.6g} by the module "
                "hooks): the closed-loop GFLOP/chunk column does not see them"
            )
    if unmeasured:
        notes.append(
            f"replay: counted work of every torch product not compared for {', '.join(unmeasured)} "
            "(a bench without it: bench that run again)"
        )
    return out, notes


def replay_warnings(speeds: Sequence[ReplaySpeed]) -> list[str]:
    """One line per inconclusive pair (the gate passes, but says it could not tell)."""
    return [
        f"{s.pair}: replay speed inconclusive: {s.describe()}: the interval reaches past the allowed "
        "slowdown; the machine was too noisy to tell (run the bench again with more --rounds, "
        "or on a quieter machine)"
        for s in speeds
        if s.verdict == "inconclusive"
    ]
