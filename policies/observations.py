"""How observations are named and stored, shared by collection (harness/collect.py),
training (policies/dvla/training.py) and the decoder policies (policies/dvla/policy.py), so that
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


def relative_positions(states: np.ndarray, positions: tuple[int, ...]) -> np.ndarray:
    """States with each world position minus the end effector's appended.

    `positions` are start indices of 3-D world positions in the state vector, the end
    effector's first (the env's `state_positions`, adapters/base.py). A small model reads
    absolute coordinates through one MLP and has to learn their differences itself; on
    LIBERO that is where its reach lost centimetres. Empty `positions`: states unchanged.
    """
    states = np.asarray(states, dtype=np.float32)
    if not positions:
        return states
    anchor = states[..., positions[0] : positions[0] + 3]
    offsets = [states[..., p : p + 3] - anchor for p in positions[1:]]
    return np.concatenate([states, *offsets], axis=-1)
