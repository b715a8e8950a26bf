"""What `--resume` continues, and what a resumed run must match.

`dvla-harness run --out DIR --resume` with no other flags continues the config recorded in
DIR/manifest.json (not the embedded default); flags override it, and the result must
evaluate the same thing. Configs are compared by what they evaluate, not how they were
typed: the suite and its tasks by the names they resolve to (an index and a name are one task), policies
by their validated parameters (`seed=1` from a flag and `seed = 1` from TOML are one),
and the order of either does not matter.

Recorded rows are not run again, except those whose failure says the machinery failed,
not the policy (INFRASTRUCTURE_FAILURES: a lost worker, a lost policy server); with
--retry-failed, every failed row.

Two differences are not refused:

- More episodes per task than recorded (or the whole protocol) extends the run. An
  episode is fixed by its index in the protocol (its seed and initial state do not depend
  on how many are run), so the first 10 of 50 are the first 10 of 10: the recorded rows
  stay and only the new indices run. Fewer is refused, since a run folder is never cut
  short.
- A policy that gained a parameter since the rows were recorded (a package upgrade),
  at that parameter's default: the rows are taken as made at the default, which is what
  a defaulted parameter promises, instead of running every episode again.
- A checkpoint that the same config resolves to another path (a shipped checkpoint, or
  a set name such as `checkpoint=metaworld-mt10`, in a clone at another folder: run
  folders move between machines, CI clones to temporary folders): with the same file
  name and the same content (sha256) the rows are that model's, and the run continues
  under the recorded parameters and config id. With other content it is refused, since
  the rows would not be one model's (`adopt_moved_checkpoints`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from harness.config import ResolvedRun, build_config
from harness.episode.actions import DEFAULT_OUT_OF_SPACE
from harness.errors import UsageError
from policies.registry import (
    SHIPPED_CHECKPOINTS,
    PolicyParamError,
    UnknownPolicyError,
    get_policy,
    params_json,
    parse_params,
)
from results.generalization import split_perturbation
from results.store import ResultsFileError, RunDir

# Failure reasons that say the machinery failed, not the policy: a worker process or Ray
# actor lost (after --max-retries), a remote policy's server gone (policies/remote.py
# ConnectionLost). A plain --resume runs these episodes again; --retry-failed runs every
# failed episode again.
INFRASTRUCTURE_FAILURES = ("worker lost:", "ConnectionLost:")


def run_again(failure_reasons: pd.Series, retry_failed: bool = False) -> pd.Series:
    """Which recorded rows --resume runs again (True): infrastructure failures, and with
    --retry-failed every failure."""
    if retry_failed:
        return failure_reasons.notna()
    return failure_reasons.map(lambda r: isinstance(r, str) and r.startswith(INFRASTRUCTURE_FAILURES))


def recorded_config_data(out: Path) -> dict[str, Any] | None:
    """The config recorded in OUT's manifest, as config data for flags to override; None
    when OUT is not a run folder (check_output refuses it later, with the reason)."""
    run_dir = RunDir(out)
    if not run_dir.is_run():
        return None
    try:
        config = run_dir.read_manifest(required=("config",))["config"]
    except ResultsFileError as exc:
        raise UsageError(f"--resume: {exc}") from None
    data = config_data(config)
    try:
        build_config(dict(data))
    except UsageError as exc:
        raise UsageError(
            f"--resume: the config recorded in {run_dir.manifest_path} is not valid: {exc}"
        ) from None
    return data


def config_data(config: Mapping[str, Any]) -> dict[str, Any]:
    """A manifest's recorded config (RunConfig.to_dict) as config data (TOML keys)."""
    keys = (
        "suite", "tasks", "episodes_per_task", "replan_every", "split", "out_of_space", "inference_latency",
        "execution",
    )  # fmt: skip
    data = {key: config[key] for key in keys if key in config}
    if "policies" in config:
        data["policy"] = config["policies"]
    return data


def _policy_identity(entry: Any) -> str:
    """A config's policy entry as what it evaluates: the name and validated parameters."""
    name = entry.get("name") if isinstance(entry, Mapping) else getattr(entry, "name", None)
    raw = entry.get("params", {}) if isinstance(entry, Mapping) else getattr(entry, "params", {})
    try:
        return f"{name}:{params_json(parse_params(get_policy(str(name)), raw))}"
    except (UnknownPolicyError, PolicyParamError, TypeError):
        return f"{name}:{json.dumps(raw, sort_keys=True, default=str)}"


def _without_keys(policies: Any) -> Any:
    """Recorded policy entries with an inline `token` masked: a folder written before keys
    were refused inline holds one, and an error message must not repeat it."""
    if not isinstance(policies, list):
        return policies
    return [
        p | {"params": p["params"] | {"token": "<set>"}}
        if isinstance(p, dict) and isinstance(p.get("params"), dict) and p["params"].get("token")
        else p
        for p in policies
    ]


