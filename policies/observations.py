"""How observations are named and stored, shared by collection (harness/collect.py),
training (policies/training.py) and the decoder policies (policies/dvla.py), so that
what a demonstration records and what a checkpoint reads cannot drift apart."""

from __future__ import annotations

import io

import gymnasium as gym
import numpy as np


def cameras_of(space: gym.Space) -> list[str]:
    """The image keys of a dict observation space (everything but "state"), sorted."""
    if isinstance(space, gym.spaces.Dict):
        return sorted(k for k in space.spaces if k != "state")
    return []


def png(pixels: np.ndarray) -> bytes:
    """Lossless; compression level 1 because collection is CPU-bound."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels, dtype=np.uint8)).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def unpng(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
