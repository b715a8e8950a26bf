"""The row of an episode whose worker process is lost or runs past --episode-timeout says
what the episode had done (steps, chunks, policy and env time) as its worker last reported
it, and the wall clock it held the worker: real processes, a real SIGKILL and a real hang
in the middle of an episode (tests/test_schedule.py has the rule on a scripted clock)."""

from __future__ import annotations

import pandas as pd
import pytest

from harness.backends import Execution
from harness.run.runner import run
from tests.fakes import FakeBuild

# ChunkPolicy decodes chunks of 2 actions, 0.05 s a call; the fault strikes at the 10th
# call of episode 1, after 9 chunks, 18 steps: its worker says how far it got 4 times a second.
FAULT_AT, SECONDS_PER_CALL = 10, 0.05


@pytest.mark.parametrize(
    ("fault", "execution", "reason"),
    [
        (f"hang@{FAULT_AT}", {"episode_timeout": 3.0}, "timeout: ran past --episode-timeout 3 s"),
        # a limit it never reaches: one worker process (without one the run stays in this process)
        (
            f"sigkill@{FAULT_AT}",
            {"max_retries": 0, "episode_timeout": 60.0},
            "worker lost: killed by SIGKILL",
        ),
    ],
)
def test_a_lost_or_timed_out_episode_records_the_steps_and_times_that_ran(tmp_path, fault, execution, reason):
    build = FakeBuild(faults=((1, fault),), episodes=2, succeed_at=None, delay=SECONDS_PER_CALL, max_steps=40)
    report = run(build(), tmp_path / "r", execution=Execution(workers=1, rebuild=build, **execution))
    rows = pd.read_parquet(report.run_dir.path / "episodes.parquet").set_index("episode_index")
    row = rows.loc[1]
    assert row["failure_reason"].startswith(reason)
    assert 0 < row["chunks"] < FAULT_AT and 2 * (row["chunks"] - 1) < row["steps"] <= 2 * row["chunks"]
    assert row["action_tokens_total"] == 4 * row["chunks"] and row["nfe_total"] == 0
    assert row["policy_time_s"] >= 0.9 * SECONDS_PER_CALL * row["chunks"] and row["env_time_s"] > 0
    assert row["wall_clock_s"] >= row["policy_time_s"] + row["env_time_s"]
    if reason.startswith("timeout"):
        assert row["wall_clock_s"] >= 3.0
    assert rows.loc[0, "steps"] == 40 and pd.isna(rows.loc[0, "failure_reason"])
