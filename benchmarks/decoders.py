"""Decoder speed at paper-like shapes, replaying the passes trained models make.

A decoder's cost is its sequence of forward passes: which action positions each pass
runs as queries, whether it computes the observation prefix, and how many positions it
reads from the KV cache (policies.dvla.decoding.Pass). For the fixed-schedule decoders
(bidirectional T = 12, block_diffusion, autoregressive) that sequence does not depend
on the weights: it is generated here by running the decoder itself at the paper shape.
For the data-dependent ones (fast_dvla, fast_dllm) it does, and random weights never
clear their confidence thresholds, so theirs are replayed from decode traces of the
shipped, trained libero-spatial checkpoints (chunks of 8 steps x 7-D actions = 56
tokens, the paper's), committed in benchmarks/traces/ (see --extract for how they were
made and `RECORD` below for the run that recorded them). The committed traces come from
the previous, evaluation-state spatial set (student ca86e42c8a5d, teacher 85b7d0c43706,
shipped until commit ebcea68); `RECORD` today decodes with the held-out set that
replaced it, so re-recording changes the replayed passes a little.

Replay runs, for each chunk, the same passes at paper-like shapes (256 prefix tokens,
56 action tokens, 8 layers, width 512, RANDOM weights: cost does not depend on them):
each pass with that pass's query positions, computing the prefix where the trace did,
against a KV cache of as many positions as the trace read, built from earlier passes'
keys/values with KVCache.select/extend as the decoders build theirs, and scores the
logits and reads them on the host as every decoder does. Which cached positions they
are does not change the cost. What replay leaves out is each decoder's own commit
bookkeeping: on this project's 2-core CPU, one thread, replaying a decoder's own passes
took 0.96-1.05x the time of the decoder itself at this shape (fast_dvla's numpy
bookkeeping is the 5%).

The reference row, bidirectional_cached, is the same T = 12 decode with an exact
prefix cache (`bidirectional:cache_prefix=true` on a model whose prefix does not see the
actions): one pass computes the 256 prefix positions, the other 11 run the 56 action
positions against their cached keys/values. Each speedup over bidirectional then splits
into what caching the prefix buys (the reference over bidirectional) and what the
decoder buys beyond it (the "vs cached" column: fewer passes, fewer positions per pass).
Beside the time the table prints what explains it, counted from the passes' shapes
(decoder_traces.Chunk.counts): passes, positions run, keys/values attended, query-key
scores. On this CPU time follows positions run (compute-bound). On an H100 at batch 1
and this shape every pass costs about the same whatever it runs (launch-bound), so time
follows the pass count and caching buys nothing; a full pass becomes compute-bound
only at about a billion parameters (`--width 2048 --layers 24`), where caching the
prefix pays again (docs/measurements-speed.md, "On a GPU").

All decoders run in one process on one set of weights per attention pattern, taking
turns within each round (the order rotates); each round times every decoder on its own
chunks, so the speedups are per-round ratios measured side by side, reported as mean
and 95% Student t interval over the rounds.

    python benchmarks/decoders.py [--rounds 10] [--chunks 2] [--threads 1] [--kernels default] [--json PATH]
    python benchmarks/decoders.py --device cuda --width 2048 --layers 24 --heads 16 --ffn 8192
    python benchmarks/decoders.py --extract runs/traces-spatial   # rebuild the trace file

CPU decoding uses oneDNN-prepacked linear weights, as the policies do (policies/dvla/kernels.py);
`--kernels default` measures torch's default kernels. On a GPU (torch.cuda.is_available())
it runs there and says so.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from benchmarks.decoder_traces import COUNTS, EXTRACT, RECORD, TRACES, Chunk, extract, load_traces  # noqa: E402

# bidirectional_cached is the reference row: the bidirectional decode (T = 12) with an
# exact prefix cache, so a speedup splits into what caching the prefix buys and the rest.
DECODERS = (
    "bidirectional",
    "bidirectional_cached",
    "fast_dllm",
    "block_diffusion",
    "fast_dvla",
    "autoregressive",
)
REFERENCE = "bidirectional_cached"
RECORDED = ("fast_dllm", "fast_dvla")  # data-dependent: replayed from trained checkpoints' traces
# which model each decoder runs on: an attention pattern, and for the reference a
# bidirectional model whose prefix does not see the actions (so caching it is exact)
PATTERN = {
    "bidirectional": "bidirectional",
    "bidirectional_cached": "bidirectional_prefix_blind",
    "fast_dllm": "bidirectional",
    "block_diffusion": "block_causal",
    "fast_dvla": "block_causal",
    "autoregressive": "causal",
}
MODELS = {
    "bidirectional": {"pattern": "bidirectional"},
    "bidirectional_prefix_blind": {"pattern": "bidirectional", "prefix_sees_actions": False},
    "block_causal": {"pattern": "block_causal"},
    "causal": {"pattern": "causal"},
}
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


def decode(name: str, model, words, state):
    """The decoder itself, default parameters (bidirectional T = 12; the reference row is
    `bidirectional:cache_prefix=true`)."""
    from policies.dvla import decoders as d
    from policies.dvla.fast_dllm import decode_fast_dllm
    from policies.dvla.fast_dvla import decode_fast_dvla

    return {
        "bidirectional": lambda: d.decode_bidirectional(model, words, state, steps=12),
        "bidirectional_cached": lambda: d.decode_bidirectional(
            model, words, state, steps=12, reuse_prefix_cache=True
        ),
        "fast_dllm": lambda: decode_fast_dllm(model, words, state),
        "block_diffusion": lambda: d.decode_block_diffusion(model, words, state),
        "fast_dvla": lambda: decode_fast_dvla(model, words, state),
        "autoregressive": lambda: d.decode_autoregressive(model, words, state),
    }[name]()


def generated(name: str, model, words, state) -> Chunk:
    """A fixed-schedule decoder's passes, from running it (the same for any weights)."""
    trace = decode(name, model, words, state).row_trace(0)
    return Chunk(trace["query"], trace["prefix"], trace["cached"])


