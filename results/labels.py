"""Configuration labels: the one name a table, plot, report and the `config_label` column
give a policy configuration, e.g. `fast_dvla`, `acme_pd (gain=0.5)`, `fast_dvla (block_size=4)`.

A label is the policy plus the parameters that tell its configuration apart from the
policy's other configurations in the same rows, or from the policy's registered defaults
(so a lone `fast_dvla` at tau_conf=0.3 is never shown as plain `fast_dvla`). Labels are
unique per configuration: two configurations that would read alike get their
policy_config_id appended. Every output derives its names here, so a name printed in a
table is the name a user groups the Parquet rows by.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import pandas as pd

LABEL_COLUMN = "config_label"


def registered_defaults() -> dict[str, dict[str, Any]]:
    """Registered parameter defaults, so labels show only what a configuration changed."""
    try:
        from policies.registry import all_policies

        return {
            name: {f.name: f.default for f in dataclasses.fields(spec.params)}
            for name, spec in all_policies().items()
        }
    except Exception:  # a broken plugin must not stop a table; labels then show differences only
        return {}


def unused_params(policy: str, values: Mapping[str, Any]) -> set[str]:
    """Parameters a configuration does not use (fast_dllm's steps_per_block when it decodes
    by threshold), from the params class's optional `unused(values)`; labels leave them
    out, so a legend never names a setting that had no effect."""
    try:
        from policies.registry import all_policies

        spec = all_policies().get(policy)
        unused = getattr(spec.params, "unused", None) if spec is not None else None
        return set(unused(values)) if callable(unused) else set()
    except Exception:  # a plugin's broken rule must not stop a table: show every parameter
        return set()


def uses_param(policy: str, values: Mapping[str, Any], key: str) -> bool:
    """Whether a configuration sets `key` and it has an effect: the rule labels follow,
    so a plot axis and a legend agree on which configurations a parameter describes."""
    return key in values and key not in unused_params(policy, values)


def not_using(episodes: pd.DataFrame, key: str) -> dict[str, str]:
    """policy_config_id -> config_label of the configurations in `episodes` that do not use
    parameter `key` (not theirs, or without effect at their settings)."""
    configs = episodes.drop_duplicates("policy_config_id")
    labels = with_config_labels(configs).set_index("policy_config_id")[LABEL_COLUMN]
    return {
        cid: str(labels[cid])
        for cid, policy, params in configs[["policy_config_id", "policy", "policy_params"]].itertuples(
            index=False
        )
        if not uses_param(str(policy), _parse(params), key)
    }


def param_users(key: str) -> list[str]:
    """The registered policies a parameter means something to, for an error that says where
    `key` applies: a policy whose defaults leave it unused is named with that condition."""
    try:
        from policies.registry import all_policies
    except Exception:  # pragma: no cover - the registry is part of the package
        return []
    users = []
    for name, default in sorted(registered_defaults().items()):
        if key not in default:
            continue
        spec = all_policies()[name]
        unused = getattr(spec.params, "unused", None)
        ignored = callable(unused) and key in unused(default)
        users.append(
            f"{name} (not at its default {key}={show_value(key, default[key])})" if ignored else name
        )
    return users


def show_value(key: str, value: Any) -> str:
    """A parameter value as a label prints it: a checkpoint as checkpoint_name names it,
    floats to 4 significant digits, numpy scalars as the Python values they are (a row's
    2 equals the default 2)."""
    if isinstance(value, np.generic):
        value = value.item()
    if key == "checkpoint" and isinstance(value, str):
        return checkpoint_name(value)
    if isinstance(value, float):
        return format(value, ".4g")
    return str(value)


# A shipped checkpoint is policies/checkpoints/<set>-<recipe>.safetensors, named on the
# command line by its set (`checkpoint=libero-object`, policies/dvla/policy.py).
SHIPPED_RECIPES = ("bidirectional", "block_diffusion", "fast_dvla", "autoregressive")


@functools.cache
def shipped_sets() -> frozenset[str]:
    """The shipped checkpoint sets' names, from the files (no torch, no policy import)."""
    import policies

    folder = Path(policies.__file__).resolve().parent / "checkpoints"
    return frozenset(f.stem.rpartition("-")[0] for f in folder.glob("*-*.safetensors"))


