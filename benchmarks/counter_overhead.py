"""What the NFE and counted-work hooks (harness/episode/nfe.py) add to a forward pass.

    OMP_NUM_THREADS=1 python benchmarks/counter_overhead.py [--width 8] [--baseline-nfe FILE]

Runs the shipped MT10 model's shape (4 layers, a 13-position prefix, one 8-token block
per pass, batch 1, one thread) 8 passes per policy call, as a decoder does, with no
counter and with `NFECounter.counting()` around each call (passes and counted work), in
interleaved rounds. Times are thread CPU time, which a busy machine disturbs far less
than wall time does; the median of the rounds is reported. `--baseline-nfe` also times
another nfe.py (e.g. `git show REV:harness/episode/nfe.py > /tmp/nfe_before.py`) in the same
rounds, so a change to the counter is measured against what it replaced. Width 8 leaves
the per-module cost visible (compute noise is small); 128 is the shipped width.
Writes benchmarks/results/counter-overhead.json unless --json says otherwise.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from harness.episode.nfe import NFECounter  # noqa: E402
from policies.dvla.model import ActionTokenModel, ModelConfig  # noqa: E402

PASSES = 8  # per policy call


def load_counter(path: str) -> type:
    spec = importlib.util.spec_from_file_location("nfe_baseline", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NFECounter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=21)
    parser.add_argument("--calls", type=int, default=20, help="policy calls per round and variant")
    parser.add_argument("--baseline-nfe", default="", metavar="FILE")
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "counter-overhead.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    heads = 2 if args.width < 16 else 4
    cfg = ModelConfig(
        action_dim=4, chunk_len=8, state_dim=39, width=args.width, heads=heads,
        ffn=max(args.width, 4 * args.width if args.width >= 16 else args.width), layers=4, max_words=10,
    )  # fmt: skip
    model = ActionTokenModel(cfg).eval()
    words, state = torch.randint(1, 20, (1, 10)), torch.randn(1, 39)
    tokens, positions = torch.full((1, cfg.block), cfg.mask_id), torch.arange(cfg.block)
    variants: dict[str, object] = {"no counter": None, "counter": NFECounter()}
    if args.baseline_nfe:
        variants["baseline counter"] = load_counter(args.baseline_nfe)()

    def call(counter: object) -> None:
        if counter is None:
            for _ in range(PASSES):
                model(tokens, positions, words, state)
            return
        with counter.counting():  # type: ignore[attr-defined]
            for _ in range(PASSES):
                model(tokens, positions, words, state)
        counter.take()  # type: ignore[attr-defined]
        if hasattr(counter, "take_work"):
            counter.take_work()

    times: dict[str, list[float]] = {name: [] for name in variants}
    with torch.inference_mode():
        for _ in range(args.rounds):
            for name, counter in variants.items():
                start = time.thread_time()
                for _ in range(args.calls):
                    call(counter)
                times[name].append(1e6 * (time.thread_time() - start) / (args.calls * PASSES))
    median = {name: statistics.median(t) for name, t in times.items()}
    result = {
        "benchmark": "counter_overhead",
        "width": args.width,
        "cpu": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "us_per_pass_median": {k: round(v, 1) for k, v in median.items()},
        "added_us_per_pass": {
            k: round(v - median["no counter"], 1) for k, v in median.items() if k != "no counter"
        },
    }
    print(json.dumps(result, indent=2))
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
