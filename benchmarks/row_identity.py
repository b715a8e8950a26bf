"""Row identity: the same fixed set of runs on two source trees, every column compared.

A change to the core (the episode loop, the runner, the backends) must leave every row
of every run as it was, timings aside. This script runs a fixed set of configurations
through the command line of a source tree (`python -m harness`, with that tree first on
the path, in worker processes and Ray workers too) and compares two such recordings
column by column, row by row:

    python benchmarks/row_identity.py record --tree /path/to/old-checkout --out /tmp/rows-before
    python benchmarks/row_identity.py record --tree . --out /tmp/rows-after
    python benchmarks/row_identity.py compare /tmp/rows-before /tmp/rows-after [--json PATH]

`compare` prints one line per configuration and writes benchmarks/results/row-identity.json
(unless --json says otherwise); it exits 1 when any compared value differs.

What is compared: every column of episodes.parquet except the ones that measure time or
depend on it (TIMING below: clocks, rates, the CPU-time verdict, the run's own id and
calibration verdict), in the order the rows were written; `checkpoint` (a path, which
differs between two checkouts) by its file name, its content by `checkpoint_sha256`;
`worker_id` only where one process ran everything (with several workers, which worker
takes which task depends on which starts first). Also each run's traces.jsonl lines
(without their start time and run id) where it records traces, and the manifest's
`config` and `config_fingerprint`. Inference latencies are set as fixed delays
(`passes:0+MS`), so the delays are a function of the rows, not of the clock.

The set covers each way an episode can run: the CI smoke config; batched decoding; sync
and async latency at d = 1, 3 and longer than the chunk, whole chunks and every 4
steps, unbatched and batched; an instruction-chain suite (plain, batched, under latency);
a LIBERO suite; a SimplerEnv-like suite; worker processes, a per-episode timeout, Ray;
a served policy (plain, batched under latency); a resumed and extended run; the three
out-of-space rules; failing episodes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import re
import shlex
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from results.schema import TIMING_COLUMNS  # noqa: E402

# Columns that measure time or depend on it, and when the episode ran: never compared.
TIMING = tuple(sorted(TIMING_COLUMNS | {"run_id", "started_at"}))


@dataclass(frozen=True)
class Config:
    """One run of the set: its name, the `run` arguments, and how it is made."""

    name: str
    command: str  # `run`'s arguments; {port}: the served policy's port
    served: str = ""  # `serve` arguments: the run's remote policy talks to it
    resume: str = ""  # a second `run --resume` with these arguments
    one_process: bool = True  # worker_id is compared
    traces: bool = False

    @property
    def args(self) -> list[str]:
        return shlex.split(self.command)


MT10_3 = "--suite metaworld/mt10 --tasks button-press-topdown-v3,drawer-close-v3,door-open-v3"
MT10_2 = "--suite metaworld/mt10 --tasks reach-v3,drawer-close-v3"
TEACHER_STUDENT = "--policy bidirectional --policy fast_dvla"
CHAINS = "--suite chains/libero_goal"
CHAIN_POLICIES = "--policy bidirectional:checkpoint=chains-goal --policy fast_dvla:checkpoint=chains-goal"


def latency_configs() -> list[Config]:
    """Sync and async at d = 1, 3 and 10 (Meta-World's 80 Hz: 12.5 ms a step; the chunk is
    8 actions), whole chunks and every 4 steps."""
    return [
        Config(
            f"latency-{execution}-d{d}-r{replan}",
            f"{MT10_2} --episodes-per-task 2 {TEACHER_STUDENT} --inference-latency passes:0+{ms} "
            f"--execution {execution} --replan-every {replan}",
        )
        for execution in ("sync", "async")
        for d, ms in ((1, 12), (3, 37), (10, 125))
        for replan in (0, 4)
    ]


CONFIGS: tuple[Config, ...] = (
    Config("smoke", "--config results/baselines/metaworld-mt10-smoke.toml", traces=True),
    Config(
        "batch4",
        f"{MT10_3} --episodes-per-task 5 {TEACHER_STUDENT} --policy fast_dllm --batch-envs 4",
        traces=True,
    ),
    Config(
        "batch3-replan4",
        f"{MT10_2} --episodes-per-task 4 --policy fast_dvla --policy block_diffusion --batch-envs 3 --replan-every 4",
    ),
    *latency_configs(),
    *(
        Config(
            f"latency-batched-{execution}",
            f"{MT10_2} --episodes-per-task 4 {TEACHER_STUDENT} --batch-envs 3 --inference-latency passes:1+3 "
            f"--execution {execution} --replan-every 4",
        )
        for execution in ("sync", "async")
    ),
    Config(
        "out-of-space-fail",
        f"{MT10_3} --episodes-per-task 2 --policy scripted --policy random:chunk_length=3 --out-of-space fail",
    ),
    Config("out-of-space-clip", f"{MT10_3} --episodes-per-task 2 --policy scripted --out-of-space clip"),
    Config(
        "out-of-space-record",
        f"{MT10_3} --episodes-per-task 2 --policy scripted:action_noise=0.5 --out-of-space record",
    ),
    Config(
        "chains", f"{CHAINS} --episodes-per-task 2 --policy libero_scripted {CHAIN_POLICIES}", traces=True
    ),
    Config(
        "chains-batched",
        f"{CHAINS} --episodes-per-task 3 --policy fast_dvla:checkpoint=chains-goal --batch-envs 2 --replan-every 4",
    ),
    Config(
        "chains-latency",
        f"{CHAINS} --episodes-per-task 2 {CHAIN_POLICIES} --inference-latency passes:0+120 --execution async "
        "--replan-every 4",
    ),
    Config(
        "libero",
        "--suite libero/spatial --tasks 0,1 --episodes-per-task 2 --policy libero_scripted "
        "--policy bidirectional:checkpoint=libero-spatial --policy fast_dvla:checkpoint=libero-spatial",
    ),
    Config(
        "simpler",
        "--suite simpler/push_cube --variants lighting --episodes-per-task 2 --policy maniskill_scripted "
        "--policy fast_dvla:checkpoint=simpler-state",
    ),
    Config(
        "workers2",
        f"{MT10_3} --episodes-per-task 2 --policy scripted --policy fast_dvla --workers 2",
        one_process=False,
    ),
    Config(
        "workers2-batch2",
        f"{MT10_3} --episodes-per-task 3 --policy fast_dvla --policy bidirectional --workers 2 --batch-envs 2",
        one_process=False,
    ),
    Config(
        "episode-timeout",
        f"{MT10_2} --episodes-per-task 2 --policy fast_dvla --episode-timeout 300",
        one_process=False,
    ),
    Config(
        "ray",
        f"{MT10_3} --episodes-per-task 2 --policy scripted --policy fast_dvla --backend ray --workers 2",
        one_process=False,
    ),
    Config(
        "remote",
        f"{MT10_2} --episodes-per-task 2 --policy remote:url=ws://127.0.0.1:{{port}}",
        served="--policy fast_dvla --suite metaworld/mt10",
    ),
    Config(
        "remote-batched-latency",
        f"{MT10_2} --episodes-per-task 3 --policy remote:url=ws://127.0.0.1:{{port}} --batch-envs 2 "
        "--inference-latency passes:1 --execution async --replan-every 4",
        served="--policy fast_dvla --suite metaworld/mt10",
    ),
    Config(
        "resumed",
        f"{MT10_2} --episodes-per-task 1 --policy fast_dvla --policy bidirectional",
        resume="--episodes-per-task 3",
    ),
)


def environment(tree: Path) -> dict[str, str]:
    """The tree first on the path of this process's children, their workers included."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(tree), *filter(None, [env.get("PYTHONPATH")])])
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def serving(tree: Path, args: str, log: Path) -> Iterator[int]:
    """`serve` with `args` on a free loopback port, until the block ends."""
    port = free_port()
    command = [sys.executable, "-m", "harness", "serve", *shlex.split(args), "--port", str(port)]
    with open(log, "w") as out:
        server = subprocess.Popen(
            command, cwd=tree, env=environment(tree), stdout=out, stderr=subprocess.STDOUT
        )
        try:
            deadline = time.monotonic() + 180
            while True:
                if server.poll() is not None:
                    raise RuntimeError(f"serve exited with {server.returncode}; see {log}")
                with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"serve did not listen within 180 s; see {log}")
                time.sleep(0.5)
            yield port
        finally:
            server.terminate()
            try:
                server.wait(30)
            except subprocess.TimeoutExpired:
                server.kill()


