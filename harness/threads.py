"""How many CPU threads torch may use while policies are timed, chosen once per process.

torch's default is one intra-op thread per physical core, and its OpenMP threads spin
while they wait for work. The shipped policies' forward passes are small (a ~0.9M-
parameter model, batch 1), so a second thread buys little when the machine is idle and
costs a great deal when it is not: with two busy loops on a 2-core machine, MT10 ran
2.4x slower with the default threads than with one, and 2 threads on 2 busy cores cut
fast_dvla's tokens/s by 90% (docs/ci-gate.md). So the default here is one thread per
worker process (the committed gate baseline's thread count too); `--threads N` asks for
more, and the manifest records what was asked for and what torch ended up with.

Worker processes that share a machine (harness/backends/) call `apply_threads` in each
worker with their own share, so workers x threads stays within the cores.

Each process calls `apply_threads` once, before any heavy import: the environment
variables it sets are read by torch's and the BLAS libraries' thread pools when they
load. torch's inter-op pool reads no variable, so when torch is not loaded yet a one-shot
import hook sets torch's counts right after torch's own import has run, in whatever
module first imports it (building a policy, usually).
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import os
import sys
from pathlib import Path
from typing import Any

THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")  # read by torch when it loads
DEFAULT_THREADS_PER_WORKER = 1
MAX_THREADS = 1024

_applied: dict[str, Any] | None = None


def available_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity mask, which containers narrow)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def physical_cores(cpus: list[int] | None = None) -> int:
    """Distinct physical cores among `cpus` (hyper-threads of one core count once)."""
    cpus = available_cpus() if cpus is None else cpus
    cores = set()
    for cpu in cpus:
        topology = Path(f"/sys/devices/system/cpu/cpu{cpu}/topology")
        try:
            package = (topology / "physical_package_id").read_text().strip()
            core = (topology / "core_id").read_text().strip()
        except OSError:
            return max(1, len(cpus))  # no topology to read: count logical CPUs
        cores.add((package, core))
    return max(1, len(cores))


def default_threads(workers: int = 1) -> int:
    """Threads per worker when none are asked for: DEFAULT_THREADS_PER_WORKER, and never
    more than the worker's share of the physical cores (at least 1)."""
    share = physical_cores() // max(1, workers)
    return max(1, min(DEFAULT_THREADS_PER_WORKER, share))


def parse_threads(text: str) -> int:
    """`--threads` value: a whole number from 1 to MAX_THREADS (argparse `type=`)."""
    import argparse

    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number; give 1..{MAX_THREADS}") from None
    if not 1 <= n <= MAX_THREADS:
        raise argparse.ArgumentTypeError(f"{n} is out of range; give 1..{MAX_THREADS}")
    return n


def _env_threads() -> int | None:
    value = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(value) if value.isdigit() and int(value) >= 1 else None


def apply_threads(n: int | None = None, workers: int = 1) -> dict[str, Any]:
    """Set this process's thread counts and return what to record in the manifest.

    n: threads asked for (`--threads`); None takes OMP_NUM_THREADS if the user set it,
    else `default_threads(workers)`. Call it once, before any torch work: the environment
    variables torch and BLAS read when they load are set (and inherited by child
    processes), and torch's own counts are set now if it is loaded, else as soon as it
    is (`_TorchThreads`). Calling it again with the same arguments changes nothing.
    """
    global _applied
    if n is not None:
        target, source = n, "--threads"
    elif _applied is not None and _applied["source"] != "OMP_NUM_THREADS":
        target, source = _applied["threads"], _applied["source"]  # our own env var, not the user's
    elif _env_threads() is not None:
        target, source = _env_threads(), "OMP_NUM_THREADS"
    else:
        target, source = default_threads(workers), "default"
    for name in THREAD_ENV:
        os.environ[name] = str(target)
    _applied = {
        "requested": n,
        "source": source,
        "threads": target,
        "workers": workers,
        "physical_cores": physical_cores(),
        "cpus_available": len(available_cpus()),
    }
    torch = sys.modules.get("torch")
    if torch is None:
        _TorchThreads.install()
        return threads_record()
    note = _set_torch_threads(torch, target)
    return threads_record() | ({"interop_note": note} if note else {})


def _set_torch_threads(torch: Any, target: int) -> str | None:
    """torch's intra- and inter-op thread counts; a note when the inter-op pool had
    already started (its count can then no longer change)."""
    if torch.get_num_threads() != target:
        torch.set_num_threads(target)
    if torch.get_num_interop_threads() != target:
        try:
            torch.set_num_interop_threads(target)
        except RuntimeError:
            return "left as it was: torch's inter-op pool had already started"
    return None


class _TorchThreads(importlib.abc.MetaPathFinder):
    """A one-shot import hook: when this process first imports torch, torch's thread
    counts are set (to what `apply_threads` chose last) right after its module has run."""

    @classmethod
    def install(cls) -> None:
        if not any(isinstance(f, cls) for f in sys.meta_path):
            sys.meta_path.insert(0, cls())

    def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
        if name != "torch":
            return None
        sys.meta_path.remove(self)  # once: the import below, and every later one, is torch's own
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        loader, run = spec.loader, spec.loader.exec_module

        def exec_module(module: Any) -> None:
            run(module)
            if _applied is not None:
                _set_torch_threads(module, _applied["threads"])

        loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


def threads_record() -> dict[str, Any]:
    """What was asked for (by apply_threads) and what torch uses now (None: torch not loaded)."""
    torch = sys.modules.get("torch")
    applied = _applied or {"requested": None, "source": "not set by dvla-harness"}
    return applied | {
        "torch_intra_op": torch.get_num_threads() if torch is not None else None,
        "torch_interop": torch.get_num_interop_threads() if torch is not None else None,
    }
