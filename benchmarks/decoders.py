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

All decoders run in one process on one set of weights per attention pattern, taking
turns within each round (the order rotates); each round times every decoder on its own
chunks, so the speedups are per-round ratios measured side by side, reported as mean
and 95% Student t interval over the rounds.

    python benchmarks/decoders.py [--rounds 10] [--chunks 2] [--threads 1] [--kernels default] [--json PATH]
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
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DECODERS = ("bidirectional", "fast_dllm", "block_diffusion", "fast_dvla", "autoregressive")
RECORDED = ("fast_dllm", "fast_dvla")  # data-dependent: replayed from trained checkpoints' traces
PATTERN = {
    "bidirectional": "bidirectional",
    "fast_dllm": "bidirectional",
    "block_diffusion": "block_causal",
    "fast_dvla": "block_causal",
    "autoregressive": "causal",
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
TRACES = ROOT / "benchmarks" / "traces" / "libero-spatial.json"
RECORD = (
    "dvla-harness run --suite libero/spatial --episodes-per-task 1 "
    "--policy fast_dvla:checkpoint=libero-spatial "
    "--policy fast_dllm:checkpoint=libero-spatial,blocks=8,threshold=0.9 "
    "--traces --out runs/traces-spatial --quiet"
)
EXTRACT = "python benchmarks/decoders.py --extract runs/traces-spatial"


# ------------------------------------------------------------------------- traces


@dataclass
class Chunk:
    """One chunk's passes: per pass the action positions run, whether the prefix was
    computed, and the positions read from the KV cache (prefix included)."""

    query: list[list[int]]
    prefix: list[bool]
    cached: list[int]

    def at_prefix(self, recorded: int, prefix_len: int) -> Chunk:
        """The same passes for a model whose prefix has `prefix_len` positions where the
        recording model's had `recorded`: every cache read includes the whole prefix."""
        shift = prefix_len - recorded
        return Chunk(self.query, self.prefix, [c + shift if c else 0 for c in self.cached])

    def counts(self, prefix_len: int) -> dict[str, int]:
        prefix_passes = sum(self.prefix)
        queries = sum(len(q) for q in self.query)
        return {
            "nfe": len(self.query),
            "prefix_passes": prefix_passes,
            "query_tokens": queries,
            "tokens_run": queries + prefix_passes * prefix_len,
            "cached_read": sum(self.cached),
        }


def to_runs(positions: Sequence[int]) -> list[list[int]]:
    """[start, stop) runs of consecutive positions, in order: [0..6, 14..20] -> [[0, 7], [14, 21]]."""
    runs: list[list[int]] = []
    for p in positions:
        if runs and runs[-1][1] == p:
            runs[-1][1] += 1
        else:
            runs.append([p, p + 1])
    return runs


def from_runs(runs: Sequence[Sequence[int]]) -> list[int]:
    return [p for start, stop in runs for p in range(start, stop)]


def extract(run_dir: str | Path, out: str | Path = TRACES) -> dict:
    """The compact trace file from a `--traces` run: per policy, its parameters, the
    checkpoint's prefix length, and every chunk's passes (queries as [start, stop) runs)."""
    from policies.dvla.checkpoint import load
    from results.store import RunDir

    run = RunDir(run_dir)
    manifest = json.loads((Path(run_dir) / "manifest.json").read_text())
    traces = run.read_traces()
    tasks = manifest["suite"]["tasks"]
    decoders: dict[str, dict] = {}
    for policy in manifest["policies"]:
        mine = traces[traces["policy_config_id"] == policy["config_id"]].copy()
        mine["task_index"] = mine["task"].map(tasks.index)
        mine = mine.sort_values(["task_index", "episode_index", "chunk"])
        cfg = load(policy["checkpoint"]).model.cfg
        params = json.loads(policy["params"])
        if Path(params["checkpoint"]).is_relative_to(ROOT):
            params["checkpoint"] = str(Path(params["checkpoint"]).relative_to(ROOT))
        decoders[policy["name"]] = {
            "params": params,
            "checkpoint_sha256": policy["checkpoint_sha256"],
            "prefix_len": cfg.prefix_len,
            "action_tokens": cfg.action_tokens,
            "chunks": [
                {
                    "task": int(row.task_index),
                    "episode": int(row.episode_index),
                    "chunk": int(row.chunk),
                    "query": [to_runs(q) for q in row.query],
                    "prefix": [int(p) for p in row.prefix],
                    "cached": [int(c) for c in row.cached],
                }
                for row in mine.itertuples()
            ],
        }
    record = {
        "source": f"{manifest['suite']['name']}, run {manifest['run_id']}",
        "commands": [RECORD, EXTRACT],
        "decoders": decoders,
    }
    lines = json.dumps({k: v for k, v in record.items() if k != "decoders"}, indent=1)[:-2]
    body = []  # one chunk a line: small, and diffs read per chunk
    for name, d in decoders.items():
        head = json.dumps({k: v for k, v in d.items() if k != "chunks"})[:-1]
        chunks = ",\n".join("    " + json.dumps(c, separators=(",", ":")) for c in d["chunks"])
        body.append(f'  {json.dumps(name)}: {head}, "chunks": [\n{chunks}\n  ]}}')
    text = lines + ',\n "decoders": {\n' + ",\n".join(body) + "\n }\n}\n"
    assert json.loads(text) == record
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(text)
    return record


def load_traces(path: str | Path = TRACES) -> dict[str, dict]:
    """Per recorded decoder: its record, with `chunks` as Chunk objects at the recorded prefix."""
    record = json.loads(Path(path).read_text())
    out = {}
    for name, d in record["decoders"].items():
        chunks = [
            Chunk([from_runs(q) for q in c["query"]], [bool(p) for p in c["prefix"]], c["cached"])
            for c in d["chunks"]
        ]
        out[name] = {**d, "chunks": chunks}
    return out


def decode(name: str, model, words, state):
    """The decoder itself, default parameters (bidirectional T = 12)."""
    from policies.dvla import decoders as d
    from policies.dvla.fast_dllm import decode_fast_dllm
    from policies.dvla.fast_dvla import decode_fast_dvla

    return {
        "bidirectional": lambda: d.decode_bidirectional(model, words, state, steps=12),
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
    for pattern in sorted(set(PATTERN.values())):
        torch.manual_seed(0)
        models[pattern] = ActionTokenModel(ModelConfig(**shape, pattern=pattern)).eval().to(device)
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
    base = samples.get("bidirectional")
    for name in decoders:
        mine = samples[name]
        ms, ms_ci = mean_ci([s["ms_per_chunk"] for s in mine])
        row = {"decoder": name, "source": "recorded" if name in RECORDED else "generated"}
        for key in ("nfe", "prefix_passes", "query_tokens", "tokens_run", "cached_read"):
            row[key] = statistics.fmean(s[key] for s in mine)
        row |= {"ms_per_chunk": ms, "ms_per_chunk_ci95": ms_ci, "chunks_timed": rounds * chunks}
        row["tokens_per_s"] = cfg.action_tokens * 1000 / ms
        if base:
            ratios = [b["ms_per_chunk"] / s["ms_per_chunk"] for b, s in zip(base, mine, strict=True)]
            row["speedup_vs_bidirectional"], row["speedup_ci95"] = mean_ci(ratios)
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


def report(result: dict) -> None:
    threads = result["threads"]
    print(
        f"paper-like shapes ({result['prefix_len']} prefix + {result['action_tokens']} action tokens, "
        f"width {SHAPE['width']}, {SHAPE['layers']} layers); device {result['device']}, {threads} CPU "
        f"thread{'s' * (threads != 1)}, linear kernels: {result['linear_kernels']} "
        f"({result['packed_linears']} layers packed)"
    )
    print(
        f"{'decoder':16}{'source':>10}{'NFE':>7}{'prefix':>8}{'queries':>9}{'tokens run':>12}"
        f"{'cached read':>13}{'ms/chunk':>18}{'speedup':>16}"
    )
    for r in result["rows"]:
        ms = f"{r['ms_per_chunk']:.1f} ± {r['ms_per_chunk_ci95']:.1f}"
        speed = (
            f"{r['speedup_vs_bidirectional']:.2f}x ± {r['speedup_ci95']:.2f}" if "speedup_ci95" in r else ""
        )
        print(
            f"{r['decoder']:16}{r['source']:>10}{r['nfe']:>7.1f}{r['prefix_passes']:>8.1f}{r['query_tokens']:>9.0f}"
            f"{r['tokens_run']:>12.0f}{r['cached_read']:>13.0f}{ms:>18}{speed:>16}"
        )
    print("(per chunk: means over the timed chunks; ± is a 95% Student t interval over rounds)")
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
    result = measure(
        args.rounds,
        args.chunks,
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
        "shape": SHAPE,
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
