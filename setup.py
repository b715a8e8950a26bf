"""Build hook: record the commit a wheel or a non-editable `pip install .` was built from.

Everything else about the package is in pyproject.toml. An installed copy has no .git
beside it, so `harness.run.manifest.git_commit()` reads harness/_build_info.json, which
build_py writes into the built package (never into the source tree).

setuptools builds in `build/` beside the sources, so a plain `pip install .` left a
`build/` and a `dvla_harness.egg-info/` folder in the clone (issue 22); both default to
temporary folders here, removed when the build ends (explicit `build_base` or
`egg_base` options are kept as given).
"""

from __future__ import annotations

import atexit
import json
import shutil
import subprocess
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build import build
from setuptools.command.build_py import build_py
from setuptools.command.egg_info import egg_info

HERE = Path(__file__).resolve().parent
BUILD_INFO = "_build_info.json"  # harness.run.manifest.BUILD_INFO


def source_commit(source: Path = HERE) -> str | None:
    """HEAD of the source checkout, or None (a tarball, or no git installed)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(source), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else None


def write_build_info(package_dir: Path, version: str, source: Path = HERE) -> Path:
    """Write {"version", "git_commit"} into the built `harness` package folder."""
    path = Path(package_dir) / BUILD_INFO
    path.write_text(json.dumps({"version": version, "git_commit": source_commit(source)}) + "\n")
    return path


class BuildPyWithCommit(build_py):
    def run(self) -> None:
        super().run()
        if not self.dry_run and not self.editable_mode:  # an editable install asks git live
            target = Path(self.build_lib) / "harness"
            target.mkdir(parents=True, exist_ok=True)
            write_build_info(target, self.distribution.get_version())


def scratch_dir() -> str:
    """A temporary folder removed when the build process ends."""
    path = tempfile.mkdtemp(prefix="dvla-harness-build-")
    atexit.register(shutil.rmtree, path, True)
    return path


class BuildOutsideClone(build):
    def finalize_options(self) -> None:
        if self.build_base in (None, "build"):  # setuptools' default: inside the clone
            self.build_base = scratch_dir()
        super().finalize_options()


class EggInfoOutsideClone(egg_info):
    def finalize_options(self) -> None:
        if self.egg_base is None:  # setuptools' default: the clone (dvla_harness.egg-info/)
            self.egg_base = scratch_dir()
        super().finalize_options()


if __name__ == "__main__":  # how setuptools' build backend runs this file
    setup(
        cmdclass={"build": BuildOutsideClone, "build_py": BuildPyWithCommit, "egg_info": EggInfoOutsideClone}
    )