def checkpoint_name(path: str) -> str:
    """How a label names a checkpoint: a shipped one by the set name a user types
    (`libero-object`, not `libero-object-bidirectional.safetensors`), any other by its
    file name; by the name alone either way, since paths differ between machines."""
    p = PurePath(path)
    set_name, _, recipe = p.stem.rpartition("-")
    if p.suffix == ".safetensors" and recipe in SHIPPED_RECIPES and set_name in shipped_sets():
        return set_name
    return p.name


def _parse(params: Any) -> dict[str, Any]:
    try:
        parsed = json.loads(params) if params else {}
    except (TypeError, json.JSONDecodeError):
        return {"params": params}
    return parsed if isinstance(parsed, dict) else {"params": params}


def config_labels(
    episodes: pd.DataFrame, used: Mapping[str, Mapping[str, Any]] | None = None
) -> dict[str, str]:
    """policy_config_id -> label for every configuration in `episodes` (any frame with
    policy_config_id, policy and policy_params columns, one row per episode or per
    configuration). `used` overrides a configuration's recorded parameters with the values
    it actually ran with (plots: a block size of 0 is the checkpoint's)."""
    configs = episodes.drop_duplicates("policy_config_id")[["policy_config_id", "policy", "policy_params"]]
    defaults = registered_defaults()
    parsed: dict[str, dict[str, Any]] = {}
    for cid, params in zip(configs["policy_config_id"], configs["policy_params"], strict=True):
        parsed[cid] = _parse(params) | dict((used or {}).get(cid, {}))
    labels: dict[str, str] = {}
    for policy, group in configs.groupby("policy", sort=False):
        ids = list(group["policy_config_id"])
        default = defaults.get(str(policy), {})
        keys = sorted({k for cid in ids for k in parsed[cid]})

        def value(cid: str, key: str, default: dict[str, Any] = default) -> str:
            # A parameter added after a run was recorded counts as its default there.
            return show_value(key, parsed[cid].get(key, default.get(key)))

        shown = [
            k
            for k in keys
            if len({value(cid, k) for cid in ids}) > 1
            or (k in default and any(value(cid, k) != show_value(k, default[k]) for cid in ids))
            or (default and k not in default)
        ]
        for cid in ids:
            skip = unused_params(str(policy), parsed[cid])
            parts = [f"{k}={value(cid, k)}" for k in shown if k in parsed[cid] and k not in skip]
            labels[cid] = f"{policy} ({', '.join(parts)})" if parts else str(policy)
    seen: dict[str, int] = {}
    for label in labels.values():
        seen[label] = seen.get(label, 0) + 1
    return {cid: (f"{lab} [{cid}]" if seen[lab] > 1 else lab) for cid, lab in labels.items()}


def labels_consistent(episodes: pd.DataFrame) -> bool:
    """Whether the rows' config_label column names each configuration by one label of its own."""
    if LABEL_COLUMN not in episodes or episodes[LABEL_COLUMN].isna().any():
        return False
    pairs = episodes[["policy_config_id", LABEL_COLUMN]].drop_duplicates()
    return pairs["policy_config_id"].is_unique and pairs[LABEL_COLUMN].is_unique


def with_config_labels(episodes: pd.DataFrame) -> pd.DataFrame:
    """`episodes` with config_label set on every row. Rows keep the labels they were
    written with when those are complete and one per configuration; otherwise (tables
    written before the column existed, rows of runs recorded under other defaults) the
    whole frame is labelled afresh, so the column stays unique per configuration."""
    if episodes.empty or labels_consistent(episodes):
        return episodes
    out = episodes.copy()
    out[LABEL_COLUMN] = out["policy_config_id"].map(config_labels(out))
    return out


def row_labels(episodes: pd.DataFrame) -> dict[str, str]:
    """policy_config_id -> the config_label the rows hold, for printing a run's tables: the
    labels were worked out from every configuration the run lists, so a summary printed
    before all of them have rows still names each one as its rows do."""
    labelled = with_config_labels(episodes)
    if labelled.empty:
        return {}
    pairs = labelled.drop_duplicates("policy_config_id")
    return dict(zip(pairs["policy_config_id"], pairs[LABEL_COLUMN], strict=True))
