"""The suite's own run: on every core (pytest-xdist), with the tests that must share a
worker kept together, and the docs naming the groups the tests use.

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
GROUP = re.compile(r"xdist_group\(\"([\w-]+)\"\)")


def _pytest_command() -> list[str]:
    tox = configparser.ConfigParser(interpolation=None)
    tox.read(REPO / "tox.ini")
    lines = [line.strip() for line in tox["testenv:test"]["commands"].splitlines()]
    (command,) = [line for line in lines if line.startswith("pytest")]
    return shlex.split(command)


def test_tox_runs_the_suite_on_every_core_and_keeps_each_group_on_one_worker():
    argv = _pytest_command()
    assert argv[argv.index("-n") + 1] == "auto"
    assert argv[argv.index("--dist") + 1] == "loadgroup"  # any other mode ignores xdist_group
    # the user's arguments come last, so `tox -e test -- -n 0` runs serially
    assert argv[-1] == "{posargs}"
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert any(re.match(r"pytest-xdist\b", requirement) for requirement in extras["dev"])


def test_the_groups_the_docs_explain_are_the_groups_the_tests_use():
    used = {g for path in (REPO / "tests").glob("*.py") for g in GROUP.findall(path.read_text())}
    text = (REPO / "docs" / "architecture.md").read_text()
    section = text[text.index("## The test suite in parallel") :]
    documented = set(re.findall(r"^\| `([\w-]+)` \|", section, re.M))
    assert used == documented
    assert {"local-ray", "real-sweep"} <= used
