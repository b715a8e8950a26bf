"""Unmasking schedules and confidence measures: the knobs that noise-schedule ablations vary.

Pure Python (no torch), so policy parameters can name their valid choices without
loading a model.
"""

from __future__ import annotations

import math

SCHEDULES = ("cosine", "linear", "concave")
CONFIDENCES = ("max_prob", "margin", "entropy", "random")  # policies/dvla/decoding.py says what each is


def still_masked(schedule: str, step: int, steps: int, total: int) -> int:
    """How many of `total` tokens stay masked after `step` of `steps` (0 after the last)."""
    r = step / steps
    frac = {"cosine": math.cos(math.pi / 2 * r), "linear": 1 - r, "concave": 1 - r * r}[schedule]
    return min(total, max(0, math.ceil(total * frac - 1e-9)))


# Fast-dLLM's approximate KV cache (policies/dvla/fast_dllm.py): what a step inside a block reuses.
CACHE_MODES = ("dual", "prefix", "none")
