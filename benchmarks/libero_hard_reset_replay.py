"""This harness's LIBERO env against LIBERO's own `ControlEnv` run as openpi's loop runs it
(hard resets, `env.seed(7)`, initial state j, 10 settle steps), in one process, on one
recorded episode: the largest difference in the full simulator state (qpos, qvel, the
solver's warm start, ...) after settling, then the first step of the recorded actions
(gripper by sign, as vla-eval executes it) where qpos or qvel differ. No cameras: they
move no physics (`--cameras` builds upstream's env as vla-eval does, with them). docs/libero.md, "vla-eval on the same episodes".

    python benchmarks/libero_hard_reset_replay.py --suite object --task 1 --demos demos/vlaeval-object
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

FIELDS = ("qpos", "qvel", "qacc_warmstart", "act", "ctrl", "qfrc_applied")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--suite", default="object")
    parser.add_argument("--task", type=int, default=1)
    parser.add_argument("--episode", type=int, default=0)
    parser.add_argument(
        "--cameras",
        action="store_true",
        help="upstream's env as vla-eval builds it (OffScreenRenderEnv, 256 px)",
    )
    parser.add_argument(
        "--demos", required=True, help="the scripted expert's episodes (collect --split eval)"
    )
    args = parser.parse_args()

    from libero.libero.envs.env_wrapper import ControlEnv

    from adapters.libero_sim import configure_libero
    from adapters.registry import load_suite
    from policies.playback import load_demos

    configure_libero()
    suite = load_suite(f"libero/{args.suite}:obs=state,seeding=openpi")
    task = suite.tasks[args.task]
    env = suite.make_env(task)
    env.reset(options={"episode": task.episodes[args.episode]})
    ours = env.unwrapped.libero.env.sim.data
    if args.cameras:
        from libero.libero.envs import OffScreenRenderEnv

        upstream = OffScreenRenderEnv(
            bddl_file_name=env.unwrapped._bddl, camera_heights=256, camera_widths=256
        )
    else:
        upstream = ControlEnv(
            bddl_file_name=env.unwrapped._bddl,
            has_renderer=False,
            has_offscreen_renderer=False,
            use_camera_obs=False,
            hard_reset=True,
        )
    upstream.seed(7)
    upstream.reset()
    upstream.set_init_state(env.unwrapped.init_states[args.episode])
    for _ in range(10):
        upstream.step([0, 0, 0, 0, 0, 0, -1])
    theirs = upstream.env.sim.data
    for name in FIELDS:
        a, b = np.asarray(getattr(ours, name)), np.asarray(getattr(theirs, name))
        print(f"after settling, max |difference| in {name}: {float(np.abs(a - b).max()) if a.size else 0.0}")
    _, episodes = load_demos(Path(args.demos))
    actions = episodes[(task.name, args.episode)].actions.copy()
    actions[:, -1] = np.where(actions[:, -1] < 0, -1.0, 1.0)
    for step, action in enumerate(actions):
        env.step(action.astype(np.float32))
        upstream.step(action)
        diff = max(float(np.abs(getattr(ours, k) - getattr(theirs, k)).max()) for k in ("qpos", "qvel"))
        if diff > 0:
            print(f"qpos/qvel first differ after step {step}: {diff}")
            return
    print(f"qpos and qvel equal after every one of the {len(actions)} steps")


if __name__ == "__main__":
    main()
