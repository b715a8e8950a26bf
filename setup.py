"""Build hook: record the commit a wheel or a non-editable `pip install .` was built from.

Everything else about the package is in pyproject.toml. An installed copy has no .git
beside it, so `harness.manifest.git_commit()` reads harness/_build_info.json, which
build_py writes into the built package (never into the source tree).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
BUILD_INFO = "_build_info.json"  # harness.manifest.BUILD_INFO


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


if __name__ == "__main__":  # how setuptools' build backend runs this file
    setup(cmdclass={"build_py": BuildPyWithCommit})
