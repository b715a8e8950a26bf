"""The warnings a leaderboard prints beside its numbers: what makes two rows not the
same measurement (versions, render backend, seeds, episode sets, budgets, batch sizes,
machines). Kept apart from the arithmetic so that each rule reads on its own; outputs
must show them, not bury them (results/leaderboard.py)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from results.runs import batch_sizes, speed_warning
from results.simulator_versions import suspect as simulator_suspect


def _scoring_provenance(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """What in a manifest besides simulator versions changes scores: rendering. (Versions
    are results/simulator_versions.py's, named first as one warning.)"""
    env = manifest.get("environment") or {}
    suite = manifest.get("suite") or {}
    out: dict[str, Any] = {"render backend": suite.get("render_backend")}
    # a suite that renders nothing is not touched by MUJOCO_GL (older manifests recorded
    # the variable as import order left it); harness.run.manifest.mujoco_gl records this now
    unrendered = str(suite.get("render_backend") or "").startswith("none")
    out["MUJOCO_GL"] = "unused (state observations)" if unrendered else env.get("mujoco_gl")
    for key, value in (suite.get("provenance") or {}).items():  # e.g. SAPIEN's Vulkan driver
        out[key.replace("_", " ")] = value
    return out


def provenance_warnings(runs: Sequence[str], provenance: Mapping[str, Mapping[str, Any]]) -> list[str]:
    known = {r: _scoring_provenance(provenance[r]) for r in runs if provenance.get(r)}
    # first: a version difference alone flips outcomes, so it is the first thing to rule out
    versions = simulator_suspect({r: provenance[r] for r in runs if provenance.get(r)})
    warnings = [f"{versions}; rule that out first where success differs between rows"] if versions else []
    warnings += [
        f"{r}: speed figures unreliable (tokens/s, Hz, speedups): {speed_warning(provenance[r])}"
        for r in runs
        if provenance.get(r) and speed_warning(provenance[r])
    ]
    for r in runs:
        if r not in known:
            warnings.append(
                f"{r or 'rows'}: no manifest, so versions, render backend and machine are unknown"
            )
    for key in sorted({k for p in known.values() for k in p}):
        values: dict[str, list[str]] = {}
        for r, p in known.items():
            values.setdefault(str(p.get(key)), []).append(r)
        if len(values) > 1:
            listed = "; ".join(f"{v} ({', '.join(rs)})" for v, rs in values.items())
            warnings.append(f"runs differ in {key}: {listed}; success may not be comparable")
    return warnings


def episode_warnings(df: pd.DataFrame, keys: list[tuple[str, str]], labels: Mapping[str, str]) -> list[str]:
    warnings = []

    def name(key: tuple[str, str]) -> str:
        return labels[key[0]] + (f" @ {key[1]}" if len({m for _, m in keys}) > 1 else "")

    by_row = {k: g for k, g in df.groupby(["policy_config_id", "machine"], sort=False)}
    counts = {k: len(by_row[k]) for k in keys}
    if len(set(counts.values())) > 1:
        listed = ", ".join(f"{name(k)} {n}" for k, n in counts.items())
        warnings.append(f"episode counts differ between rows: {listed}; intervals differ in width")
    episodes = {k: set(zip(by_row[k]["task"], by_row[k]["episode_index"], strict=True)) for k in keys}
    if len(set(counts.values())) == 1 and len({frozenset(e) for e in episodes.values()}) > 1:
        warnings.append("rows were evaluated on different episodes (task, episode index); compare with care")
    starts = df.groupby(["task", "episode_index"])[["seed", "init_state_id"]].nunique(dropna=False)
    differing = starts[(starts > 1).any(axis=1)]
    if len(differing):
        task, index = differing.index[0]
        warnings.append(
            f"seeds or initial states differ between rows for {len(differing)} episode(s) "
            f"(e.g. {task} #{index}); rows did not start from the same states"
        )
    for column, what in (
        ("suite_version", "suite version"),
        ("replan_every", "replan_every"),
        ("out_of_space_rule", "--out-of-space rule"),
    ):
        if column in df and df[column].nunique() > 1:
            warnings.append(f"rows differ in {what}: {sorted(map(str, df[column].unique()))}")
    # Budgets differ between tasks by the suite's own definition (LIBERO-90, chains); only
    # one task run under two budgets is a difference between rows.
    budgets = df.groupby("task")["max_steps"].unique()
    differing = budgets[budgets.map(len) > 1]
    if len(differing):
        listed = "; ".join(f"{task}: {sorted(map(int, b))}" for task, b in differing.items())
        warnings.append(f"rows differ in step budgets for the same task ({listed})")
    sizes = batch_sizes(df)
    if len(sizes) > 1:
        warnings.append(
            f"rows ran at different batch sizes (--batch-envs {', '.join(map(str, sizes))}): speed "
            "figures (tokens/s, Hz, speedups) are not comparable between them; compare speed within one"
        )
    machines = df.groupby("policy_config_id")["machine"].nunique()
    for cid in machines[machines > 1].index:
        warnings.append(f"{labels[cid]} was measured on {machines[cid]} machines: one row per machine")
    return warnings + out_of_space_warnings(df, labels)


def out_of_space_rules(df: pd.DataFrame) -> list[str]:
    """The --out-of-space rules a table's rows ran under (none for rows before it was recorded)."""
    return sorted(set(df["out_of_space_rule"].dropna())) if "out_of_space_rule" in df else []


def out_of_space_gate_warnings(baseline: pd.DataFrame, candidate: pd.DataFrame) -> tuple[str, ...]:
    """`gate`'s lines: the two sides ran under different rules (a clipped candidate's success
    is not a failing baseline's), or a side's actions left the action space."""
    rules = {"baseline": out_of_space_rules(baseline), "candidate": out_of_space_rules(candidate)}
    warnings = []
    if rules["baseline"] and rules["candidate"] and rules["baseline"] != rules["candidate"]:
        warnings.append(
            f"--out-of-space rules differ (baseline {', '.join(rules['baseline'])}, candidate "
            f"{', '.join(rules['candidate'])}): success is compared across rules; run both under one"
        )
    for side, df in (("baseline", baseline), ("candidate", candidate)):
        warnings += [f"{side} {line}" for line in out_of_space_warnings(df)]
    return tuple(warnings)


def out_of_space_warnings(df: pd.DataFrame, labels: Mapping[str, str] | None = None) -> list[str]:
    """One line per configuration whose rows counted actions outside the action space:
    its episodes either failed for it or ran under a rule that let them through (clip,
    record), and either way its success rate says so only here."""
    if "actions_out_of_space" not in df or not (df["actions_out_of_space"].fillna(0) > 0).any():
        return []
    warnings = []
    for cid, rows in df.groupby("policy_config_id", sort=False):
        hit = rows[rows["actions_out_of_space"].fillna(0) > 0]
        if not len(hit):
            continue
        rules = out_of_space_rules(hit)
        failed = int(hit["failure_reason"].fillna("").str.startswith("ActionOutOfSpace").sum())
        name = (labels or {}).get(cid, str(rows["policy"].iloc[0]))
        warnings.append(
            f"{name}: {int(hit['actions_out_of_space'].sum())} action(s) outside the action space in "
            f"{len(hit)} of {len(rows)} episode(s), largest excess {hit['max_action_excess'].max():.3g} "
            f"(--out-of-space {', '.join(rules) or 'unknown'}; {failed} episode(s) failed for it)"
        )
    return warnings
