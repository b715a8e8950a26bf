"""One real, short sweep on Meta-World, shared by test_sweep.py and test_plots.py.

Made once per test session (a cache, not a fixture, so both modules share it): the
shipped fast_dvla checkpoint (32 action tokens, trained with blocks of 4) decoded with
blocks of 4 and 8, two easy MT10 tasks, two episodes each, with decode traces. It is
interrupted after 3 of its 8 episodes and finished by `dvla-harness sweep --resume`,
so every test that reads it also relies on resume.

Under pytest-xdist (tox.ini: --dist loadfile) the cache is per worker: made once for
each of the two modules when they run on different workers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

SWEEP_ARGS = [
    "--suite", "metaworld/mt10", "--tasks", "drawer-close-v3,window-open-v3",
    "--policy", "fast_dvla", "--grid", "block_size=4,8", "--episodes-per-task", "2",
    "--traces", "--quiet",
]  # fmt: skip
INTERRUPT_AFTER = 3


@dataclass(frozen=True)
class SweepRun:
    path: Path
    executed_before_interrupt: int
    resume_exit: int


_CACHE: dict[str, SweepRun] = {}


def real_sweep(tmp_path_factory: pytest.TempPathFactory) -> SweepRun:
    pytest.importorskip("metaworld")
    if "run" in _CACHE:
        return _CACHE["run"]
    from harness.cli import build_parser, main
    from harness.commands.run import config_from_args
    from harness.config import resolve
    from harness.run.runner import run
    from harness.run.sweep import expand, parse_grid

    out = tmp_path_factory.mktemp("sweep") / "run"
    args = build_parser().parse_args(["sweep", *SWEEP_ARGS, "--out", str(out)])
    resolved = resolve(expand(config_from_args(args), parse_grid(args.grid)))

    def progress(total: int, skipped: int):
        done = []

        def tick(success: bool) -> None:
            done.append(success)
            if len(done) == INTERRUPT_AFTER:
                raise KeyboardInterrupt  # as Ctrl-C between two episodes

        return tick

    first = run(resolved, out, progress=progress, traces=True)
    assert first.interrupted
    code = main(["sweep", *SWEEP_ARGS, "--out", str(out), "--resume"])
    _CACHE["run"] = SweepRun(out, first.executed, code)
    return _CACHE["run"]