def run_cli(tree: Path, args: list[str], log: Path) -> int:
    command = [sys.executable, "-m", "harness", "run", *args, "--quiet"]
    with open(log, "a") as out:
        out.write("$ " + " ".join(command) + "\n")
        out.flush()
        return subprocess.run(
            command, cwd=tree, env=environment(tree), stdout=out, stderr=subprocess.STDOUT
        ).returncode


def record(tree: Path, out: Path, only: list[str] | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    tree = tree.resolve()
    statuses: dict[str, Any] = {}
    for config in CONFIGS:
        if only and config.name not in only:
            continue
        folder, log = out / config.name, out / f"{config.name}.log"
        log.unlink(missing_ok=True)
        start = time.monotonic()
        with contextlib.ExitStack() as stack:
            args = config.args
            if config.served:
                port = stack.enter_context(serving(tree, config.served, out / f"{config.name}.serve.log"))
                args = [a.format(port=port) for a in args]
            args += ["--out", str(folder.resolve()), "--overwrite"]
            if config.traces:
                args.append("--traces")
            codes = [run_cli(tree, args, log)]
            if config.resume:
                resume = ["--out", str(folder.resolve()), "--resume", *shlex.split(config.resume)]
                codes.append(run_cli(tree, resume, log))
        statuses[config.name] = {"exit": codes, "seconds": round(time.monotonic() - start, 1)}
        print(f"{config.name:28s} exit {codes}  {statuses[config.name]['seconds']:7.1f} s", flush=True)
    commit = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True)
    meta = {"tree": str(tree), "commit": commit.stdout.strip(), "python": sys.version.split()[0]}
    (out / "recording.json").write_text(json.dumps(meta | {"runs": statuses}, indent=2) + "\n")


