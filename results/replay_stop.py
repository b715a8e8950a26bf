"""When the replay benchmark may stop timing: a sequential rule on the gate's own verdict.

A fixed number of rounds is too many on a quiet machine, where ten rounds already
settle the verdict, and costs minutes a CI job does not have on a loaded one. So when
`dvla-harness bench` decodes a baseline's observations and that baseline was benched
(`--observations BASELINE_DIR`), it computes the gate's verdict (results/replay.py) as it
goes and takes more rounds only while the interval straddles the allowed slowdown, up to
a fixed cap, as pyperf calibrates its loops until the figure is stable and no longer.

Looks: after `min_rounds`, then every `step` rounds, until the cap. At each look each
judged configuration's change against the baseline bench is bootstrapped at a confidence
raised for the number of looks (Bonferroni: 1 - 0.05 / looks), and timing stops when
every one is settled at it: the whole interval beyond the allowed slowdown (fail) or
none of it (pass). Why raised: each look is one more chance that noise put an interval on
the wrong side; splitting the 5% over the looks keeps the chance that any look stops on a
wrong verdict at or below that of one look at 95%. And the wider interval holds the
gate's 95% one (the same seeded resamples, a wider percentile range), so a verdict
settled at a look is the verdict the gate reads from the rounds written: stopping early
changes how many rounds there are, never what they say. At the cap timing stops
whatever the interval says, and the gate decides (inconclusive, if it still straddles).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from results.replay import CONFIDENCE, ReplaySpeed, paired_ratios, replay_speed

LOOK_EVERY = 5  # rounds between looks after the first


@dataclass(frozen=True)
class JudgedPair:
    """A configuration of the bench and the baseline bench's configuration it is judged
    against (policy_config_ids), by the name the verdict gives it."""

    label: str
    candidate_id: str
    baseline_id: str


@dataclass(frozen=True)
class StoppingRule:
    """Stop once every pair's replay verdict against the baseline is settled (module doc)."""

    baseline_rounds: Mapping[str, Sequence[float]]  # the baseline bench: config id -> s/chunk per round
    pairs: tuple[JudgedPair, ...]  # the reference's own pair left out
    reference: JudgedPair
    max_slowdown: float
    min_rounds: int
    cap: int
    step: int = LOOK_EVERY

    def looks(self) -> list[int]:
        """The round counts after which the rule looks: min_rounds, every `step`, the cap."""
        first = min(self.min_rounds, self.cap)
        return sorted({*range(first, self.cap, self.step), self.cap})

    @property
    def confidence(self) -> float:
        return 1.0 - (1.0 - CONFIDENCE) / len(self.looks())

    def verdicts(self, rounds: Mapping[str, Sequence[float]]) -> list[ReplaySpeed]:
        """Each pair's verdict on the rounds so far, at the rule's raised confidence."""
        base_ref = self.baseline_rounds[self.reference.baseline_id]
        cand_ref = rounds[self.reference.candidate_id]
        return [
            replay_speed(
                pair.label,
                paired_ratios(self.baseline_rounds[pair.baseline_id], base_ref),
                paired_ratios(rounds[pair.candidate_id], cand_ref),
                self.max_slowdown,
                confidence=self.confidence,
            )
            for pair in self.pairs
        ]

    def settled(self, rounds: Mapping[str, Sequence[float]]) -> bool:
        """At a look: is every pair's verdict settled (pass or fail)? Between looks: no."""
        done = len(rounds[self.reference.candidate_id])
        if done not in self.looks() or done == self.cap:
            return False
        return all(v.verdict != "inconclusive" for v in self.verdicts(rounds))

    def record(self, rounds: Mapping[str, Sequence[float]]) -> dict[str, object]:
        """What replay.json says about the rule and where it stopped."""
        done = len(rounds[self.reference.candidate_id])
        verdicts = self.verdicts(rounds) if done >= 2 else []
        settled = bool(verdicts) and all(v.verdict != "inconclusive" for v in verdicts)
        return {
            "rule": "more rounds only while the interval straddles the allowed slowdown",
            "min_rounds": self.min_rounds,
            "max_rounds": self.cap,
            "look_every": self.step,
            "looks": self.looks(),
            "look_confidence": self.confidence,
            "max_slowdown": self.max_slowdown,
            "reference": self.reference.label,
            "rounds": done,
            "stopped": "settled" if settled and done < self.cap else "cap",
            "verdicts": {v.pair: v.verdict for v in verdicts},
        }
