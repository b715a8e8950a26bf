"""A module of the harness that vanishes while it runs (a non-editable `pip install` of an
extra reinstalls the package under a running process) is named as the cause in one line."""

from __future__ import annotations

import importlib.abc
import sys

import pytest

from harness.errors import vanished_in

GONE = "policies.dvla.fast_dvla"


class _Vanished(importlib.abc.MetaPathFinder):
    """What a reinstall in flight looks like to an import: the file is not there."""

    def find_spec(self, name, path=None, target=None):  # type: ignore[no-untyped-def]
        if name == GONE:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


@pytest.fixture
def vanished(monkeypatch):
    monkeypatch.delitem(sys.modules, GONE, raising=False)
    monkeypatch.setattr(sys, "meta_path", [_Vanished(), *sys.meta_path])


@pytest.mark.metaworld
def test_episodes_that_fail_on_a_vanished_module_say_why_in_one_line(cli, tmp_path, vanished):
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "fast_dvla", "--episodes-per-task", "1",
        "--quiet", "--out", str(out),
    )  # fmt: skip
    assert code == 1, err
    (line,) = [line for line in err.splitlines() if "vanished" in line]
    assert f"module '{GONE}' of dvla-harness vanished while it ran" in line
    assert "install every extra before starting runs" in line
    assert line.endswith(f"dvla-harness run --out {out} --resume --retry-failed")


def test_a_command_that_meets_a_vanished_module_exits_3_with_one_line(cli, tmp_path, vanished, monkeypatch):
    import results.plots

    def plot_frame(*args, **kwargs):  # what `plot` runs into when the decoders' module is gone
        import policies.dvla.fast_dvla  # noqa: F401

    monkeypatch.setattr(results.plots, "plot_frame", plot_frame)
    from tests.test_html_fit import _mt10_rows
    from tests.test_leaderboard import write_run

    run = write_run(tmp_path / "r", _mt10_rows())
    code, _, err = cli("plot", "pareto", str(run), "--out", str(tmp_path / "p.png"))
    assert code == 3
    assert err.strip().splitlines() == [
        f"dvla-harness plot: error: module '{GONE}' of dvla-harness vanished while it ran: the installed "
        "package was replaced under it (a `pip install` of an extra during a run does that); install every "
        "extra before starting runs; then run the command again"
    ]


def test_only_the_harness_own_modules_count_as_vanished():
    reasons = [
        "ModuleNotFoundError: No module named 'libero'",  # an extra not installed: its own message
        "ValueError: action outside the space",
        f"ModuleNotFoundError: No module named '{GONE}'",
        f"ModuleNotFoundError: No module named '{GONE}'",
    ]
    cause, count = vanished_in(reasons)
    assert count == 2 and GONE in cause
    assert vanished_in(reasons[:2]) is None
