"""What the CI gate reads of each run, checked before it judges anything.

The gate decides a CI job's exit status from rows someone else wrote (a committed
baseline, an artifact, a file edited by hand). A row with `success` NaN or null would
count as a success or a failure depending on the reader (pandas reads NaN as True), a
negative NFE would read as a speed-up: so every column the gate reads must hold what
the harness writes, and the first row that does not is refused (exit 2) by its column
and its episode, before any verdict.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import pandas as pd

from results.store import ResultsFileError

Check = Callable[[Any], bool]


def _missing(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA


def _count(value: Any) -> bool:
    """A non-negative integer (Parquet's nullable integers read back as floats)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return hasattr(value, "dtype") and value.dtype.kind in "iu" and int(value) >= 0
    return math.isfinite(value) and value >= 0 and float(value).is_integer()


def _seconds(value: Any) -> bool:
    return (
        not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value) and value >= 0
    )


def _boolean(value: Any) -> bool:
    return isinstance(value, bool) or (hasattr(value, "dtype") and value.dtype.kind == "b")


def _text(value: Any) -> bool:
    return isinstance(value, str)


def _params(value: Any) -> bool:
    try:
        return isinstance(json.loads(value), dict)
    except (TypeError, ValueError):
        return False


def _integer(value: Any) -> bool:
    """Any integer, negative included (a seed)."""
    if isinstance(value, bool):
        return False
    if isinstance(value, int):
        return True
    return isinstance(value, float) and math.isfinite(value) and value.is_integer()


# column -> (what it must hold, in words; its check; may it be null)
GATE_COLUMNS: dict[str, tuple[str, Check, bool]] = {
    "success": ("true or false", _boolean, False),
    "suite": ("a suite name", _text, False),
    "task": ("a task name", _text, False),
    "task_index": ("an integer >= 0", _count, False),
    "episode_index": ("an integer >= 0", _count, False),
    "seed": ("an integer", _integer, True),
    "init_state_id": ("an integer", _integer, True),
    "variant": ("a variant name", _text, True),
    "policy": ("a policy name", _text, False),
    "policy_params": ("a JSON object", _params, False),
    "policy_config_id": ("a configuration id", _text, False),
    "checkpoint_sha256": ("a sha256 (or empty)", _text, False),
    "steps": ("an integer >= 0", _count, False),
    "chunks": ("an integer >= 0", _count, False),
    "nfe_total": ("an integer >= 0", _count, True),
    "flops_total": ("an integer >= 0", _count, True),
    "action_tokens_total": ("an integer >= 0", _count, False),
    "policy_time_s": ("a finite number of seconds >= 0", _seconds, False),
    "subtasks_completed": ("an integer >= 0", _count, True),
    "failure_reason": ("text", _text, True),
    "batch_envs": ("an integer >= 1", lambda v: _count(v) and v >= 1, True),
    "inference_latency": ("a latency mode", _text, True),
    "execution": ("sync or async", lambda v: v in ("sync", "async"), True),
}


def _shown(value: Any) -> str:
    """A value as the user wrote it: numpy scalars as Python's, 4.0 in an integer column
    (Parquet's nullable integers read back as floats) as 4, a missing value (None, or the
    NaN pandas reads a null integer as) as null."""
    if _missing(value):
        return "null"
    value = value.item() if hasattr(value, "item") else value
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return repr(value)


def _episode(episodes: pd.DataFrame, position: int) -> str:
    """A row by what identifies its episode, as the user finds it in the table."""
    return ", ".join(
        f"{column} {_shown(episodes[column].iloc[position])}"
        for column in ("task", "episode_index", "policy")
        if column in episodes
    )


def check_gate_inputs(episodes: pd.DataFrame, source: str) -> None:
    """Refuse (ResultsFileError) the first value of a column the gate reads that is not
    what the harness writes, naming `source` (the run), the column, the row and the value."""
    for column, (expected, check, nullable) in GATE_COLUMNS.items():
        if column not in episodes:
            continue
        for position, value in enumerate(episodes[column].tolist()):
            if _missing(value) and nullable:
                continue
            if _missing(value) or not check(value):
                raise ResultsFileError(
                    f"{source}: column {column!r} holds {_shown(value)} in row {position} "
                    f"({_episode(episodes, position)}); "
                    f"the gate needs {expected}{'' if nullable else ', never null'}"
                )
