"""The CI gate's verdict as records: per configuration pair and task (TaskDiff), per
pair's speed (SpeedDiff), and the whole (GateResult), whose `failures` is the verdict.

Apart from the rules that fill them (results/gate.py, results/gate_speed.py), so that
both read one definition without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from results.pairing import ConfigPair


@dataclass(frozen=True)
class TaskDiff:
    """One configuration pair on one task (or `ALL`)."""

    pair: str
    task: str
    episodes: int
    baseline_successes: int
    candidate_successes: int
    drops: int  # baseline succeeded, candidate failed
    gains: int
    p_value: float
    alpha: float  # the level this row is tested at
    baseline_nfe: float | None  # passes per chunk
    candidate_nfe: float | None
    nfe_gated: bool = True
    baseline_work: float | None = None  # counted FLOPs per chunk; None: not measured
    candidate_work: float | None = None
    work_gated: bool = True
    # Instruction chains only (None otherwise): subtasks completed per chain, paired.
    baseline_length: float | None = None  # mean over the chains
    candidate_length: float | None = None
    length_drops: int = 0  # chains where the candidate completed fewer subtasks
    length_gains: int = 0
    length_p: float | None = None

    @property
    def success_regressed(self) -> bool:
        return self.p_value <= self.alpha

    @property
    def length_regressed(self) -> bool:
        return self.length_p is not None and self.length_p <= self.alpha

    @property
    def nfe_increased(self) -> bool:
        if self.baseline_nfe is None or self.candidate_nfe is None:
            return False
        return self.candidate_nfe > self.baseline_nfe * (1 + 1e-9) + 1e-12

    @property
    def work_increased(self) -> bool:
        if self.baseline_work is None or self.candidate_work is None:
            return False
        return self.candidate_work > self.baseline_work * (1 + 1e-9) + 1e-12


@dataclass(frozen=True)
class SpeedDiff:
    """tokens/s relative to the in-run reference decoder's, per pair: candidate run vs baseline run."""

    pair: str
    baseline_tokens_per_s: float
    candidate_tokens_per_s: float
    baseline_reference: float  # the reference decoder's tokens/s in the baseline run
    candidate_reference: float  # ... and in the candidate run, over the same episodes
    max_slowdown: float

    @property
    def baseline_ratio(self) -> float:
        return self.baseline_tokens_per_s / self.baseline_reference

    @property
    def candidate_ratio(self) -> float:
        return self.candidate_tokens_per_s / self.candidate_reference

    @property
    def change(self) -> float:
        return self.candidate_ratio / self.baseline_ratio - 1.0

    @property
    def regressed(self) -> bool:
        return self.change < -self.max_slowdown


@dataclass(frozen=True)
class GateResult:
    pairs: tuple[ConfigPair, ...]
    tasks: tuple[TaskDiff, ...]
    speed: tuple[SpeedDiff, ...]
    notes: tuple[str, ...] = field(default=())  # skipped comparisons and why
    # Pairs whose candidate raised in more episodes than the baseline did.
    raised: tuple[str, ...] = field(default=())
    # (pair label, why its speed was not compared): "not comparable: ..." in the table
    not_comparable: tuple[tuple[str, str], ...] = field(default=())
    reference: str = ""  # the label of the reference pair, whose ratio is 1 by definition
    warnings: tuple[str, ...] = field(default=())  # runs whose speed figures are unreliable
    # The runs' simulator versions differ (results/simulator_versions.py): '' or the sentence
    # naming them, put first among the failures when success drops.
    simulator_suspect: str = ""
    # Replay benchmark verdicts (results/replay.py ReplaySpeed), for pairs both runs benched:
    # these, not the closed-loop ratio in `speed`, decide those pairs' speed.
    replay: tuple[Any, ...] = field(default=())
    # ... and the work their decodes ran, counted at torch's dispatcher (ReplayWork)
    replay_work: tuple[Any, ...] = field(default=())
    # What an inconclusive replay verdict does: "pass" (a warning) or "fail" (--inconclusive)
    inconclusive: str = "pass"

    @property
    def failures(self) -> list[str]:
        out = list(self.raised)
        if self.simulator_suspect and any(t.success_regressed for t in self.tasks):
            out.insert(0, f"success: first suspect: {self.simulator_suspect}")
        for t in self.tasks:
            if t.success_regressed:
                out.append(
                    f"{t.pair} / {t.task}: success {t.baseline_successes} -> {t.candidate_successes} "
                    f"of {t.episodes} ({t.drops} drops, {t.gains} gains, p = {t.p_value:.3g} <= {t.alpha:.3g})"
                )
            if t.length_regressed:
                out.append(
                    f"{t.pair} / {t.task}: subtasks completed per chain {t.baseline_length:.2f} -> "
                    f"{t.candidate_length:.2f} ({t.length_drops} chains shorter, {t.length_gains} longer, "
                    f"p = {t.length_p:.3g} <= {t.alpha:.3g})"
                )
            if t.nfe_increased and t.nfe_gated:
                out.append(f"{t.pair} / {t.task}: NFE/chunk {t.baseline_nfe:.3f} -> {t.candidate_nfe:.3f}")
            if t.work_increased and t.work_gated:
                out.append(
                    f"{t.pair} / {t.task}: counted work {t.baseline_work / 1e9:.6g} -> "
                    f"{t.candidate_work / 1e9:.6g} GFLOP/chunk ({t.candidate_work / t.baseline_work - 1:+.2%})"
                )
        for w in self.replay_work:
            if w.increased and w.gated:
                out.append(f"{w.pair}: {w.describe()}")
        by_replay = {r.pair for r in self.replay}
        for r in self.replay:
            if r.verdict == "fail":
                out.append(f"{r.pair}: replay speed relative to the reference {r.describe()}")
            elif r.verdict == "inconclusive" and self.inconclusive == "fail":
                out.append(
                    f"{r.pair}: replay speed inconclusive, failed as asked (--inconclusive fail): {r.describe()}"
                )
        for s in self.speed:
            if s.regressed and s.pair not in by_replay:
                out.append(
                    f"{s.pair}: tokens/s relative to the reference {s.change:+.1%} "
                    f"({s.baseline_ratio:.3f} -> {s.candidate_ratio:.3f}x the reference's; "
                    f"allowed -{s.max_slowdown:.0%})"
                )
        return out

    @property
    def passed(self) -> bool:
        return not self.failures
