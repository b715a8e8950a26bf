"""The scripted expert carrying out a chain's first two subtasks on LIBERO's live state,
shared by each scene's test that an authored complement undoes its pair."""

from __future__ import annotations

from typing import Any

from adapters import chain_scenes as cs

Predicate = tuple[str, ...]


def expert_plays_a_pair(
    scene: str, chain: tuple[str, ...], done: Predicate, undone: Predicate, init_state_id: int = 0
) -> tuple[tuple[bool, bool], list[tuple[bool, bool]], dict[str, Any], dict[str, Any]]:
    """Run `chain` in `scene` with the expert until its second subtask ends.

    Returns what LIBERO's predicates say of (`done`, `undone`) at the reset and at the end of
    each of the first two subtasks, and the two subtasks' records (from LIBERO's initial
    state `init_state_id` of the scene's task). Fails the calling test
    when the chain ends first (a failed subtask)."""
    from adapters import chains
    from adapters.base import EpisodeSpec
    from policies.base import EpisodeContext
    from policies.experts.libero_scripted import LiberoScripted, LiberoScriptedParams

    suite = chains.load_suite(f"chains/{scene}")
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        obs, info = env.reset(
            options={"episode": EpisodeSpec(index=0, seed=0, init_state_id=init_state_id, chain=chain)}
        )
        at_start = (env.holds(done), env.holds(undone))
        expert = LiberoScripted(LiberoScriptedParams())

        def follow(info: dict[str, Any]) -> None:
            ctx = EpisodeContext(
                suite.name, task.name, info["instruction"], env.action_space, env.observation_space,
                cs.STEPS_PER_SUBTASK, 0, subtask_index=info["subtask_index"],
            )  # fmt: skip
            expert.reset([ctx])

        follow(info)
        seen = []
        for _ in range(2 * cs.STEPS_PER_SUBTASK):
            k = info["subtask_index"]
            obs, _, terminated, _, info = env.step(expert.act([obs]).actions[0, 0])
            if info["subtask_index"] != k:
                seen.append((env.holds(done), env.holds(undone)))
                if info["subtask_index"] == 2:
                    break
                follow(info)
            assert not terminated, info["subtasks"][:2]
        first, second = info["subtasks"][:2]
        return at_start, seen, first, second
    finally:
        env.close()


def put_in_tray(env: Any, groceries: tuple[str, ...]) -> None:
    """Move living_room_scene3's groceries into its tray by hand (MuJoCo's joint state), side
    by side, as a placement that knocks the next one in would; the next step settles them."""
    import numpy as np

    sim = env.inner.libero.env.sim
    tray = sim.data.body_xpos[sim.model.body_name2id("wooden_tray_1_main")].copy()
    offsets = np.linspace(-0.05, 0.05, len(groceries)) if len(groceries) > 1 else [0.0]
    for offset, grocery in zip(offsets, groceries, strict=True):
        joint = f"{grocery}_1_joint0"
        qpos = sim.data.get_joint_qpos(joint).copy()
        qpos[:2] = tray[:2] + np.array([offset, 0.0])  # over the tray
        qpos[2] += 0.02  # its height above the table, plus the tray's floor
        sim.data.set_joint_qpos(joint, qpos)
        sim.data.set_joint_qvel(joint, np.zeros(6))
    sim.forward()