def _shown(value: Any) -> str:
    return json.dumps(value, default=str)


def _suite_hint(recorded: str, now: str, same_flag: bool) -> str:
    """Why a recorded suite name differs from the one --suite resolves to, and what to do.
    A LIBERO-PRO lan/task folder named before the `instruction=` option heard each BDDL's own
    words: `instruction=bddl` names that protocol now, but under a new name, so no --suite
    reproduces the recorded one and the only way on is a new run."""
    recorded_perturb, now_perturb = split_perturbation(recorded)[1], split_perturbation(now)[1]
    if "instruction=" not in recorded and "(instruction=bddl)" in recorded_perturb:
        bddl = now if "instruction=bddl" in now else now.replace("instruction=filename", "instruction=bddl")
        return (
            " (this folder was recorded before the `instruction=` suite option; its policy heard "
            "each BDDL's own words, which `instruction=bddl` names now under another suite name, so "
            f"it cannot be resumed: start a new run with --suite {bddl}"
            + (
                ""
                if now_perturb == recorded_perturb
                else ", or instruction=filename for LIBERO-PRO's published path"
            )
            + ")"
        )
    if same_flag:
        return (
            " (the same --suite now resolves to another protocol, e.g. a changed default such as "
            "LIBERO's seeding; name the recorded one in --suite)"
        )
    return ""


def config_changes(
    manifest: Mapping[str, Any], resolved: ResolvedRun
) -> tuple[list[str], tuple[int | None, int | None] | None]:
    """(the differences that refuse the resume, "key: recorded -> now" each; (recorded,
    new) episodes_per_task when the run is extended, else None)."""
    old, new = manifest["config"], resolved.config
    changes = []
    # the suite by the name it resolved to (its options spelled out), so that naming the
    # recorded protocol in --suite after a default changed is the same suite
    recorded_suite = (manifest.get("suite") or {}).get("name")
    if recorded_suite is None and old.get("suite") != new.suite:
        changes.append(f"suite: {_shown(old.get('suite'))} -> {_shown(new.suite)}")
    elif recorded_suite is not None and recorded_suite != resolved.suite.name:
        changes.append(
            f"suite: {_shown(recorded_suite)} -> {_shown(resolved.suite.name)}"
            f"{_suite_hint(recorded_suite, resolved.suite.name, old.get('suite') == new.suite)}"
        )
    recorded_version = (manifest.get("suite") or {}).get("version")
    if recorded_version is not None and recorded_version != resolved.suite.version:
        changes.append(
            f"suite version: {_shown(recorded_version)} -> {_shown(resolved.suite.version)} (the "
            "suite's episodes or scoring changed since the run began, e.g. the chain suites' credit "
            "rule: its rows would not compare; start a new run)"
        )
    recorded_tasks = (manifest.get("suite") or {}).get("tasks")
    tasks = [t.name for t in resolved.tasks]
    if recorded_tasks is None:  # a manifest without the resolved names: the config's
        recorded_tasks, tasks = [str(t) for t in old.get("tasks") or []], list(new.tasks)
    if sorted(map(str, recorded_tasks)) != sorted(tasks):
        changes.append(f"tasks: {_shown(recorded_tasks)} -> {_shown(tasks)}")
    recorded_policies = sorted(_policy_identity(p) for p in old.get("policies") or [])
    if recorded_policies != sorted(_policy_identity(p) for p in new.policies):
        shown = [dataclasses.asdict(p) for p in new.policies]
        changes.append(f"policies: {_shown(_without_keys(old.get('policies')))} -> {_shown(shown)}")
    # absent from older manifests: their defaults (rows before the action check ran unchecked)
    for key, default in (
        ("replan_every", 0),
        ("split", "eval"),
        ("out_of_space", DEFAULT_OUT_OF_SPACE),
        ("inference_latency", "none"),
        ("execution", "sync"),
    ):
        if old.get(key, default) != getattr(new, key):
            changes.append(f"{key}: {_shown(old.get(key, default))} -> {_shown(getattr(new, key))}")
    extended = None
    before, after = old.get("episodes_per_task"), new.episodes_per_task
    counts = [(_count(before, t.episodes), _count(after, t.episodes)) for t in resolved.tasks]
    if any(b > a for b, a in counts):
        changes.append(
            f"episodes_per_task: {_shown(before)} -> {_shown(after)} (fewer than recorded: a run "
            "folder is never cut short; `show` and `leaderboard` read it as it is)"
        )
    elif any(b < a for b, a in counts):
        extended = (before, after)
    return changes, extended


