"""Which goals already hold where the stored chains start, on the live LIBERO state.

Under CALVIN's credit rule (adapters/chain_credit.py) a subtask whose goal already holds
when it takes over fails the chain. The precondition model cannot see that for goals
the BDDL's :init does not list (LIBERO's initial states are sampled, and the model knows
only the :init predicates), so this checks each stored chain's initial state itself:
after LIBERO's settle steps, which of the scene's goals hold, and which of them a later
subtask of that chain has that no earlier subtask undoes first (in the scene's model: a
chain that would fail there, or count differently under the two rules):

    python -m adapters.chain_starts living_room_scene3 --chains 50

Resetting is cheap (no policy, no chain steps): about 0.4 s a chain here.
"""

from __future__ import annotations

import argparse
import sys

from adapters import chain_scenes as cs
from adapters.chain_credit import Holds, goal_holds


def later_goals_holding(scene: cs.Scene, chain: tuple[str, ...], holds: Holds) -> list[tuple[int, str]]:
    """(position, id) of each subtask after the first whose goal holds in `holds` and that
    no earlier subtask of the chain undoes first (removes, in the scene's model): a pot
    back on its starting region holds at the start, and "take the pot off the stove"
    comes only after "put the pot on the stove", which undoes it."""
    found, undone = [], set()
    for k, sid in enumerate(chain):
        subtask = scene.subtask(sid)
        if k > 0 and not set(subtask.goal) & undone and goal_holds(subtask, holds):
            found.append((k, sid))
        undone = (undone | set(subtask.removes)) - set(subtask.goal)
    return found


def check_starts(scene_name: str, count: int) -> list[dict]:
    """Per chain (the first `count`): the scene's subtasks whose goals hold at its start,
    and those of them that are later subtasks of the chain."""
    from adapters import chains

    suite = chains.load_suite(f"{chains.PREFIX}{scene_name}")
    task = suite.tasks[0]
    env = suite.make_env(task)
    scene = cs.load_scene(scene_name)
    out = []
    try:
        for spec in task.episodes[:count]:
            env.inner.reset(seed=spec.seed, options={"episode": spec})  # no chain check: just the state
            held = [s.id for s in scene.subtasks if goal_holds(s, env.holds)]
            later = later_goals_holding(scene, spec.chain, env.holds)
            out.append({"chain": spec.index, "goals_held": held, "later_in_chain": later})
    finally:
        env.close()
    return out


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m adapters.chain_starts",
        description="On each stored chain's initial state (live LIBERO predicates), which goals "
        "already hold, and whether a later subtask of the chain has one of them.",
    )
    parser.add_argument("scene", choices=cs.scene_names(), help="the chain scene")
    parser.add_argument(
        "--chains", type=int, default=cs.CHAINS_PER_SCENE, help=f"the first N (default {cs.CHAINS_PER_SCENE})"
    )
    args = parser.parse_args(argv)
    if args.chains < 1:
        print("error: --chains must be at least 1", file=sys.stderr)
        return 2
    try:
        rows = check_starts(args.scene, args.chains)
    except cs.ChainDataError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for row in rows:
        if row["goals_held"]:
            print(f"chain {row['chain']}: goals held at the start {row['goals_held']}; later in the chain: "
                  f"{row['later_in_chain'] or 'none'}")  # fmt: skip
    affected = sum(bool(r["later_in_chain"]) for r in rows)
    held = sum(bool(r["goals_held"]) for r in rows)
    print(
        f"{args.scene}: {len(rows)} chains; a goal holds at the start of {held}; a later subtask's "
        f"goal holds at the start of {affected}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(_main())