# ---- compare ------------------------------------------------------------------------------


def same(a: Any, b: Any) -> bool:
    """Equal values, NaN equal to NaN and None to NaN (both are null in Parquet)."""
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    null_a = a is None or (isinstance(a, float) and math.isnan(a))
    null_b = b is None or (isinstance(b, float) and math.isnan(b))
    if null_a or null_b:
        return null_a and null_b
    if hasattr(a, "tolist"):
        a = a.tolist()
    if hasattr(b, "tolist"):
        b = b.tolist()
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return bool(a == b)


@dataclass
class Verdict:
    name: str
    rows: tuple[int, int]
    compared: list[str] = field(default_factory=list)
    differences: list[str] = field(default_factory=list)
    traces: tuple[int, int] | None = None

    @property
    def identical(self) -> bool:
        return not self.differences and self.rows[0] == self.rows[1]


def portable_params(text: str) -> str:
    """policy_params with a checkpoint path reduced to its file name (two checkouts hold the
    shipped checkpoints at two paths) and a server's port left out."""
    params = json.loads(text)
    if isinstance(params.get("checkpoint"), str):
        params["checkpoint"] = Path(params["checkpoint"]).name
    return portable(json.dumps(params, sort_keys=True))


def portable(text: str) -> str:
    """A served policy's address without the port it got (whichever was free)."""
    return re.sub(r"(127\.0\.0\.1):\d+", r"\1:PORT", text)


def episodes(folder: Path) -> Any:
    """The rows in an order that does not depend on where the checkout was (the file's own
    order sorts by policy_config_id, a hash that covers the checkpoint's path)."""
    import pandas as pd

    rows = pd.read_parquet(folder / "episodes.parquet")
    rows["policy_params"] = rows["policy_params"].map(portable_params)
    rows["checkpoint"] = rows["checkpoint"].map(lambda v: Path(v).name if v else v)
    rows["config_label"] = rows["config_label"].map(portable)
    keys = ["task_index", "episode_index", "variant", "policy", "policy_params"]
    return rows.sort_values(keys, kind="stable", na_position="first").reset_index(drop=True)


def traces(folder: Path) -> list[dict[str, Any]]:
    path = folder / "traces.jsonl"
    if not path.is_file():
        return []
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [{k: v for k, v in line.items() if k not in ("started_at", "run_id")} for line in lines]


def id_map(a: Any, b: Any) -> dict[str, str] | str:
    """Each configuration id of `a` to the one of `b` with the same policy and portable
    parameters, or why there is no one-to-one map."""
    left = a.groupby("policy_config_id")[["policy", "policy_params"]].first()
    right = b.groupby("policy_config_id")[["policy", "policy_params"]].first()
    by_config = {tuple(r): i for i, r in right.iterrows()}
    mapping = {i: by_config.get(tuple(r)) for i, r in left.iterrows()}
    if None in mapping.values() or len(set(mapping.values())) != len(mapping) or len(mapping) != len(right):
        return f"configurations do not pair: {sorted(left.index)} vs {sorted(right.index)}"
    return mapping