# ------------------------------------------------------------------------- replay


def replay(model, chunk: Chunk, words, state) -> dict[str, int]:
    """Run `chunk`'s passes on `model` (see the module docstring); returns what was run,
    counted from the calls made (query tokens, prefix passes, cache lengths)."""
    import torch

    from policies.dvla.decoding import score

    cfg = model.cfg
    dev = words.device
    tokens = torch.full((words.shape[0], cfg.action_tokens), cfg.mask_id, dtype=torch.long, device=dev)
    cache = latest = None
    ran = Chunk([], [], [])
    for query, prefix, cached in zip(chunk.query, chunk.prefix, chunk.cached, strict=True):
        pos = torch.tensor(query, dtype=torch.long, device=dev)
        if prefix:
            if cached:
                raise ValueError("a pass that computes the prefix reads nothing from the cache")
            result = model(tokens[:, pos], pos, words, state)
            cache = None  # decoders that recompute the prefix rebuild their cache from it
        else:
            cache = _cache_for(cache, latest, cached)
            result = model(tokens[:, pos], pos, cache=cache)
        choice, _ = score(result.logits, "max_prob")
        choice.cpu()  # every decoder reads each pass's commits on the host (its trace)
        ran.query.append(pos.tolist())
        ran.prefix.append(prefix)
        ran.cached.append(0 if prefix else len(cache))
        latest = result.kv
    return {"ran": ran, **ran.counts(cfg.prefix_len)}


def _cache_for(cache, latest, cached: int):
    """A cache of `cached` positions, as the decoders get theirs: the one in use when it
    has that many; else extended by the first entries of the latest pass's keys/values
    (finished blocks, the last autoregressive token); else selected from the latest pass
    (a fresh prefix pass: fast_dllm's refresh, everyone's first cache)."""
    import torch

    def first(kv, n: int):
        return kv.select(torch.arange(len(kv), device=kv.positions.device) < n)

    if latest is None or cached < 1:
        raise ValueError("a pass without the prefix needs a cache, built from an earlier pass")
    if cache is None:
        if cached > len(latest):
            raise ValueError(f"the pass reads {cached} cached positions; the last pass made {len(latest)}")
        return first(latest, cached)
    if cached == len(cache):
        return cache
    if cached < len(cache):
        return first(cache, cached)
    if cached - len(cache) > len(latest):
        raise ValueError(f"the cache grows by {cached - len(cache)}; the last pass made {len(latest)}")
    return cache.extend(first(latest, cached - len(cache)))


