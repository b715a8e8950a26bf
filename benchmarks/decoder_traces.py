"""The decode traces benchmarks/decoders.py replays: the compact trace file (one chunk
a line), reading it back, and what a chunk's passes process, counted from their shapes.

A chunk's cost on a compute-bound machine follows from its passes alone: how many there
are (each reads every weight once), how many positions each runs (queries, the prefix's
256 when the pass computes it) and how many keys/values each run position attends to
(its own pass's positions plus those read from the KV cache). `Chunk.counts` gives
these, so the benchmark's table can say why one decoder is faster than another.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TRACES = ROOT / "benchmarks" / "traces" / "libero-spatial.json"
RECORD = (
    "dvla-harness run --suite libero/spatial --episodes-per-task 1 "
    "--policy fast_dvla:checkpoint=libero-spatial "
    "--policy fast_dllm:checkpoint=libero-spatial,blocks=8,threshold=0.9 "
    "--traces --out runs/traces-spatial --quiet"
)
EXTRACT = "python benchmarks/decoders.py --extract runs/traces-spatial"
COUNTS = ("nfe", "prefix_passes", "query_tokens", "tokens_run", "cached_read", "kv_attended", "scores")


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
        """What the passes process, from their shapes alone: forward passes (`nfe`), those
        computing the prefix, action queries, positions run (queries plus the prefix
        where computed), cached keys/values read, keys/values attended (each pass's run
        positions attend to its own and the cached ones; masks do not shrink the work)
        and query-key scores computed (the part of a pass that grows with its length)."""
        run = [len(q) + prefix_len * p for q, p in zip(self.query, self.prefix, strict=True)]
        return {
            "nfe": len(self.query),
            "prefix_passes": sum(self.prefix),
            "query_tokens": sum(len(q) for q in self.query),
            "tokens_run": sum(run),
            "cached_read": sum(self.cached),
            "kv_attended": sum(r + c for r, c in zip(run, self.cached, strict=True)),
            "scores": sum(r * (r + c) for r, c in zip(run, self.cached, strict=True)),
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
