"""The drawer expert's geometry, without the simulator (tests/test_libero.py runs it)."""

from __future__ import annotations

import numpy as np

from policies.experts.libero_drawer import HANDLES, drawer_plan, pitched_rotation
from policies.experts.libero_pick import rotation_error

SLICES = {
    "wooden_cabinet_1": slice(16, 23),
    "wooden_cabinet_1_top_region": slice(23, 26),
    "plate_1": slice(26, 33),
}


def test_a_drawer_region_gives_its_cabinet_handle_and_region():
    plan = drawer_plan(SLICES, ["wooden_cabinet_1", "plate_1"], "wooden_cabinet_1_top_region")
    assert plan is not None
    assert (plan.cabinet, plan.region) == (slice(16, 23), slice(23, 26))
    assert plan.handle == HANDLES["wooden_cabinet"]["top"] and plan.category == "wooden_cabinet"


def test_regions_that_are_not_a_known_drawer_give_none():
    entities = ["wooden_cabinet_1", "plate_1"]
    assert drawer_plan(SLICES, entities, "main_table_plate_region") is None
    # a drawer level the cabinet does not have, and a drawer region not in the state
    assert drawer_plan(SLICES, entities, "wooden_cabinet_1_fourth_region") is None
    assert drawer_plan(SLICES, entities, "wooden_cabinet_1_middle_region") is None


def test_the_pitched_hand_points_into_the_cabinet_and_closes_vertically():
    home = np.diag([1.0, -1.0, -1.0])  # LIBERO's start: fingers down, closing along world y
    for pull in (np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])):
        rot = pitched_rotation(home, pull)
        assert np.allclose(rot.T @ rot, np.eye(3)) and np.isclose(np.linalg.det(rot), 1.0)
        assert np.allclose(rot[:, 2], -pull)  # the fingers point along -pull
        assert np.allclose(np.abs(rot[:, 1]), [0.0, 0.0, 1.0])  # they close vertically
    # of the two vertical closings, the one nearer the start: a quarter turn, not more
    assert np.isclose(
        np.linalg.norm(rotation_error(pitched_rotation(home, np.array([0.0, 1.0, 0.0])), home)), np.pi / 2
    )


def test_a_half_turn_is_an_error_of_pi_not_zero():
    # The pitched pose of the other vertical closing is half a turn from the chosen one;
    # the axis-angle of a half turn has no antisymmetric part to read the axis from.
    half = np.diag([-1.0, -1.0, 1.0])
    error = rotation_error(half, np.eye(3))
    assert np.isclose(np.linalg.norm(error), np.pi) and np.allclose(np.abs(error), [0.0, 0.0, np.pi])