def _count(n: Any, episodes: tuple) -> int:
    return len(episodes) if n is None else min(int(n), len(episodes))


def adopt_recorded_params(
    manifest: Mapping[str, Any], recorded: pd.DataFrame, resolved: ResolvedRun
) -> list[str]:
    """Match rows recorded before a policy gained a defaulted parameter; returns one
    notice per such policy.

    A row's key holds the policy's full parameters, so after an upgrade that adds one the
    recorded rows would all look like another configuration and run again. When a
    recorded parameter set lacks only keys whose current value is their default, this
    run continues under the recorded parameters and config id (its new rows join the
    old ones as one configuration)."""
    seen = _recorded_sets(manifest, recorded)
    notices = []
    for run in resolved.policies:
        known = seen.get(run.spec.name, {})
        if not known or run.params_json in known:
            continue
        for params, (config_id, _digests) in known.items():
            added = _added_at_default(params, run.params_json, run.spec.params)
            if added:
                notices.append(
                    f"--resume: policy {run.spec.name!r} has parameters its recorded rows predate "
                    f"({', '.join(f'{k}={v!r}' for k, v in added.items())}); this run uses their "
                    f"defaults, so the rows count as made with them and new rows keep the recorded "
                    f"parameters (policy_config_id {config_id})"
                )
                run.params_json, run.config_id = params, config_id
                break
    return notices


def _added_at_default(recorded: str, current: str, params_cls: type) -> dict[str, Any]:
    """The parameters `current` has beyond `recorded`, if every other value is equal and
    each added one is at its default; else {}."""
    try:
        old, new = json.loads(recorded), json.loads(current)
        defaults = json.loads(params_json(params_cls()))
    except (ValueError, TypeError):
        return {}
    if not isinstance(old, dict) or not set(old) < set(new):
        return {}
    if any(old[k] != new[k] for k in old):
        return {}
    added = {k: new[k] for k in sorted(set(new) - set(old))}
    if set(added) & getattr(params_cls, "CHANGED_BY_ADDING", frozenset()):
        return {}  # its default is not what the recorded rows did (e.g. fast_dllm's blocks)
    return added if all(k in defaults and defaults[k] == v for k, v in added.items()) else {}


def changed_checkpoints(
    manifest: Mapping[str, Any], recorded: pd.DataFrame, resolved: ResolvedRun
) -> list[str]:
    """Policies whose checkpoint file now has other content than when the run recorded it.

    The config names a checkpoint by path; what was evaluated is its content, so a file
    replaced at the same path is another model, and resuming would put two models' rows
    under one policy label."""
    seen = _recorded_sets(manifest, recorded)
    changes = []
    for p in resolved.policies:
        _, digests = seen.get(p.spec.name, {}).get(p.params_json, ("", set()))
        old = sorted(digests - {p.checkpoint_sha256})
        if old:
            changes.append(
                f"policy {p.spec.name}: checkpoint {p.checkpoint!r} had sha256 {old[0][:12]} "
                f"and now has {(p.checkpoint_sha256 or 'none')[:12]}"
            )
    return changes


def _recorded_sets(
    manifest: Mapping[str, Any], recorded: pd.DataFrame
) -> dict[str, dict[str, tuple[str, set[str]]]]:
    """policy -> recorded params JSON -> (its config id, the checkpoint sha256s recorded
    with it), from the manifest's policies and the rows."""
    seen: dict[str, dict[str, tuple[str, set[str]]]] = {}
    for p in manifest.get("policies") or []:
        if isinstance(p.get("params"), str):
            entry = seen.setdefault(str(p.get("name")), {}).setdefault(
                p["params"], (str(p.get("config_id") or ""), set())
            )
            if p.get("checkpoint_sha256"):
                entry[1].add(str(p["checkpoint_sha256"]))
    if len(recorded):
        cols = ["policy", "policy_params", "policy_config_id", "checkpoint_sha256"]
        for name, params, config_id, digest in recorded[cols].drop_duplicates().itertuples(index=False):
            entry = seen.setdefault(name, {}).setdefault(params, (config_id, set()))
            if isinstance(digest, str) and digest:
                entry[1].add(digest)
    return seen


def _other_checkpoint(recorded: str, current: str, params_cls: type) -> tuple[str, dict[str, Any]] | None:
    """(the recorded `checkpoint`, the parameters the recorded set predates) when the two
    sets differ in `checkpoint` alone, or in it and parameters added at their defaults
    (_added_at_default: a package upgraded as well as moved); else None."""
    try:
        old, new = json.loads(recorded), json.loads(current)
    except (ValueError, TypeError):
        return None
    if not isinstance(old, dict) or not isinstance(new, dict) or "checkpoint" not in old:
        return None
    if "checkpoint" not in new or old["checkpoint"] == new["checkpoint"]:
        return None
    here = old | {"checkpoint": new["checkpoint"]}
    added = {} if here == new else _added_at_default(json.dumps(here), current, params_cls)
    return (str(old["checkpoint"]), added) if here == new or added else None


