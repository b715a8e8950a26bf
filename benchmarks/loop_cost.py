"""What the episode loop itself costs, per step and per policy call, with nothing else in it.

A physics-free env (each step returns at once) and a policy that returns numbered chunks
at once, through the harness's episode loop (harness/episode/loop.py run_episode), so
what is timed is the loop: the timeline, the action guard's admission of each chunk, the
timed policy call with its NFE hooks, the charges. The chunk length sets how often a
call happens: 1,000 actions a chunk is the cost of a step; 1 action a chunk, of a call
every step.

    python benchmarks/loop_cost.py [--episodes 25] [--steps 1000] [--json PATH]

Prints microseconds a step (the best episode of `--episodes`, which is the least
disturbed by other load) per chunk length, and writes benchmarks/results/loop-cost.json
unless --json says otherwise. Compare two trees by running it in each, back to back.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from adapters.base import EpisodeSpec  # noqa: E402
from harness.episode.loop import run_episode  # noqa: E402
from tests.fakes import ChunkPolicy, CountdownEnv, context  # noqa: E402

CHUNKS = (1000, 8, 1)


def per_step_us(chunk: int, episodes: int, steps: int) -> float:
    """Microseconds a step of the best of `episodes` episodes of `steps` steps."""
    best = float("inf")
    for _ in range(episodes):
        env, policy = CountdownEnv(succeed_at=steps), ChunkPolicy(chunk=chunk)
        start = time.perf_counter()
        out = run_episode(env, policy, context(steps + 1), EpisodeSpec(0))
        elapsed = time.perf_counter() - start
        assert out.steps == steps and out.failure_reason is None, out
        best = min(best, elapsed / steps)
    return best * 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--episodes", type=int, default=25, help="episodes per chunk length (best one counts)"
    )
    parser.add_argument("--steps", type=int, default=1000, help="steps per episode")
    parser.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "loop-cost.json")
    args = parser.parse_args(argv)
    rows = {chunk: per_step_us(chunk, args.episodes, args.steps) for chunk in CHUNKS}
    print(f"{'actions a chunk':>16s}  {'us a step':>9s}")
    for chunk, us in rows.items():
        print(f"{chunk:>16d}  {us:9.2f}")
    result = {
        "benchmark": "loop_cost",
        "command": "python benchmarks/loop_cost.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "episodes": args.episodes,
        "steps": args.steps,
        "us_per_step": {str(chunk): round(us, 3) for chunk, us in rows.items()},
        "load_average": os.getloadavg()[0],
        "machine": {"cpu": platform.machine(), "python": platform.python_version()},
    }
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
