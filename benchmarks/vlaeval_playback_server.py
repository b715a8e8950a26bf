"""The `playback` policy as a vla-eval model server of vla-eval's own making: a subclass
of its `PredictModelServer`, served by its own `serve`, so a throughput figure for
vla-eval carries none of this harness's serving code. It asks its benchmark for nothing
beyond the default (the agentview image), since playback reads no observation.

    python benchmarks/vlaeval_playback_server.py --demos DIR --suite libero/spatial:seeding=openpi --port 8001

Episode j of task i (vla-eval's task_id, episode_idx) plays the actions recorded for
episode j of the suite's task i, one per observation, the gripper by sign.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
from vla_eval.model_servers.predict import PredictModelServer
from vla_eval.model_servers.serve import serve

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from adapters.registry import load_suite
from policies.playback import load_demos


class Playback(PredictModelServer):
    def __init__(self, demos: str, suite: str):
        super().__init__()
        self.tasks = [task.name for task in load_suite(suite).tasks]
        _, self.episodes = load_demos(Path(demos))
        self.playing: dict[str, np.ndarray] = {}

    async def on_episode_start(self, config: dict[str, Any], ctx: Any) -> None:
        task = config["task"]
        recorded = self.episodes[(self.tasks[task["task_id"]], task["episode_idx"])].actions.copy()
        recorded[:, -1] = np.where(recorded[:, -1] < 0, -1.0, 1.0)
        self.playing[ctx.session_id] = recorded
        await super().on_episode_start(config, ctx)

    def predict(self, obs: dict[str, Any], ctx: Any) -> dict[str, Any]:
        actions = self.playing[ctx.session_id]
        if ctx.step < len(actions):
            return {"actions": actions[ctx.step]}
        hold = np.zeros(actions.shape[1], np.float32)
        hold[-1] = actions[-1, -1]
        return {"actions": hold}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--demos", required=True)
    parser.add_argument("--suite", required=True, help="this harness's name of the suite the demos come from")
    parser.add_argument("--port", type=int, required=True)
    args = parser.parse_args()
    serve(Playback(args.demos, args.suite), "127.0.0.1", args.port)


if __name__ == "__main__":
    main()
