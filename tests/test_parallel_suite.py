"""The suite's own run: on every core (pytest-xdist), each test file on one worker.

The project's rule is a test suite under 15 minutes on an idle 2-core machine; serially
it took over 16, so the parallel run is part of the README's test command, not an option.
"""

from __future__ import annotations

import configparser
import re
import shlex
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _pytest_command() -> list[str]:
    tox = configparser.ConfigParser(interpolation=None)
    tox.read(REPO / "tox.ini")
    lines = [line.strip() for line in tox["testenv:test"]["commands"].splitlines()]
    (command,) = [line for line in lines if line.startswith("pytest")]
    return shlex.split(command)


def test_tox_runs_the_suite_on_every_core_and_each_file_on_one_worker():
    argv = _pytest_command()
    assert argv[argv.index("-n") + 1] == "auto"
    # a file on one worker: test_backends.py's local Ray clusters one at a time, module fixtures once
    assert argv[argv.index("--dist") + 1] == "loadfile"
    # the user's arguments come last, so `tox -e test -- -n 0` runs serially
    assert argv[-1] == "{posargs}"
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(re.match(r"pytest-xdist\b", requirement) for requirement in extras["dev"])


def test_no_test_relies_on_an_xdist_group():
    """pytest 9.2 drops loadgroup's grouping silently (the group rides on a node id pytest
    no longer lets xdist change): a test that needs company goes in the same file instead."""
    others = [p for p in (REPO / "tests").glob("*.py") if p.name != Path(__file__).name]
    assert len(others) > 50
    assert [p.name for p in others if "xdist_group(" in p.read_text()] == []
