"""How far a replay verdict can be trusted: what the candidate's bench ran under.

The gate's speed verdict is drawn from the candidate bench's per-round ratios
(results/replay.py); the interval says how noisy they were, not whether the machine
moved them. Two things do, measured on the project's 2-core EPYC
(benchmarks/replay_load.py, docs/ci-gate.md "What load does to the ratio"): a busy
machine makes the reference itself decode slower, in CPU time, than in the baseline's
bench, and contention costs the candidate's small passes more than the reference's
full-width ones, so the ratio reads slower than it is; and decodes that wait for a core
(wall time above CPU time) widen the interval without moving its middle. Both are
measured from the benches and said beside the verdict, so a red or green gate says
which instrument decided and how steady it was.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

# Beyond this, the reference decoded slower (CPU time per chunk) than in the baseline's
# bench by enough that the ratio itself moves: a busy machine's contention costs
# fast_dvla's small passes more than bidirectional's full-width ones (docs/ci-gate.md,
# "What load does to the ratio"; benchmarks/replay_load.py).
BUSIER_MACHINE = 1.3
WAITED = 1.25  # wall over CPU time of the bench's decodes: they waited for a core (cpu_time.py)


@dataclass(frozen=True)
class BenchConditions:
    """What the candidate's bench ran under: how its rounds ended, whether its decodes
    waited for a core, and how fast the machine decoded the reference compared with the
    baseline's bench. The verdict is drawn from the candidate's ratio; these say how far
    that ratio can be trusted."""

    stopped: str  # "settled" (the stopping rule), "cap" (all rounds allowed), "fixed" (no rule)
    max_rounds: int
    waited: float | None  # the decodes' wall time over their CPU time, all configurations
    busier: (
        float | None
    )  # the reference's median s/chunk (CPU time where both benches have it), candidate / baseline

    def doubts(self) -> list[str]:
        """Why the figure may read slower or noisier than the decoders are (empty: none seen)."""
        out = []
        if self.busier is not None and self.busier > BUSIER_MACHINE:
            out.append(
                f"the reference decoded {self.busier:.2f}x slower than in the baseline's bench (a busier "
                "machine): contention costs small passes more than full-width ones, so the ratio reads "
                "slower than it is (docs/ci-gate.md, what load does to the ratio)"
            )
        if self.waited is not None and self.waited > WAITED:
            out.append(
                f"its decodes waited for a core (wall time {self.waited:.2f}x their CPU time): a noisier "
                "figure, a wider interval"
            )
        return out

    def describe(self, rounds: int) -> str:
        how = {"settled": "settled early", "cap": "the cap", "fixed": "fixed"}.get(self.stopped, self.stopped)
        return f"{rounds} rounds ({how}, at most {self.max_rounds})"


def bench_conditions(
    baseline: Mapping[str, Any], candidate: Mapping[str, Any], reference_b: str, reference_c: str
) -> BenchConditions:
    """The candidate bench's conditions against the baseline bench; reference_b and
    reference_c: the reference decoder's policy_config_id in each."""
    rule = candidate.get("sequential") or {}
    configs = candidate["configurations"]
    cpu = [c.get("round_cpu_chunk_s") for c in configs]
    waited = None
    if cpu and all(
        isinstance(v, list) and len(v) == len(c["round_chunk_s"]) for v, c in zip(cpu, configs, strict=True)
    ):
        used = sum(sum(v) for v in cpu)
        waited = sum(sum(c["round_chunk_s"]) for c in configs) / used if used > 0 else None

    def reference_s(replay: Mapping[str, Any], config_id: str, key: str) -> float | None:
        found = next((c for c in replay["configurations"] if str(c["policy_config_id"]) == config_id), None)
        values = found.get(key) if found else None
        return float(np.median(values)) if isinstance(values, list) and values else None

    # CPU time where a bench has it (the machine's speed, not its waiting; a baseline
    # benched on a quiet machine waited for nothing, so its wall time stands in)
    seconds = [
        reference_s(replay, config_id, "round_cpu_chunk_s") or reference_s(replay, config_id, "round_chunk_s")
        for replay, config_id in ((baseline, reference_b), (candidate, reference_c))
    ]
    busier = seconds[1] / seconds[0] if seconds[0] and seconds[1] else None
    return BenchConditions(
        "fixed" if not rule else rule.get("stopped", "fixed"),
        int(candidate.get("max_rounds") or candidate.get("rounds") or 0),
        waited,
        busier,
    )
