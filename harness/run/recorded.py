"""What a resumed folder's own rows say the run is, against what its manifest now says.

`--resume` continues the config recorded in manifest.json, and the rows are the record
of what was actually run: each carries its episode key and the run's settings
(replan_every, the out-of-space rule, the latency). A manifest edited by hand (or
damaged) would otherwise be believed: new rows made with another `replan_every` under
the old rows' configuration id, or a changed policy parameter leaving every recorded row
an orphan of no configuration while the run starts again beside them. So the rows are
checked against the config the resume resolved to, and a disagreement is refused
naming the field; the manifest's `config_fingerprint` is checked against its own config,
which catches an edit no row records (the split, a suite option).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

import pandas as pd

from harness.backends.jobs import job_key, normalised_key, plan_jobs
from harness.config import ResolvedRun, build_config
from harness.run.resume import config_data
from results.schema import EPISODE_KEY


def fingerprint_of(config: Mapping[str, Any]) -> str:
    """A recorded config's fingerprint, computed as RunConfig.fingerprint computes it."""
    text = json.dumps(config, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _fingerprint_disagreement(manifest: Mapping[str, Any]) -> str:
    recorded = manifest.get("config_fingerprint")
    config = manifest.get("config")
    if not isinstance(recorded, str) or not isinstance(config, Mapping):
        return ""
    if recorded == fingerprint_of(config):
        return ""
    try:  # a run extended before the fingerprint was taken of the recorded config itself
        if recorded == build_config(config_data(config)).fingerprint():
            return ""
    except ValueError:
        pass
    return (
        f"config_fingerprint: the manifest records {recorded}, and the config beside it gives "
        f"{fingerprint_of(config)}: the config was changed after the run wrote it"
    )


# A row's column -> the config key it records, the value a row written before the column
# existed stands for (None: compared only where recorded).
SETTINGS = (
    ("replan_every", "replan_every", None),
    ("out_of_space_rule", "out_of_space", None),
    ("inference_latency", "inference_latency", "none"),
    ("execution", "execution", None),
)


def _plain(value: Any) -> Any:
    """A row's value as Python's: numpy scalars unwrapped, NaN (pandas' null) as None."""
    value = value.item() if hasattr(value, "item") else value
    return None if isinstance(value, float) and value != value else value


def _shown(value: Any) -> str:
    return json.dumps(_plain(value), default=str)


def _setting_disagreements(recorded: pd.DataFrame, resolved: ResolvedRun) -> list[str]:
    found = []
    for column, key, before in SETTINGS:
        if column not in recorded:
            continue
        values = recorded[column] if before is None else recorded[column].fillna(before)
        values = values.dropna()
        now = getattr(resolved.config, key)
        other = values[values != now]
        if len(other):
            found.append(
                f"{key}: the manifest's config says {_shown(now)}, and {len(other)} of its "
                f"{len(recorded)} rows were recorded with {_shown(other.iloc[0])}"
            )
    return found


def _params_difference(recorded: str, now: str) -> str:
    """The first parameter two params JSON strings disagree on, in words."""
    try:
        old, new = json.loads(recorded), json.loads(now)
    except (TypeError, ValueError):
        old = new = None
    if not isinstance(old, dict) or not isinstance(new, dict):
        return f"parameters: the manifest's config gives {now}, its rows were recorded with {recorded}"
    for key in sorted(set(old) | set(new)):
        if old.get(key) != new.get(key):
            return (
                f"parameter {key}: the manifest's config gives {_shown(new.get(key, '(absent)'))}, "
                f"its rows were recorded with {_shown(old.get(key, '(absent)'))}"
            )
    return f"parameters: the manifest's config gives {now}, its rows were recorded with {recorded}"


def _why_not_planned(row: Mapping[str, Any], resolved: ResolvedRun) -> str:
    """Which field makes a recorded row no episode of the resolved config."""
    runs = [r for r in resolved.policies if r.spec.name == row["policy"]]
    if not runs:
        return f"policies: rows of policy {row['policy']!r}, which the manifest's config does not list"
    if not any(r.params_json == row["policy_params"] for r in runs):
        return f"policy {row['policy']!r} {_params_difference(row['policy_params'], runs[0].params_json)}"
    tasks = {t.name: t for t in resolved.tasks}
    if row["task"] not in tasks:
        return f"tasks: rows of task {row['task']!r}, which the manifest's config does not name"
    specs = {s.index: s for s in resolved.episodes(tasks[row["task"]])}
    index = int(row["episode_index"])
    if index not in specs:
        return (
            f"episodes_per_task: the manifest's config gives {len(specs)} episodes of task "
            f"{row['task']!r}, and its rows hold episode_index {index}"
        )
    spec = specs[index]
    for column, now in (("seed", spec.seed), ("init_state_id", spec.init_state_id)):
        if _plain(row[column]) != now:
            return (
                f"{column}: episode {index} of task {row['task']!r} was recorded with {_shown(row[column])}, "
                f"the manifest's config gives {_shown(now)} (its split or suite options were changed)"
            )
    return "the rows' episode keys (variant or checkpoint)"


def _orphans(recorded: pd.DataFrame, resolved: ResolvedRun) -> list[str]:
    """Rows that are no episode of the resolved config: the first one's reason."""
    planned = {job_key(resolved.suite.name, job) for job in plan_jobs(resolved)}
    rows = recorded[list(EPISODE_KEY)].to_dict("records")
    lost = [row for row in rows if normalised_key(row) not in planned]
    if not lost:
        return []
    return [
        f"{_why_not_planned(lost[0], resolved)}, so {len(lost)} of its {len(rows)} rows are no episode of it"
    ]


def recorded_disagreements(
    manifest: Mapping[str, Any], recorded: pd.DataFrame, resolved: ResolvedRun
) -> list[str]:
    """Each way the folder's rows (and the manifest's own fingerprint) disagree with the
    config this resume resolved to, one line each, naming the field; [] when they agree.
    Called after the resume adopted what it may (harness/run/resume.py), so rows from
    before a defaulted parameter or with a moved checkpoint already match."""
    found = []
    if len(recorded):
        found += _setting_disagreements(recorded, resolved)
        found += _orphans(recorded, resolved)
    if not found:  # an edit the rows do not show (the fingerprint says only that one was made)
        found += [fingerprint] if (fingerprint := _fingerprint_disagreement(manifest)) else []
    return found
