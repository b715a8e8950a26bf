"""Decoder speed at paper-like shapes: tokens/s, NFE per chunk and peak memory, side by side.

Shapes follow the Fast-dVLA setting: ~256 prefix tokens, 8 x 7 = 56 action tokens,
blocks of one action step (7 tokens), 8 layers, width 512. Weights are RANDOM: this
measures speed only. Confidence-driven decoders (fast_dvla) behave differently on
trained weights, where confidences are high and more tokens clear the thresholds per
pass; on random weights fast_dvla mostly advances by its k-th-highest rule.

Each decoder runs in its own subprocess (so peak RSS is its own), the subprocesses
take turns round by round, and NFE is counted by the harness's hooks.

    python benchmarks/decoders.py [--rounds 3] [--chunks 5] [--json PATH] [--kernels default]

CPU decoding uses oneDNN-prepacked linear weights, as the policies do (policies/kernels.py):
small passes run ~2x faster with them, full-size ones ~14%, so the speedups of decoders
that run small passes grow; `--kernels default` measures torch's default kernels.

Target: fast_dvla >= 4x the tokens/s of bidirectional (T = 12), and faster than
block_diffusion and fast_dllm.
"""

from __future__ import annotations

import argparse
import json
import os
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


CHECKPOINT_OF = {
    "bidirectional": "bidirectional",
    "fast_dllm": "bidirectional",
    "block_diffusion": "block_diffusion",
    "fast_dvla": "fast_dvla",
    "autoregressive": "autoregressive",
}


def _mt10_inputs(ckpt):
    """Model inputs from real observations: the first evaluation episode of each MT10 task."""
    from adapters.registry import load_suite
    from policies.checkpoint import to_tensors

    suite = load_suite("metaworld/mt10")
    inputs = []
    for task in suite.tasks:
        env = suite.make_env(task)
        obs, _ = env.reset(options={"episode": task.episodes[0]})
        inputs.append(to_tensors(ckpt, [task.instruction], obs[None]))
        env.close()
    return inputs


A_CHUNKS_PER_B_CHUNK = 40  # (a) decodes this many chunks for each of (b)'s


def measure(name: str, chunks: int, checkpoint_dir: str = "", device: str = "auto") -> dict:
    """Runs in a subprocess: build or load the model, warm up, decode `chunks` chunks."""
    import torch

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"

    from harness.nfe import NFECounter
    from policies import decoders as d
    from policies.model import ActionTokenModel, ModelConfig

    torch.manual_seed(0)
    torch.set_grad_enabled(False)
    if checkpoint_dir:
        from policies.checkpoint import load

        ckpt = load(Path(checkpoint_dir) / f"metaworld-mt10-{CHECKPOINT_OF[name]}.safetensors")
        model = ckpt.model
        inputs = _mt10_inputs(ckpt)
    else:
        pattern = {"autoregressive": "causal", "block_diffusion": "block_causal", "fast_dvla": "block_causal"}
        model = ActionTokenModel(ModelConfig(**SHAPE, pattern=pattern.get(name, "bidirectional"))).eval()
        g = torch.Generator().manual_seed(1)
        inputs = [
            (
                torch.randint(1, SHAPE["vocab_words"], (1, SHAPE["max_words"]), generator=g),
                torch.randn(1, SHAPE["state_dim"], generator=g),
            )
        ]
    model = model.to(device)
    from policies.kernels import describe, pack_linears

    packed = pack_linears(model)  # as the policies do (none on CUDA or with --kernels default)
    linears = sum(isinstance(m, torch.nn.Linear) for m in model.modules()) + packed
    inputs = [tuple(t.to(device) for t in pair) for pair in inputs]
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
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
    with torch.inference_mode():
        run(*inputs[0])  # warm-up
        sync()
        counter.take()
        start = time.perf_counter()
        for i in range(chunks):
            run(*inputs[i % len(inputs)])
        sync()
        seconds = time.perf_counter() - start
    tokens = chunks * model.cfg.action_tokens
    return {
        "decoder": name,
        "seconds": seconds,
        "tokens_per_s": tokens / seconds,
        "ms_per_chunk": 1000 * seconds / chunks,
        "nfe_per_chunk": counter.take() / chunks,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "device": torch.cuda.get_device_name(0) if device == "cuda" else "cpu",
        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None,
        "threads": torch.get_num_threads(),
        "linear_kernels": describe() if device == "cpu" else "cuda",
        "packed_linears": f"{packed} of {linears}",
    }


