"""Provenance a new user relies on: the commit and version of a non-editable
install, and MUJOCO_GL recorded as what the suite's observations actually use."""

from __future__ import annotations

import copy
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import harness.run.manifest as manifest_module
from results.leaderboard import leaderboards
from results.runs import load_run
from tests.test_leaderboard import BIDI, FAST, MANIFEST, episodes, write_run

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent


def head() -> str:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("needs the git checkout")
    return subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()


def setup_module_file():
    spec = importlib.util.spec_from_file_location("dvla_setup", REPO / "setup.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)  # not __main__: defines the hook, builds nothing
    return module


def test_the_build_hook_writes_the_commit_and_version_into_the_package(tmp_path):
    path = setup_module_file().write_build_info(tmp_path, "0.1.0")
    assert path.name == manifest_module.BUILD_INFO
    assert json.loads(path.read_text()) == {"version": "0.1.0", "git_commit": head()}


def test_an_installed_copy_without_git_reads_the_commit_recorded_at_build(tmp_path, monkeypatch):
    package = tmp_path / "site-packages" / "harness"
    package.mkdir(parents=True)
    (package / manifest_module.BUILD_INFO).write_text(json.dumps({"version": "9.9", "git_commit": "c0ffee"}))
    monkeypatch.setattr(manifest_module, "__file__", str(package / "run" / "manifest.py"))
    monkeypatch.setattr(manifest_module, "package_version", lambda name: None)
    assert manifest_module.git_commit() == "c0ffee"
    assert manifest_module.harness_version() == "9.9"
    env = manifest_module.environment()
    assert env["git_commit"] == "c0ffee" and env["harness_version"] == "9.9"
    (package / manifest_module.BUILD_INFO).unlink()  # a copy built without the hook
    assert manifest_module.git_commit() is None


def pip_wheel(source: str, out: Path, cwd: Path, env: dict[str, str] | None = None) -> None:
    """`pip wheel` without build isolation (no network) and without dependencies."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-build-isolation",
            "--no-deps",
            "-q",
            "-w",
            str(out),
            source,
        ],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    if done.returncode != 0 and "No module named pip" in done.stderr:
        pytest.skip("pip is not installed in this environment")
    assert done.returncode == 0, done.stderr


def test_a_non_editable_build_carries_the_commit(tmp_path):
    """What `pip install .` builds (without build isolation, so no network): the wheel's
    harness package holds _build_info.json with the checkout's HEAD."""
    commit = head()
    extra = tmp_path / "build.cfg"  # keep setuptools' build folder out of the clone
    extra.write_text(f"[build]\nbuild_base = {tmp_path / 'build'}\n")
    pip_wheel(str(REPO), tmp_path, REPO, {**os.environ, "DIST_EXTRA_CONFIG": str(extra)})
    (wheel,) = tmp_path.glob("dvla_harness-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        info = json.loads(zf.read("harness/_build_info.json"))
    assert info["git_commit"] == commit and info["version"]


@pytest.mark.parametrize("variable", [None, "egl", "osmesa"])
def test_mujoco_gl_of_a_state_suite_is_unused_whatever_the_variable_says(monkeypatch, variable):
    if variable is None:
        monkeypatch.delenv("MUJOCO_GL", raising=False)
    else:
        monkeypatch.setenv("MUJOCO_GL", variable)
    assert manifest_module.mujoco_gl("none (state observations)") == manifest_module.NO_RENDERER
    assert manifest_module.mujoco_gl("egl (128 px, shadows on, reflections on)") == variable


def test_a_state_run_records_no_renderer_and_old_runs_are_not_flagged_for_it(cli, tmp_path, monkeypatch):
    pytest.importorskip("metaworld")
    monkeypatch.setenv("MUJOCO_GL", "egl")  # as an earlier import of a renderer leaves it
    out = tmp_path / "run"
    args = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--policy", "random"]
    assert cli(*args, "--out", str(out), "--quiet")[0] == 0
    env = json.loads((out / "manifest.json").read_text())["environment"]
    assert env["mujoco_gl"] == "unused (state observations)"
    assert env["harness_version"] and env["git_commit"]
    # two state runs whose manifests recorded the variable as it happened to be
    old = copy.deepcopy(MANIFEST)
    old["environment"]["mujoco_gl"] = "egl"
    a = write_run(tmp_path / "a", episodes("bidirectional", BIDI, "bidi000001", [1]))
    b = write_run(tmp_path / "b", episodes("fast_dvla", FAST, "fast000001", [1]), old)
    (board,) = leaderboards([load_run(a), load_run(b)])
    assert not any("MUJOCO_GL" in w for w in board.warnings), board.warnings


def test_building_from_a_clone_leaves_no_build_folder_in_it(tmp_path):
    """What a plain `pip install .` runs (a wheel build, here without build isolation, so
    no network): setuptools' build/ and egg-info folders land outside the clone."""
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True, timeout=120)
    shutil.copy(REPO / "setup.py", clone / "setup.py")  # this checkout's hook, committed or not
    pip_wheel(".", tmp_path, clone)
    assert len(list(tmp_path.glob("dvla_harness-*.whl"))) == 1
    left = subprocess.run(
        ["git", "status", "--short", "--ignored"], cwd=clone, capture_output=True, text=True, check=True
    ).stdout
    assert left.strip() in ("", "M setup.py"), left  # no build/, no dvla_harness.egg-info/
