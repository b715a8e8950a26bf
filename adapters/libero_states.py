"""Fresh LIBERO initial states: drawn from a task's BDDL distribution, checked against evaluation.

LIBERO's 50 initial states per task (`init_files/*.pruned_init`) are what its env's reset
leaves after the placement initializers run: robosuite's samplers put every object and
fixture in its BDDL region, and the flattened simulator state (time, qpos, qvel) is saved.
Demonstrations collected on those same 50 states make a trained model's evaluation a
memory test, where upstream's demonstrations came from other draws. `initial_states=fresh`
makes the draw again, from numpy's global RNG seeded per episode with
`derive_seed("libero-fresh", states_seed, task, j)`: a reset that runs the placement
initializers (libero_seeding.HardResets: what a hard reset of a new env draws), whose
state is then restored exactly as an evaluation state would be.

Disjointness is checked, not assumed: every fresh state's sha256 is compared with the
task's 50 evaluation states' (an equal one is refused), and its distance to them is the
minimum over evaluation states of the largest object displacement (metres), which
`collect` reports. Continuous draws make equality practically impossible; the distance
says how far apart the two sets actually are.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from adapters.base import derive_seed

INITIAL_STATES = ("evaluation", "fresh")
DEFAULT_STATES_SEED = 0
# Fresh episodes a task offers: enough for any collection here, each its own draw.
FRESH_EPISODES_PER_TASK = 1000
_FREE_JOINT = 0  # mjtJoint.mjJNT_FREE: an object lying loose (position 3, quaternion 4)


class InitialStateOverlap(ValueError):
    """A fresh initial state equals one of the task's evaluation states."""


def state_sha256(state: Any) -> str:
    """sha256 of a flattened simulator state as float64 bytes (the init files' dtype)."""
    return hashlib.sha256(np.ascontiguousarray(state, dtype=np.float64).tobytes()).hexdigest()


def fresh_seed(states_seed: int, task: str, j: int) -> int:
    """The RNG seed of fresh episode j of a task."""
    return derive_seed("libero-fresh", states_seed, task, j)


def object_position_slices(model: Any) -> list[slice]:
    """Where each loose object's world position sits in a flattened state
    ([time, qpos, qvel]): its free joint's first three qpos entries, after the time."""
    return [
        slice(1 + int(model.jnt_qposadr[j]), 4 + int(model.jnt_qposadr[j]))
        for j in range(model.njnt)
        if model.jnt_type[j] == _FREE_JOINT
    ]


def object_positions(states: np.ndarray, slices: list[slice]) -> np.ndarray:
    """(states, objects, 3) world positions of the loose objects."""
    states = np.atleast_2d(np.asarray(states, dtype=np.float64))
    return np.stack([states[:, s] for s in slices], axis=1)


@dataclass(frozen=True)
class StateCheck:
    """A fresh state against the task's evaluation states."""

    sha256: str
    distance: float  # min over evaluation states of the largest object displacement (m)
    overlap: bool  # its hash equals an evaluation state's


class EvaluationStates:
    """A task's evaluation states, as hashes and object positions, to check fresh ones."""

    def __init__(self, init_states: Any, model: Any):
        states = np.asarray(init_states, dtype=np.float64)
        self.hashes = {state_sha256(s): j for j, s in enumerate(states)}
        self.slices = object_position_slices(model)
        self.positions = object_positions(states, self.slices)

    def check(self, state: np.ndarray) -> StateCheck:
        digest = state_sha256(state)
        fresh = object_positions(state, self.slices)  # (1, objects, 3)
        gaps = np.linalg.norm(self.positions - fresh, axis=2).max(axis=1)  # per evaluation state
        return StateCheck(digest, float(gaps.min()), digest in self.hashes)


def sample_state(resets: Any, seed: int) -> np.ndarray:
    """The flattened state after a reset that runs the placement initializers from numpy's
    global RNG seeded with `seed` (the first hard reset of a newly seeded env)."""
    np.random.seed(seed)
    resets.reset(0)
    return np.asarray(resets.inner.sim.get_state().flatten(), dtype=np.float64)


def draw_fresh(resets: Any, evaluation: EvaluationStates, seed: int) -> tuple[np.ndarray, StateCheck]:
    """A fresh state and its check; refuses one equal to an evaluation state."""
    state = sample_state(resets, seed)
    check = evaluation.check(state)
    if check.overlap:
        raise InitialStateOverlap(
            f"fresh initial state (seed {seed}) equals evaluation initial state "
            f"{evaluation.hashes[check.sha256]} (sha256 {check.sha256[:12]}); "
            "refusing to train on an evaluation state"
        )
    return state, check