def compare(rounds: int, chunks: int, checkpoint_dir: str = "", device: str = "auto") -> list[dict]:
    """Every decoder in its own subprocess, taking turns round by round; medians."""
    root = Path(__file__).resolve().parent.parent
    samples: dict[str, list[dict]] = {name: [] for name in DECODERS}
    for _ in range(rounds):
        for name in DECODERS:
            argv = [sys.executable, __file__, "--worker", name, "--chunks", str(chunks), "--device", device]
            if checkpoint_dir:
                argv += ["--checkpoints", checkpoint_dir]
            done = subprocess.run(
                argv,
                capture_output=True,
                text=True,
                check=True,
                cwd=root,
                env={**os.environ, "PYTHONPATH": str(root)},
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
                "peak_gpu_mb": max((r["peak_gpu_mb"] or 0) for r in runs) or None,
                "device": runs[0]["device"],
                "threads": runs[0]["threads"],
                "linear_kernels": runs[0]["linear_kernels"],
                "packed_linears": runs[0]["packed_linears"],
            }
        )
    base = next(r for r in rows if r["decoder"] == "bidirectional")["tokens_per_s"]
    for row in rows:
        row["speedup_vs_bidirectional"] = row["tokens_per_s"] / base
    return rows


def report(title: str, rows: list[dict]) -> bool:
    threads = rows[0]["threads"]
    print(
        f"{title} [device: {rows[0]['device']}, {threads} CPU thread{'s' * (threads != 1)}, "
        f"linear kernels: {rows[0]['linear_kernels']}; {rows[0]['packed_linears']} layers packed]"
    )
    print(f"{'decoder':18}{'tokens/s':>10}{'ms/chunk':>10}{'NFE/chunk':>11}{'speedup':>9}{'peak RSS MB':>13}")
    for r in rows:
        print(
            f"{r['decoder']:18}{r['tokens_per_s']:>10.1f}{r['ms_per_chunk']:>10.1f}{r['nfe_per_chunk']:>11.1f}"
            f"{r['speedup_vs_bidirectional']:>8.2f}x{r['peak_rss_mb']:>13.0f}"
        )
    fast = next(r for r in rows if r["decoder"] == "fast_dvla")
    others = [r for r in rows if r["decoder"] in ("block_diffusion", "fast_dllm")]
    faster = all(fast["tokens_per_s"] > r["tokens_per_s"] for r in others)
    print(
        f"fast_dvla faster than block_diffusion and fast_dllm: {'yes' if faster else 'NO'}; "
        f"{fast['speedup_vs_bidirectional']:.2f}x bidirectional\n"
    )
    return faster


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=3, help="rounds; decoders take turns within each")
    parser.add_argument(
        "--chunks",
        type=int,
        default=3,
        help="chunks decoded per decoder per round in (b); (a) decodes 40x as many",
    )
    parser.add_argument(
        "--checkpoints",
        default=str(Path(__file__).resolve().parent.parent / "policies" / "checkpoints"),
        help="folder with the metaworld-mt10-*.safetensors checkpoints (part a)",
    )
    parser.add_argument("--json", default="benchmarks/results/decoders.json")
    parser.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where the decoders run; auto = CUDA when torch sees a GPU (the table says which)",
    )
    parser.add_argument(
        "--kernels",
        choices=("prepacked", "default"),
        default="prepacked",
        help="CPU linear layers: oneDNN-prepacked weights as the policies use them "
        "(policies/kernels.py), or torch's default, to see what packing is worth",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.kernels == "default":
        from policies.kernels import ENV

        os.environ[ENV] = "0"  # the workers inherit it
    if args.worker:
        ckpts = args.checkpoints if "--checkpoints" in sys.argv else ""
        print(json.dumps(measure(args.worker, args.chunks, ckpts, args.device)))
        return
    result: dict = {
        "benchmark": "decoders",
        "rounds": args.rounds,
        "chunks_per_round": args.chunks,
        "machine": {"cpu": platform.processor() or platform.machine()},
    }
    needed = {f"metaworld-mt10-{c}.safetensors" for c in CHECKPOINT_OF.values()}
    have = {p.name for p in Path(args.checkpoints).glob("*.safetensors")}
    if needed <= have:
        # The MT10 model's chunks take milliseconds: decode many more of them, or the
        # speedups in (a) are noise (they ranged 1.25x-2.60x with 4x --chunks).
        rows = compare(args.rounds, args.chunks * A_CHUNKS_PER_B_CHUNK, args.checkpoints, args.device)
        report("(a) shipped Meta-World MT10 checkpoints, real MT10 observations", rows)
        result["mt10_checkpoints"] = {"folder": args.checkpoints, "rows": rows}
    else:
        print(f"(a) skipped: {args.checkpoints} lacks {', '.join(sorted(needed - have))}\n")
    rows = compare(args.rounds, args.chunks, device=args.device)
    result["machine"] |= {"device": rows[0]["device"], "threads": rows[0]["threads"]}
    faster = report(
        "(b) paper-like shapes, RANDOM weights (speed only): 256 prefix + 56 action tokens, "
        "8 layers, width 512",
        rows,
    )
    fast = next(r for r in rows if r["decoder"] == "fast_dvla")
    result["paper_like_random_weights"] = {
        "shape": SHAPE,
        "rows": rows,
        "target_met": faster and fast["speedup_vs_bidirectional"] >= 4,
    }
    print(
        f"target (b) fast_dvla >= 4x bidirectional: {'PASS' if result['paper_like_random_weights']['target_met'] else 'FAIL'}"
    )
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
