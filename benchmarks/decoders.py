"""Decoder speed at paper-like shapes: tokens/s, NFE per chunk and peak memory, side by side.

Shapes follow the Fast-dVLA setting: ~256 prefix tokens, 8 x 7 = 56 action tokens,
blocks of one action step (7 tokens), 8 layers, width 512. Weights are RANDOM: this
measures speed only. Confidence-driven decoders (fast_dvla) behave differently on
trained weights, where confidences are high and more tokens clear the thresholds per
pass; on random weights fast_dvla mostly advances by its k-th-highest rule.

Each decoder runs in its own subprocess (so peak RSS is its own), the subprocesses
take turns round by round, and NFE is counted by the harness's hooks.

    python benchmarks/decoders.py [--rounds 3] [--chunks 5] [--json PATH]

Target: fast_dvla >= 4x the tokens/s of bidirectional (T = 12), and faster than
block_diffusion and fast_dllm.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

DECODERS = ("bidirectional", "fast_dllm", "block_diffusion", "fast_dvla", "autoregressive")
SHAPE = {
    "action_dim": 7,
    "chunk_len": 8,
    "state_dim": 39,
    "max_words": 253,
    "state_tokens": 3,
    "width": 512,
    "layers": 8,
    "heads": 8,
    "ffn": 2048,
    "bins": 256,
    "vocab_words": 1024,
}


def measure(name: str, chunks: int) -> dict:
    """Runs in a subprocess: build the model, warm up, decode `chunks` chunks."""
    import torch

    from harness.nfe import NFECounter
    from policies import decoders as d
    from policies.model import ActionTokenModel, ModelConfig

    torch.manual_seed(0)
    torch.set_grad_enabled(False)
    pattern = {"autoregressive": "causal", "block_diffusion": "block_causal", "fast_dvla": "block_causal"}
    model = ActionTokenModel(ModelConfig(**SHAPE, pattern=pattern.get(name, "bidirectional"))).eval()
    run = {
        "bidirectional": lambda w, s: d.decode_bidirectional(model, w, s, steps=12),
        "fast_dllm": lambda w, s: d.decode_bidirectional(model, w, s, steps=12, reuse_prefix_cache=True),
        "block_diffusion": lambda w, s: d.decode_block_diffusion(model, w, s, steps_per_block=4),
        "fast_dvla": lambda w, s: d.decode_fast_dvla(model, w, s),
        "autoregressive": lambda w, s: d.decode_autoregressive(model, w, s),
    }[name]

    class Holder:
        def __init__(self) -> None:
            self.model = model

    counter = NFECounter(Holder())
    g = torch.Generator().manual_seed(1)
    words = torch.randint(1, SHAPE["vocab_words"], (1, SHAPE["max_words"]), generator=g)
    state = torch.randn(1, SHAPE["state_dim"], generator=g)
    with torch.inference_mode():
        run(words, state)  # warm-up
        counter.take()
        start = time.perf_counter()
        for _ in range(chunks):
            run(words, state)
        seconds = time.perf_counter() - start
    tokens = chunks * model.cfg.action_tokens
    return {
        "decoder": name,
        "seconds": seconds,
        "tokens_per_s": tokens / seconds,
        "ms_per_chunk": 1000 * seconds / chunks,
        "nfe_per_chunk": counter.take() / chunks,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "device": "cpu",
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=3, help="rounds; decoders take turns within each")
    parser.add_argument("--chunks", type=int, default=3, help="chunks decoded per decoder per round")
    parser.add_argument("--json", default="benchmarks/results/decoders.json")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args.worker, args.chunks)))
        return
    root = Path(__file__).resolve().parent.parent
    samples: dict[str, list[dict]] = {name: [] for name in DECODERS}
    for _ in range(args.rounds):
        for name in DECODERS:
            done = subprocess.run(
                [sys.executable, __file__, "--worker", name, "--chunks", str(args.chunks)],
                capture_output=True,
                text=True,
                check=True,
                cwd=root,
                env={"PYTHONPATH": str(root)},
            )
            samples[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
    rows = []
    for name in DECODERS:
        runs = samples[name]
        rows.append(
            {
                "decoder": name,
                "tokens_per_s": statistics.median(r["tokens_per_s"] for r in runs),
                "ms_per_chunk": statistics.median(r["ms_per_chunk"] for r in runs),
                "nfe_per_chunk": statistics.median(r["nfe_per_chunk"] for r in runs),
                "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
            }
        )
    base = next(r for r in rows if r["decoder"] == "bidirectional")["tokens_per_s"]
    for row in rows:
        row["speedup_vs_bidirectional"] = row["tokens_per_s"] / base
    print(
        "paper-like shapes, RANDOM weights (speed only): 256 prefix + 56 action tokens, 8 layers, width 512"
    )
    print(f"{'decoder':18}{'tokens/s':>10}{'ms/chunk':>10}{'NFE/chunk':>11}{'speedup':>9}{'peak RSS MB':>13}")
    for r in rows:
        print(
            f"{r['decoder']:18}{r['tokens_per_s']:>10.1f}{r['ms_per_chunk']:>10.1f}{r['nfe_per_chunk']:>11.1f}"
            f"{r['speedup_vs_bidirectional']:>8.2f}x{r['peak_rss_mb']:>13.0f}"
        )
    fast = next(r for r in rows if r["decoder"] == "fast_dvla")
    others = [r for r in rows if r["decoder"] in ("block_diffusion", "fast_dllm")]
    ok = fast["speedup_vs_bidirectional"] >= 4 and all(
        fast["tokens_per_s"] > r["tokens_per_s"] for r in others
    )
    print(
        f"target fast_dvla >= 4x bidirectional and faster than block_diffusion, fast_dllm: {'PASS' if ok else 'FAIL'}"
    )
    result = {
        "benchmark": "decoders",
        "weights": "random (speed only)",
        "shape": SHAPE,
        "rounds": args.rounds,
        "chunks_per_round": args.chunks,
        "rows": rows,
        "target_met": ok,
        "machine": {"cpu": platform.processor() or platform.machine(), "device": "cpu"},
    }
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
