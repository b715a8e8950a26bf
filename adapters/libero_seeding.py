"""How a LIBERO episode's environment is seeded: upstream's way, one episode at a time.

Upstream evaluations (OpenVLA's `experiments/robot/libero/run_libero_eval.py` with
`libero_utils.get_libero_env`, openpi's `examples/libero/main.py`) build one
`OffScreenRenderEnv` per task, call `env.seed(S)` once (LIBERO's `seed` is
`np.random.seed`), then for trial j call `env.reset()` and
`env.set_init_state(initial_states[j])`. The reset is a hard reset (robosuite's default):
it rebuilds the model and draws, from numpy's global RNG, the robot's initialisation noise
(zero, but drawn), the articulated objects' joints and every fixture's and object's
placement. The initial state then overwrites the objects and joints, not the fixtures'
placement (a model parameter, `body_pos`/`body_quat`), so trial j's cabinet and stove
stand where the draws of the j resets before it left the RNG.

Two LIBERO details make a reset's draws more than a function of the RNG state, and a
soft reset (no model rebuild, ~20x faster) reproduces both:

- `object_property_initializers` (bddl_base_domain.py) gains one sampler per articulated
  object at every model load and is never cleared, so the hard reset numbered `loads`
  (0 after `env.seed`, retries included) draws each joint `loads + 2` times (the
  constructor's load, then one per reset).
- An object placed in a fixture's region (a bowl in a drawer) is placed relative to the
  region's site as the model last computed it (`SiteRegionRandomSampler` reads
  `site_xpos`), with rejection sampling, so the number of draws depends on where the
  fixture stood: after a hard reset, at its pose in the XML (the origin).

Episode j then needs the RNG as upstream's j-th reset finds it. It is kept per process
after every reset (`_MARKS`); an episode run alone (first in a process, on `--resume`)
seeds and replays the missing resets, each a soft reset of ~10-30 ms.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

# The env seed of each named seeding. OpenVLA's 7 (`cfg.seed`) seeds numpy and torch
# globally; its env seed is `env.seed(0)` in libero_utils.get_libero_env. openpi passes its
# `args.seed = 7` to `env.seed`. per_episode is this harness's old behaviour.
SEEDINGS = {"openvla": 0, "openpi": 7, "per_episode": 7}
DEFAULT_SEEDING = "openvla"
UPSTREAM = ("openvla", "openpi")  # seed once per task, episode j = upstream's j-th reset

# Attributes that move or turn a body in MJCF; a fixture's root body carries none in
# LIBERO's scenes, so its XML pose is the origin.
_POSE_ATTRIBUTES = ("pos", "quat", "euler", "axisangle", "xyaxes", "zaxis")


@dataclass(frozen=True)
class Mark:
    """The global RNG before one of upstream's resets, and the model loads before it."""

    rng: tuple[Any, ...]
    loads: int


# (BDDL file, env seed) -> marks[k]: the state before upstream's reset k.
_MARKS: dict[tuple[str, int], list[Mark]] = {}


@contextlib.contextmanager
def _fresh_data(sim: Any) -> Iterator[None]:
    """Make the robosuite env's `sim.reset()` leave the data as a newly built simulator has
    it: reset, then forward (robosuite's `_initialize_sim`). Without the forward, the
    solver's warm start differs and states drift by ~1e-13 after a few steps."""
    plain = sim.reset

    def reset() -> None:
        plain()
        sim.forward()

    sim.reset = reset
    try:
        yield
    finally:
        del sim.reset  # the class's method again


class HardResets:
    """Upstream's hard resets, made as soft ones on one built `ControlEnv`."""

    def __init__(self, libero: Any):
        inner = libero.env
        self.inner = inner
        # The constructor's model load appended one sampler per articulated object.
        self.properties = list(inner.object_property_initializers)
        model = inner.sim.model
        roots = [fixture.root_body for fixture in inner.fixtures_dict.values()]
        self.bodies = [model.body_name2id(name) for name in roots]
        self.pos, self.quat = self._xml_poses(roots)

    def _xml_poses(self, roots: list[str]) -> tuple[np.ndarray, np.ndarray]:
        """Each fixture's pose in the model's XML, where a hard reset's new model has it."""
        n = len(roots)
        pos, quat = np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        tree = self.inner.model.worldbody
        for name in roots:
            body = tree.find(f".//body[@name='{name}']")
            if body is None or any(body.get(a) is not None for a in _POSE_ATTRIBUTES):
                import mujoco  # posed in the XML: compile it once, exactly as MuJoCo reads it

                fresh = mujoco.MjModel.from_xml_string(self.inner.model.get_xml())
                return fresh.body_pos[self.bodies].copy(), fresh.body_quat[self.bodies].copy()
        return pos, quat

    def reset(self, loads: int) -> tuple[dict[str, Any], int]:
        """Upstream's reset after `loads` earlier hard resets (from `env.seed`); returns the
        observation and the loads after it. Like LIBERO's `ControlEnv.reset`, a placement
        that fails (RandomizationError) is drawn again, from a fresh model each time."""
        from robosuite.utils.errors import RandomizationError

        model = self.inner.sim.model
        while True:
            self.inner.object_property_initializers = self.properties * (loads + 2)
            model.body_pos[self.bodies] = self.pos
            model.body_quat[self.bodies] = self.quat
            loads += 1
            try:
                with _fresh_data(self.inner.sim):
                    return self.inner.reset(), loads
            except RandomizationError:
                continue


def upstream_reset(resets: HardResets, libero: Any, bddl: str, seed: int, j: int) -> dict[str, Any]:
    """Reset as upstream's j-th reset after one `env.seed(seed)`, leaving numpy's global RNG
    as upstream leaves it; the resets before j are replayed where this process has not
    made them yet (what they cost: docs/libero.md)."""
    marks = _MARKS.setdefault((bddl, seed), [])
    if not marks:
        libero.seed(seed)
        marks.append(Mark(np.random.get_state(), 0))
    k = min(j, len(marks) - 1)
    np.random.set_state(marks[k].rng)
    loads = marks[k].loads
    while True:
        raw, loads = resets.reset(loads)
        k += 1
        if k == len(marks):
            marks.append(Mark(np.random.get_state(), loads))
        if k > j:
            return raw