def compare_one(config: Config, before: Path, after: Path) -> Verdict:
    a, b = episodes(before), episodes(after)
    verdict = Verdict(config.name, (len(a), len(b)))
    if list(a.columns) != list(b.columns):
        verdict.differences.append(f"columns differ: {list(a.columns)} vs {list(b.columns)}")
        return verdict
    ids = id_map(a, b)
    if isinstance(ids, str):
        verdict.differences.append(ids)
        return verdict
    a["policy_config_id"] = a["policy_config_id"].map(ids)
    skip = set(TIMING) | ({"worker_id"} if not config.one_process else set())
    for column in a.columns:
        if column in skip:
            continue
        verdict.compared.append(column)
        for i, (x, y) in enumerate(zip(a[column].tolist(), b[column].tolist(), strict=False)):
            if not same(x, y):
                verdict.differences.append(f"row {i} column {column}: {x!r} vs {y!r}")
                break
    ta, tb = traces(before), traces(after)
    if ta or tb:
        verdict.traces = (len(ta), len(tb))
        ta = [t | {"policy_config_id": ids.get(t["policy_config_id"])} for t in ta]
        key = lambda t: (t["task"], t["episode_index"], t["policy_config_id"], t["chunk"])  # noqa: E731
        if not same(sorted(ta, key=key), sorted(tb, key=key)):
            verdict.differences.append("traces.jsonl differs")
    ma = json.loads(portable((before / "manifest.json").read_text()))
    mb = json.loads(portable((after / "manifest.json").read_text()))
    # a served policy's fingerprint covers the port it got; its config (port aside) is compared
    for name in ("config",) if config.served else ("config", "config_fingerprint"):
        if not same(ma.get(name), mb.get(name)):
            verdict.differences.append(f"manifest {name} differs")
    return verdict


def compare(before: Path, after: Path, json_path: Path) -> int:
    verdicts = []
    for config in CONFIGS:
        if not (before / config.name / "episodes.parquet").is_file():
            print(f"{config.name:28s} not recorded in {before}")
            continue
        if not (after / config.name / "episodes.parquet").is_file():
            print(f"{config.name:28s} not recorded in {after}")
            continue
        verdicts.append(compare_one(config, before / config.name, after / config.name))
    print(f"{'configuration':28s} {'rows':>9s} {'columns':>8s} {'traces':>11s}  verdict")
    for v in verdicts:
        traced = "-" if v.traces is None else f"{v.traces[0]}/{v.traces[1]}"
        rows = f"{v.rows[0]}/{v.rows[1]}"
        shown = "identical" if v.identical else "DIFFERS: " + "; ".join(v.differences[:3])
        print(f"{v.name:28s} {rows:>9s} {len(v.compared):>8d} {traced:>11s}  {shown}")
    meta = {
        side: json.loads((folder / "recording.json").read_text())
        if (folder / "recording.json").is_file()
        else {}
        for side, folder in (("before", before), ("after", after))
    }
    report = {
        "benchmark": "row_identity",
        "command": "python benchmarks/row_identity.py compare BEFORE AFTER",
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
        "before": {k: meta["before"].get(k) for k in ("commit", "python")},
        "after": {k: meta["after"].get(k) for k in ("commit", "python")},
        "not_compared": list(TIMING),
        "configurations": [
            {
                "name": v.name,
                "rows": v.rows[0],
                "columns_compared": len(v.compared),
                "trace_lines": None if v.traces is None else v.traces[0],
                "identical": v.identical,
                "differences": v.differences,
            }
            for v in verdicts
        ],
        "identical": all(v.identical for v in verdicts) and len(verdicts) == len(CONFIGS),
    }
    json_path.write_text(json.dumps(report, indent=2) + "\n")
    print(
        f"{sum(v.identical for v in verdicts)} of {len(CONFIGS)} configurations identical; wrote {json_path}"
    )
    return 0 if report["identical"] else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="run the set of configurations from a source tree")
    rec.add_argument("--tree", type=Path, default=REPO, help="the source tree to run (default: this one)")
    rec.add_argument("--out", type=Path, required=True, help="folder for the run folders and logs")
    rec.add_argument("--only", help="comma-separated configuration names (default: all)")
    cmp = sub.add_parser("compare", help="compare two recordings column by column")
    cmp.add_argument("before", type=Path)
    cmp.add_argument("after", type=Path)
    cmp.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "row-identity.json")
    args = parser.parse_args(argv)
    if args.command == "record":
        record(args.tree, args.out, args.only.split(",") if args.only else None)
        return 0
    return compare(args.before, args.after, args.json)


if __name__ == "__main__":
    sys.exit(main())