# ------------------------------------------------------------------------- measure

_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262,
         10: 2.228, 12: 2.179, 15: 2.131, 20: 2.086, 25: 2.060, 30: 2.042, 40: 2.021, 60: 2.000,
         120: 1.980}  # fmt: skip


def mean_ci(values: Sequence[float]) -> tuple[float, float]:
    """Mean and 95% Student t half-width (the table's df rounded down; 0 for one value)."""
    mean = statistics.fmean(values)
    if len(values) < 2:
        return mean, 0.0
    df = max(k for k in _T975 if k <= len(values) - 1)
    return mean, _T975[df] * statistics.stdev(values) / math.sqrt(len(values))


def build(shape: dict, device: str) -> tuple[dict, tuple, dict]:
    """Random-weight models, one per attention pattern (the same weights); random inputs."""
    import torch

    from policies.dvla.kernels import describe, pack_linears
    from policies.dvla.model import ActionTokenModel, ModelConfig

    models = {}
    for kind, options in MODELS.items():
        torch.manual_seed(0)
        # built where it runs: a billion-parameter shape initialised on one CPU thread
        # would take minutes before the first timed pass
        with torch.device(device):
            models[kind] = ActionTokenModel(ModelConfig(**shape, **options)).eval()
    linears = sum(isinstance(m, torch.nn.Linear) for m in models["bidirectional"].modules())
    packed = 0
    for model in models.values():
        packed = pack_linears(model)  # as the policies do (none on CUDA or with --kernels default)
    cfg = models["bidirectional"].cfg
    g = torch.Generator().manual_seed(1)
    words = torch.randint(1, cfg.vocab_words, (1, cfg.max_words), generator=g).to(device)
    state = torch.randn(1, cfg.state_dim, generator=g).to(device)
    info = {
        "linear_kernels": describe() if device == "cpu" else "cuda",
        "packed_linears": f"{packed} of {linears}",
        "shape": dict(shape),
        "parameters": sum(p.numel() for p in models["bidirectional"].parameters()),
    }
    return models, (words, state), info