def _shipped_elsewhere(recorded: str, current: str) -> bool:
    """Whether `recorded` is this checkout's shipped checkpoint `current` in another
    checkout: the same file name under another folder's policies/checkpoints/."""
    old, new = Path(recorded), Path(current)
    return (
        new.parent == SHIPPED_CHECKPOINTS
        and old.name == new.name
        and old.parent.parts[-2:] == (SHIPPED_CHECKPOINTS.parent.name, SHIPPED_CHECKPOINTS.name)
    )


def adopt_moved_checkpoints(
    manifest: Mapping[str, Any], recorded: pd.DataFrame, resolved: ResolvedRun
) -> list[str]:
    """Match rows whose checkpoint the same config resolved to another path; returns one
    notice per such policy, or refuses (UsageError) when the rows cannot be matched.

    A row's key holds the checkpoint's path, and a shipped checkpoint (the decoders'
    default, or a set name) resolves to an absolute path inside the clone, so a run
    folder resumed from a clone at another folder would otherwise start every policy
    again as a new configuration beside its recorded rows. The config was already found
    equal (config_changes), so a path that differs is where this install keeps the file;
    with the same file name and the same sha256 the rows are this model's, and the run
    continues under the recorded parameters and config id. Any other recorded set that
    differs from a policy of this run in `checkpoint` alone, and that no policy of this
    run matches, is refused naming both files: running it again would put a second
    configuration of one policy beside the first."""
    seen = _recorded_sets(manifest, recorded)
    claimed = {(run.spec.name, run.params_json) for run in resolved.policies}
    notices = []
    for run in resolved.policies:
        known = seen.get(run.spec.name, {})
        if run.params_json in known or not run.checkpoint:
            continue
        for params, (config_id, digests) in known.items():
            other = _other_checkpoint(params, run.params_json, run.spec.params)
            if (run.spec.name, params) in claimed or other is None:
                continue
            path, added = other
            if Path(path).name != Path(run.checkpoint).name:
                continue
            if digests != {run.checkpoint_sha256}:
                continue
            what = "shipped checkpoint" if _shipped_elsewhere(path, run.checkpoint) else "checkpoint file"
            notices.append(
                f"--resume: policy {run.spec.name!r}: its rows were recorded with the same {what} "
                f"(sha256 {run.checkpoint_sha256[:12]}) at another path, {path}; this run loads "
                f"{run.checkpoint} and keeps the recorded parameters (policy_config_id {config_id})"
                + (
                    f"; parameters the rows predate are at their defaults "
                    f"({', '.join(f'{k}={v!r}' for k, v in added.items())})"
                    if added
                    else ""
                )
            )
            claimed.add((run.spec.name, params))
            run.params_json, run.config_id = params, config_id
            break
    refusals = []
    for run in resolved.policies:
        known = seen.get(run.spec.name, {})
        if run.params_json in known:
            continue
        for params, (_config_id, digests) in known.items():
            other = _other_checkpoint(params, run.params_json, run.spec.params)
            if (run.spec.name, params) not in claimed and other is not None:
                refusals.append(_unmatched(run, other[0], digests, manifest))
                claimed.add((run.spec.name, params))
                break
    if refusals:
        raise UsageError("--resume: " + "; ".join(refusals))
    return notices


def _unmatched(run: Any, path: str, digests: set[str], manifest: Mapping[str, Any]) -> str:
    """Why rows recorded with checkpoint `path` are not this run's, and what to do."""
    old = ", ".join(sorted(d[:12] for d in digests)) or "none recorded"
    now = (run.checkpoint_sha256 or "none")[:12]
    said = (
        f"policy {run.spec.name!r}: its rows were recorded with checkpoint {path} (sha256 {old}) "
        f"and this run resolves it to {run.checkpoint} (sha256 {now})"
    )
    if _shipped_elsewhere(path, run.checkpoint):
        commit = (manifest.get("environment") or {}).get("git_commit")
        at = (
            f" ({commit[:12]}, the manifest's environment.git_commit)"
            if isinstance(commit, str) and commit
            else ""
        )
        return (
            f"{said}: the shipped checkpoint changed between the checkout that recorded the rows and "
            f"this one, so the rows are another model's. Resume from a checkout of the commit that "
            f"recorded them{at}, or start a new --out"
        )
    return (
        f"{said}: resuming would start it again as a new configuration beside its rows. Resume "
        f"where the config resolves to the recorded file, or start a new --out"
    )
