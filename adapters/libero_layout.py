"""The LIBERO state observation, laid out from a task's BDDL alone: the robot's
proprioception, then one pose per object and fixture, one position per goal region, and
the scene's joints last (docs/libero.md has the table). The scripted expert and the
chain scenes find their slices here without building a simulator; `obs=upstream`'s 8-D
state (openpi's) needs `quat2axisangle`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

PROPRIO = (("eef_pos", 3), ("eef_quat", 4), ("gripper_qpos", 2), ("joint_pos", 7))
PROPRIO_DIM = sum(n for _, n in PROPRIO)  # 16
POSE_DIM = 7  # an entity's world position (3) and quaternion (4, xyzw like robosuite)
SITE_DIM = 3  # a goal region's world position

# --- obs=upstream's state: openpi's examples/libero/main.py `observation/state`, 8 numbers:
# eef position (3), axis-angle of the eef quaternion (3), finger joint positions (2).


def quat2axisangle(quat: Any) -> np.ndarray:
    """openpi's `_quat2axisangle` (robosuite's `transform_utils.quat2axisangle`, copied):
    quaternion xyzw -> axis * angle with angle = 2 acos(w) in [0, 2 pi], not folded to
    [0, pi], exactly as upstream trained on; `quat` itself is left as it is (upstream clips
    it in place)."""
    q = np.array(quat, dtype=np.float64)
    q[3] = min(max(q[3], -1.0), 1.0)
    den = np.sqrt(1.0 - q[3] * q[3])
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return (q[:3] * 2.0 * math.acos(q[3])) / den


def _is_scenery(category: str) -> bool:
    return category.endswith("table") or category == "floor"


def entity_names(problem: dict[str, Any]) -> list[str]:
    """Objects, then fixtures other than the table/floor, in BDDL order: one pose each."""
    objects = [n for names in problem["objects"].values() for n in names]
    fixtures = [n for cat, names in problem["fixtures"].items() if not _is_scenery(cat) for n in names]
    return objects + fixtures


def goal_sites(problem: dict[str, Any]) -> list[str]:
    """Goal arguments that are regions (sites), not entities, in order of appearance."""
    entities = {n for names in problem["objects"].values() for n in names}
    entities |= {n for names in problem["fixtures"].values() for n in names}
    sites: list[str] = []
    for predicate in problem["goal_state"]:
        for arg in predicate[1:]:
            if arg not in entities and arg not in sites:
                sites.append(arg)
    return sites


def state_layout(problem: dict[str, Any], joints: tuple[str, ...] = ()) -> list[tuple[str, int, int]]:
    """(name, start, stop) of each field of the state vector; joints come last, so the
    entity and site slices are known from the BDDL alone (the scripted expert uses that)."""
    fields = list(PROPRIO)
    fields += [(name, POSE_DIM) for name in entity_names(problem)]
    fields += [(name, SITE_DIM) for name in goal_sites(problem)]
    fields += [(name, 1) for name in joints]
    layout, start = [], 0
    for name, width in fields:
        layout.append((name, start, start + width))
        start += width
    return layout


def state_positions(layout: list[tuple[str, int, int]]) -> tuple[int, ...]:
    """Where the state holds world positions: the end effector's, then each entity's and
    goal region's (adapters/base.py); a policy may read their offsets from the hand."""
    proprio = dict(PROPRIO)
    entities = (start for name, start, stop in layout if name not in proprio and stop - start > 1)
    return (0, *entities)