def measure(
    rounds: int,
    chunks: int,
    shape: dict | None = None,
    traces: str | Path | dict = TRACES,
    device: str = "auto",
    decoders: Sequence[str] = DECODERS,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The benchmark's worker: build the models, get every decoder's chunks (recorded or
    generated), warm up, then `rounds` rounds in which each decoder in turn replays
    `chunks` chunks (the next ones of a seeded shuffle of its recorded chunks; a
    fixed-schedule decoder its one chunk, `chunks` times)."""
    import torch

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    torch.set_grad_enabled(False)
    models, (words, state), info = build(shape or SHAPE, device)
    cfg = models["bidirectional"].cfg
    recorded = load_traces(traces) if not isinstance(traces, dict) else traces
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    plans: dict[str, list[Chunk]] = {}
    whole: dict[str, dict] = {}
    with torch.inference_mode():
        for name in decoders:
            model = models[PATTERN[name]]
            if name in RECORDED:
                rec = recorded[name]
                if rec["action_tokens"] != cfg.action_tokens:
                    raise ValueError(
                        f"{name}'s traces have {rec['action_tokens']} action tokens, the model {cfg.action_tokens}"
                    )
                mine = [c.at_prefix(rec["prefix_len"], cfg.prefix_len) for c in rec["chunks"]]
                random.Random(seed).shuffle(mine)
            else:
                mine = [generated(name, model, words, state)]
            plans[name] = mine
            whole[name] = {
                k: statistics.fmean(c.counts(cfg.prefix_len)[k] for c in mine) for k in mine[0].counts(0)
            }
            whole[name]["chunks"] = len(mine)
        samples: dict[str, list[dict]] = {name: [] for name in decoders}
        for name in decoders:  # warm-up
            replay(models[PATTERN[name]], plans[name][0], words, state)
        sync()
        cursor = dict.fromkeys(decoders, 0)
        for r in range(rounds):
            order = list(decoders[r % len(decoders) :]) + list(decoders[: r % len(decoders)])
            for name in order:
                plan = plans[name]
                todo = [plan[(cursor[name] + i) % len(plan)] for i in range(chunks)]
                cursor[name] += chunks
                if device == "cuda":
                    torch.cuda.reset_peak_memory_stats()
                sync()
                start = time.perf_counter()
                done = [replay(models[PATTERN[name]], c, words, state) for c in todo]
                sync()
                seconds = time.perf_counter() - start
                for c, d in zip(todo, done, strict=True):
                    if d["ran"] != c:
                        raise AssertionError(f"{name}: replay ran other passes than the trace's")
                sample = {k: sum(d[k] for d in done) / chunks for k in done[0] if k != "ran"}
                sample["ms_per_chunk"] = 1000 * seconds / chunks
                sample["peak_gpu_mb"] = (
                    torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
                )
                samples[name].append(sample)
            if progress:
                progress(
                    f"round {r + 1}/{rounds}: "
                    + ", ".join(f"{n} {samples[n][-1]['ms_per_chunk']:.0f} ms" for n in decoders)
                )
    rows = []
    for name in decoders:
        mine = samples[name]
        ms, ms_ci = mean_ci([s["ms_per_chunk"] for s in mine])
        row = {"decoder": name, "source": "recorded" if name in RECORDED else "generated"}
        for key in COUNTS:
            row[key] = statistics.fmean(s[key] for s in mine)
        row |= {"ms_per_chunk": ms, "ms_per_chunk_ci95": ms_ci, "chunks_timed": rounds * chunks}
        row["tokens_per_s"] = cfg.action_tokens * 1000 / ms
        speedups = (
            ("bidirectional", "speedup_vs_bidirectional", "speedup_ci95"),
            (REFERENCE, "speedup_vs_cached", "speedup_vs_cached_ci95"),
        )
        for base, key, ci in speedups:
            if base in samples:
                ratios = [
                    b["ms_per_chunk"] / s["ms_per_chunk"] for b, s in zip(samples[base], mine, strict=True)
                ]
                row[key], row[ci] = mean_ci(ratios)
        row["all_chunks"] = whole[name]
        if device == "cuda":
            row["peak_gpu_mb"] = max(s["peak_gpu_mb"] for s in mine)
        rows.append(row)
    return {
        "device": torch.cuda.get_device_name(0) if device == "cuda" else "cpu",
        "threads": torch.get_num_threads(),
        "prefix_len": cfg.prefix_len,
        "action_tokens": cfg.action_tokens,
        **info,
        "rows": rows,
    }


def _speed(r: dict, key: str, ci: str) -> str:
    return f"{r[key]:.2f}x ± {r[ci]:.2f}" if ci in r else ""


def report(result: dict) -> None:
    threads = result["threads"]
    print(
        f"{result['prefix_len']} prefix + {result['action_tokens']} action tokens, "
        f"width {result['shape']['width']}, {result['shape']['layers']} layers, "
        f"{result['parameters'] / 1e6:.1f}M parameters; device {result['device']}, {threads} CPU "
        f"thread{'s' * (threads != 1)}, linear kernels: {result['linear_kernels']} "
        f"({result['packed_linears']} layers packed)"
    )
    print(
        f"{'decoder':21}{'source':>10}{'NFE':>6}{'prefix':>7}{'queries':>8}{'run':>6}{'cached':>8}"
        f"{'kv attended':>12}{'scores':>10}{'ms/chunk':>16}{'vs bidirectional':>17}{'vs cached':>14}"
    )
    for r in result["rows"]:
        ms = f"{r['ms_per_chunk']:.1f} ± {r['ms_per_chunk_ci95']:.1f}"
        print(
            f"{r['decoder']:21}{r['source']:>10}{r['nfe']:>6.1f}{r['prefix_passes']:>7.1f}"
            f"{r['query_tokens']:>8.0f}{r['tokens_run']:>6.0f}{r['cached_read']:>8.0f}"
            f"{r['kv_attended']:>12.0f}{r['scores'] / 1000:>9.0f}k{ms:>16}"
            f"{_speed(r, 'speedup_vs_bidirectional', 'speedup_ci95'):>17}"
            f"{_speed(r, 'speedup_vs_cached', 'speedup_vs_cached_ci95'):>14}"
        )
    print(
        "(per chunk, means over the timed chunks: forward passes, passes computing the prefix, action "
        "queries, positions run, cached keys/values read, keys/values attended, query-key scores; "
        "± is a 95% Student t interval over rounds)"
    )
    rows = {r["decoder"]: r for r in result["rows"]}
    ref = rows.get(REFERENCE, {})
    if "speedup_vs_bidirectional" in ref:
        print(
            f"split: caching the prefix alone buys {ref['speedup_vs_bidirectional']:.2f}x "
            f"({REFERENCE} over bidirectional); over the cached reference:"
        )
        for r in result["rows"]:
            if r["decoder"] not in ("bidirectional", REFERENCE) and "speedup_vs_cached" in r:
                print(
                    f"  {r['decoder']}: {r['speedup_vs_cached']:.2f}x ({r['nfe']:.1f} passes against {ref['nfe']:.0f}, "
                    f"{r['tokens_run'] / ref['tokens_run']:.2f}x the positions run)"
                )
    for r in result["rows"]:
        if r["source"] == "recorded":
            a = r["all_chunks"]
            print(
                f"  {r['decoder']}: all {a['chunks']} recorded chunks: NFE {a['nfe']:.2f}, queries "
                f"{a['query_tokens']:.0f}, cached read {a['cached_read']:.0f}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rounds", type=int, default=10, help="rounds; decoders take turns within each")
    parser.add_argument(
        "--chunks",
        type=int,
        default=2,
        help="chunks each decoder replays per round (the next ones of its recorded chunks, "
        "shuffled; a fixed-schedule decoder's one chunk again)",
    )
    parser.add_argument("--traces", default=str(TRACES), help="the recorded traces (fast_dvla, fast_dllm)")
    parser.add_argument("--json", default="benchmarks/results/decoders.json")
    parser.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where the passes run; auto = CUDA when torch sees a GPU (the table says which)",
    )
    parser.add_argument(
        "--kernels",
        choices=("prepacked", "default"),
        default="prepacked",
        help="CPU linear layers: oneDNN-prepacked weights as the policies use them "
        "(policies/dvla/kernels.py), or torch's default, to see what packing is worth",
    )
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0 = torch's default)")
    for key in ("width", "layers", "heads", "ffn"):
        parser.add_argument(
            f"--{key}",
            type=int,
            default=SHAPE[key],
            help=f"model {key} (default {SHAPE[key]}, the paper-like shape); larger shapes show "
            "where a pass stops being launch-bound on a GPU",
        )
    parser.add_argument(
        "--extract", metavar="RUN_DIR", help="write --traces from this run's traces.jsonl and exit"
    )
    args = parser.parse_args()
    if args.extract:
        record = extract(args.extract, args.traces)
        sizes = ", ".join(f"{n} {len(d['chunks'])} chunks" for n, d in record["decoders"].items())
        print(f"wrote {args.traces}: {sizes} ({Path(args.traces).stat().st_size / 1024:.0f} kB)")
        return
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    if args.kernels == "default":
        from policies.dvla.kernels import ENV

        os.environ[ENV] = "0"
    load_before = os.getloadavg()
    shape = SHAPE | {key: getattr(args, key) for key in ("width", "layers", "heads", "ffn")}
    if shape["width"] % shape["heads"]:
        parser.error(f"--width {shape['width']} is not a multiple of --heads {shape['heads']}")
    result = measure(
        args.rounds,
        args.chunks,
        shape=shape,
        traces=args.traces,
        device=args.device,
        progress=lambda s: print(s, file=sys.stderr),
    )
    report(result)
    out = {
        "benchmark": "decoders",
        "method": "replayed passes at paper-like shapes (benchmarks/decoders.py docstring)",
        "rounds": args.rounds,
        "chunks_per_round": args.chunks,
        "traces": {"file": os.path.relpath(args.traces, ROOT), "commands": [RECORD, EXTRACT]},
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "load_before": load_before,
            "load_after": os.getloadavg(),
        },
        **result,
    }
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
