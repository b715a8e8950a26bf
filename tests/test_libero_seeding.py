"""LIBERO's env seeding: episode j is upstream's j-th reset after one `env.seed`, however run.

The reference is the loop of OpenVLA's run_libero_eval.py and openpi's examples/libero/main.py
on LIBERO's own env class: `env.seed(S)` once, then `reset()` + `set_init_state(j)` and the
settle steps, in order, with robosuite's default hard reset. `ControlEnv` is the base of
upstream's `OffScreenRenderEnv`, which only adds the renderer (no RNG draws; checked while
writing the adapter). A hard reset spends ~90% of its time compiling the same XML into the
same model, so the reference compiles each XML once and hands every reset a copy of that
model: a compile is deterministic, so this changes nothing but the time (50 hard resets
take ~1-2 min here, ~15 s this way).
"""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from adapters import libero as lb
from adapters import libero_seeding

pytestmark = pytest.mark.libero
needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")

# Spatial task 4, the bowl in the cabinet's top drawer: both details a soft reset must
# reproduce (libero_seeding's docstring) change its draws, the drawer's joint sampler and
# the bowl placed in the drawer's region.
KEY, TASK = "spatial", 4


def test_seeding_option_names_the_choice():
    assert libero_seeding.SEEDINGS == {"openvla": 0, "openpi": 7, "per_episode": 7}
    assert lb.Options().seeding == "openvla" == libero_seeding.DEFAULT_SEEDING
    assert lb.parse_options("").suffix() == ":seeding=openvla"  # always named: it moves scores
    assert lb.parse_options("obs=images,seeding=openpi").suffix() == ":obs=images,seeding=openpi"
    with pytest.raises(lb.SuiteOptionError, match="openvla or openpi or per_episode"):
        lb.parse_options("seeding=7")


@pytest.fixture
def compile_once(monkeypatch):
    """Hard resets that compile each XML once (see the module docstring)."""
    import mujoco
    from robosuite.utils import binding_utils
    from robosuite.utils.binding_utils import MjSim

    compiled: dict[str, mujoco.MjModel] = {}

    def from_xml_string(cls, xml):
        if xml not in compiled:
            compiled[xml] = mujoco.MjModel.from_xml_string(xml)
        return cls(copy.copy(compiled[xml]))

    monkeypatch.setattr(MjSim, "from_xml_string", classmethod(from_xml_string))
    # Each hard reset also runs a full garbage collection when it frees the old simulator.
    monkeypatch.setattr(binding_utils, "gc", SimpleNamespace(collect=lambda: 0))
    return compiled


def _snapshot(inner) -> dict[str, np.ndarray]:
    """The fixtures' placement, the physics state after settling (every body's pose, the
    sites, joints, velocities, warm start: the observation is made of these) and numpy's
    global RNG."""
    model, data = inner.sim.model, inner.sim.data
    roots = [model.body_name2id(f.root_body) for f in inner.fixtures_dict.values()]
    return {
        "fixtures": np.concatenate([model.body_pos[roots], model.body_quat[roots]], axis=1),
        "state": np.concatenate([[data.time], data.qpos, data.qvel, data.qacc_warmstart, data.act]),
        "bodies": np.concatenate([data.xpos.ravel(), data.xquat.ravel(), data.site_xpos.ravel()]),
        "rng": np.random.get_state()[1].copy(),
    }


def _upstream(seed: int, episodes: int) -> list[dict[str, np.ndarray]]:
    """run_libero_eval.py's loop for one task (the policy's steps draw nothing from numpy)."""
    from libero.libero.envs.env_wrapper import ControlEnv

    bench = lb.benchmark(KEY)
    initial_states = bench.get_task_init_states(TASK)
    env = ControlEnv(  # hard_reset=True: robosuite's default, what upstream gets
        bddl_file_name=bench.get_task_bddl_file_path(TASK),
        has_renderer=False,
        has_offscreen_renderer=False,
        use_camera_obs=False,
    )
    env.seed(seed)
    out = []
    try:
        for j in range(episodes):
            env.reset()
            env.set_init_state(initial_states[j])
            for _ in range(lb.SETTLE_STEPS):
                env.step(list(lb.NOOP_ACTION))
            out.append(_snapshot(env.env))
    finally:
        env.close()
    return out


def _ours(seeding: str, episodes) -> dict[int, dict[str, np.ndarray]]:
    suite = lb.load_suite(f"libero/{KEY}:seeding={seeding}")
    task = suite.tasks[TASK]
    env = suite.make_env(task)
    out = {}
    try:
        for j in episodes:
            obs, _ = env.reset(options={"episode": task.episodes[j]})
            out[j] = {**_snapshot(env.libero.env), "obs": obs}
    finally:
        env.close()
    return out


def _assert_same(ours: dict[str, np.ndarray], theirs: dict[str, np.ndarray], label: str) -> None:
    for field, value in theirs.items():
        assert np.array_equal(ours[field], value), f"{label}: {field} differs"


@needs_libero
def test_every_episode_is_upstreams_and_the_same_when_run_alone(compile_once, monkeypatch):
    """All 50 episodes of a task against upstream's loop (openvla: env.seed(0)), then some
    run alone, out of order, from a fresh process's state: bit for bit the same."""
    n = lb.EPISODES_PER_TASK
    monkeypatch.setattr(libero_seeding, "_MARKS", {})
    theirs = _upstream(libero_seeding.SEEDINGS["openvla"], n)
    in_order = _ours("openvla", range(n))
    for j in range(n):
        _assert_same(in_order[j], theirs[j], f"episode {j}")
    # Not vacuous: the cabinet and the stove stand somewhere else in every episode.
    assert len({r["fixtures"].tobytes() for r in theirs}) == n

    monkeypatch.setattr(libero_seeding, "_MARKS", {})  # as in a new process (--resume)
    alone = _ours("openvla", [37, 45, 5])  # replays 0-36, then 38-44, then nothing
    for j, row in alone.items():
        _assert_same(row, in_order[j], f"episode {j} alone")
        assert np.array_equal(row["obs"], in_order[j]["obs"]), f"episode {j} alone: observation"


@needs_libero
def test_openpi_seeding_is_upstreams_with_seed_7(compile_once, monkeypatch):
    monkeypatch.setattr(libero_seeding, "_MARKS", {})
    theirs = _upstream(7, 3)
    ours = _ours("openpi", [2, 0])
    for j in (0, 2):
        _assert_same(ours[j], theirs[j], f"openpi episode {j}")
    assert lb.load_suite("libero/spatial:seeding=openpi").tasks[0].episodes[3].seed == 7


@needs_libero
def test_per_episode_seeding_is_the_old_behaviour(monkeypatch):
    """Seed 7 before every reset (how runs before the upstream seeding were made): one
    placement for every episode of a task, none of upstream's."""
    monkeypatch.setattr(libero_seeding, "_MARKS", {})
    ours = _ours("per_episode", [3, 0])
    assert np.array_equal(ours[0]["fixtures"], ours[3]["fixtures"])
    upstream = _ours("openvla", [0, 3])
    assert not np.array_equal(ours[0]["fixtures"], upstream[0]["fixtures"])
    assert not np.array_equal(upstream[0]["fixtures"], upstream[3]["fixtures"])
