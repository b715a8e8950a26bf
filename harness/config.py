"""Run configuration: the embedded default, overridden by a TOML file, overridden by flags.

A `RunConfig` is plain data (what to evaluate). `merge_config` applies the precedence
(the embedded default, or on --resume the config the folder recorded; then --config;
then the flags); `resolve` turns the result into a `ResolvedRun` (suite loaded, tasks
chosen, policies built, checkpoints hashed) and is where every bad
input is caught, before any output folder is created.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import tomllib
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from importlib import resources
from pathlib import Path
from typing import Any

from adapters.base import EpisodeSpec, Suite, TaskSpec
from adapters.registry import (
    MissingExtraError,
    SuiteDataError,
    UnknownSuiteError,
    load_suite,
    origin_for,
    provider_for,
)
from harness.episode.actions import DEFAULT_OUT_OF_SPACE, check_rule
from harness.episode.latency import check_execution, parse_latency
from harness.episode.latency import check_run as check_latency
from harness.errors import HarnessError, UsageError
from harness.plugins import HARNESS, install_hint, one_line
from policies.base import Policy
from policies.registry import (
    PolicyParamError,
    PolicySpec,
    UnknownPolicyError,
    get_policy,
    params_json,
    parse_params,
    plugin_of,
    shipped_changed,
)

# batch_envs is how to execute (like --workers), read by `run` into its Execution: it is
# not in RunConfig, so not in the fingerprint, and a resume may use another batch size.
CONFIG_KEYS = (
    "suite", "tasks", "episodes_per_task", "replan_every", "policy", "split", "batch_envs", "out_of_space",
    "inference_latency", "execution",
)  # fmt: skip
SPLITS = ("eval", "train")


@dataclass(frozen=True)
class PolicyChoice:
    name: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunConfig:
    suite: str
    policies: tuple[PolicyChoice, ...]
    tasks: tuple[str, ...] = ()  # names or indices; empty = every task of the suite
    episodes_per_task: int | None = None  # None = every episode spec of the protocol
    replan_every: int = 0  # 0 = execute the whole chunk before asking again
    split: str = "eval"  # "train": episodes disjoint from evaluation, for demonstrations
    # What an action outside the action space does: fail, clip or record (harness/episode/actions.py).
    out_of_space: str = DEFAULT_OUT_OF_SPACE
    # Simulated decoding time (harness/episode/latency.py, docs/latency.md): the mode as recorded,
    # and whether the robot waits for each chunk (sync) or keeps moving (async).
    inference_latency: str = "none"
    execution: str = "sync"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def fingerprint(self) -> str:
        """Identity of what this config evaluates; a resumed folder must match it."""
        text = json.dumps(self.to_dict(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def parse_policy_arg(text: str) -> PolicyChoice:
    """`NAME` or `NAME:key=value,key=value` (the --policy flag)."""
    name, _, rest = text.partition(":")
    params: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise UsageError(f"--policy {text!r}: expected NAME:key=value[,key=value...], got {item!r}")
        if key.strip() in params:
            raise UsageError(f"--policy {text!r}: parameter {key.strip()!r} is given twice")
        params[key.strip()] = value
    if not name.strip():
        raise UsageError(f"--policy {text!r}: missing policy name")
    return PolicyChoice(name.strip(), params)


def _read_toml(text: str, where: str) -> dict[str, Any]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UsageError(f"{where}: invalid TOML ({exc})") from None
    unknown = sorted(set(data) - set(CONFIG_KEYS))
    if unknown:
        raise UsageError(f"{where}: unknown key {unknown[0]!r}; valid keys: {', '.join(CONFIG_KEYS)}")
    return data


def default_config_data() -> dict[str, Any]:
    text = resources.files("harness").joinpath("defaults/main.toml").read_text()
    return _read_toml(text, "embedded default config")


def load_config_file(path: str) -> dict[str, Any]:
    p = Path(path)
    if not p.is_file():
        raise UsageError(f"config file {path!r} does not exist")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UsageError(
            f"config file {path!r} is not UTF-8 text (byte {exc.start}); TOML files are UTF-8"
        ) from None
    except OSError as exc:
        raise UsageError(f"config file {path!r} cannot be read: {exc.strerror or exc}") from None
    return _read_toml(text, path)


def with_variants(suite: str, variants: str) -> str:
    """`--variants X` as the suite option it stands for (one place decides what a suite
    name means, so a run's rows and manifest carry the selection)."""
    base, _, opts = suite.partition(":")
    if not base.startswith("simpler/"):
        raise UsageError(f"--variants applies to the simpler/ suites (SimplerEnv-like), not {base!r}")
    kept = [o for o in opts.split(",") if o.strip() and not o.strip().startswith("variants=")]
    return f"{base}:" + ",".join([f"variants={variants}", *kept])


# Flags that are config keys as they are (None: not given); `tasks` and `policy` come parsed.
FLAG_KEYS = (
    "suite", "tasks", "policy", "episodes_per_task", "replan_every", "out_of_space", "inference_latency",
    "execution",
)  # fmt: skip


def merge_config(
    recorded: dict[str, Any] | None, config_file: str | None, flags: dict[str, Any]
) -> tuple[RunConfig, int | None]:
    """The run's config by precedence: the embedded default (or `recorded`, the config a
    folder being resumed recorded) < `config_file` (--config) < `flags` (each None when
    not given; also `variants` and `batch_envs`). Returns it with the batch size asked for
    (the flag, else the file's; None: neither), which is how to run, not what, so it is no
    part of the config or its fingerprint."""
    data = default_config_data() if recorded is None else recorded
    overrides = load_config_file(config_file) if config_file else {}
    batch_envs = flags.get("batch_envs")
    if batch_envs is None:
        batch_envs = overrides.get("batch_envs")
    if flags.get("suite"):
        overrides["suite"] = flags["suite"]
    if recorded is None and overrides.get("suite", data["suite"]) != data["suite"]:
        # The default's task subset and episode count are the main job's, not the protocol's.
        data.pop("tasks", None)
        data.pop("episodes_per_task", None)
    data |= overrides
    if flags.get("variants"):
        data["suite"] = with_variants(data["suite"], flags["variants"])
    for key in FLAG_KEYS:
        if key != "suite" and flags.get(key) is not None:
            data[key] = flags[key]
    data.pop("batch_envs", None)
    return build_config(data), batch_envs


def _positive_int(value: Any, what: str, allow_zero: bool = False) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise UsageError(f"{what} must be an integer, got {value!r}")
    if value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else ">= 1"
        raise UsageError(f"{what} must be {bound}, got {value}")
    return value


def build_config(data: dict[str, Any]) -> RunConfig:
    """Typed config from merged TOML/flag data; type and range errors are UsageErrors."""
    policies = []
    entries = data.get("policy", [])
    if not isinstance(entries, (list, tuple)):
        raise UsageError(
            f"policy must be a list of [[policy]] tables (name, params), got {type(entries).__name__} {entries!r}"
        )
    for i, entry in enumerate(entries):
        if isinstance(entry, PolicyChoice):
            policies.append(entry)
            continue
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise UsageError(f"policy entry {i} must be a table with a 'name' string")
        extra = sorted(set(entry) - {"name", "params"})
        if extra:
            raise UsageError(f"policy entry {i}: unknown key {extra[0]!r}; valid keys: name, params")
        params = entry.get("params", {})
        if not isinstance(params, dict):
            raise UsageError(f"policy entry {i}: 'params' must be a table")
        policies.append(PolicyChoice(entry["name"], dict(params)))
    if not policies:
        raise UsageError("no policy given; pass --policy NAME (see `dvla-harness list policies`)")
    suite = data.get("suite")
    if not isinstance(suite, str) or not suite:
        raise UsageError("no suite given; pass --suite NAME (see `dvla-harness list suites`)")
    tasks = data.get("tasks", ())
    if not isinstance(tasks, (list, tuple)) or not all(
        isinstance(t, (str, int)) and not isinstance(t, bool) for t in tasks
    ):
        raise UsageError(f"tasks must be a list of task names or indices, got {tasks!r}")
    episodes = data.get("episodes_per_task")
    if episodes is not None:
        episodes = _positive_int(episodes, "--episodes-per-task")
    replan = _positive_int(data.get("replan_every", 0), "--replan-every", allow_zero=True)
    split = data.get("split", "eval")
    if split not in SPLITS:
        raise UsageError(f"split {split!r} is not valid; choose one of {', '.join(SPLITS)}")
    out_of_space = check_rule(data.get("out_of_space", DEFAULT_OUT_OF_SPACE), "out_of_space")
    latency = parse_latency(data.get("inference_latency", "none")).text
    execution = check_execution(data.get("execution", "sync"))
    return RunConfig(
        suite=suite,
        policies=tuple(policies),
        tasks=tuple(str(t) for t in tasks),
        episodes_per_task=episodes,
        replan_every=replan,
        split=split,
        out_of_space=out_of_space,
        inference_latency=latency,
        execution=execution,
    )


@dataclass
class PolicyRun:
    """One policy configuration of a run: spec, validated params, the built policy."""

    spec: PolicySpec
    params: Any
    params_json: str
    checkpoint: str
    checkpoint_sha256: str
    config_id: str
    policy: Policy


@dataclass
class ResolvedRun:
    config: RunConfig
    suite: Suite
    tasks: tuple[TaskSpec, ...]
    policies: list[PolicyRun]

    def episodes(self, task: TaskSpec) -> tuple[EpisodeSpec, ...]:
        return first_per_variant(task.episodes, self.config.episodes_per_task)


def _variant_of(spec: EpisodeSpec) -> tuple:
    return tuple(sorted(spec.variant.items()))


def first_per_variant(specs: tuple[EpisodeSpec, ...], n: int | None) -> tuple[EpisodeSpec, ...]:
    """The first n episodes of each variant (SimplerEnv-like suites run every episode under
    every variant: --episodes-per-task counts layouts, not layouts x variants); suites
    without variants: the first n."""
    if n is None:
        return specs
    taken: dict[tuple, int] = {}
    out = []
    for spec in specs:
        key = _variant_of(spec)
        if taken.get(key, 0) < n:
            out.append(spec)
            taken[key] = taken.get(key, 0) + 1
    return tuple(out)


def sha256_file(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _check_installed(modules: tuple[str, ...], extra: str, what: str, package: str = HARNESS) -> None:
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        how = install_hint(extra, package) if extra else "install them"
        raise UsageError(f"{what} needs {', '.join(missing)}: {how}")


def resolve_suite(config: RunConfig) -> tuple[Suite, tuple[TaskSpec, ...]]:
    try:
        suite = load_suite(config.suite, config.split)
    except (UnknownSuiteError, MissingExtraError, SuiteDataError) as exc:
        raise UsageError(str(exc)) from None
    except Exception as exc:  # a provider's own bug: name it, exit 2 (1 is an episode that raised)
        raise UsageError(
            f"suite {config.suite!r}: its provider ({origin_for(config.suite)}) raised {one_line(exc)}"
        ) from None
    who = provider_for(config.suite)
    what = f"suite {suite.name!r}" + ("" if who == HARNESS else f" (from {who})")
    _check_installed(suite.simulator_packages, suite.extra, what, who.split(" ")[0])
    tasks: list[TaskSpec] = []
    for name in config.tasks or [t.name for t in suite.tasks]:
        try:
            tasks.append(suite.task(name))
        except KeyError:
            valid = ", ".join(t.name for t in suite.tasks)
            raise UsageError(
                f"suite {suite.name!r} has no task {name!r}; valid tasks (or 0..{len(suite.tasks) - 1}): {valid}"
            ) from None
    n = config.episodes_per_task
    for task in tasks:
        first = _variant_of(task.episodes[0]) if task.episodes else ()
        per_variant = sum(1 for s in task.episodes if _variant_of(s) == first)
        if n is not None and n > per_variant:
            raise UsageError(
                f"--episodes-per-task {n}: task {task.name!r} of {suite.name!r} defines "
                f"{per_variant} episodes"
                + (" per variant" if per_variant < len(task.episodes) else "")
                + f"; valid range 1..{per_variant}"
            )
    unique = {t.name: t for t in tasks}  # a task named twice runs once
    return suite, tuple(unique.values())


def resolve_policy(choice: PolicyChoice, suite: Suite, announce: bool = True) -> PolicyRun:
    """`choice` built for `suite`: parameters validated, checkpoint hashed, policy built.
    announce: say what the writing process should say once (a shipped checkpoint whose
    bytes changed); workers resolve the run again without it."""
    try:
        spec = get_policy(choice.name)
        params = parse_params(spec, choice.params)
    except (UnknownPolicyError, PolicyParamError) as exc:
        raise UsageError(str(exc)) from None
    except Exception as exc:  # a plugin's own parameter check raised
        raise policy_error(choice.name, "checking its parameters", exc) from None
    if spec.suites and not any(suite.name.startswith(p) for p in spec.suites):
        raise UsageError(
            f"policy {spec.name!r} cannot act in suite {suite.name!r}; it supports: "
            f"{', '.join(p + '*' for p in spec.suites)}"
        )
    checkpoint = str(getattr(params, "checkpoint", "") or "")
    if checkpoint and not Path(checkpoint).is_file():
        from policies.dvla.policy import shipped_sets

        raise UsageError(
            f"policy {spec.name!r}: checkpoint {checkpoint!r} does not exist; pass a path or a "
            f"shipped set: {', '.join(shipped_sets())}"
        )
    digest = sha256_file(checkpoint) if checkpoint else ""
    changed = shipped_changed(checkpoint, digest) if announce else ""
    if changed:
        warnings.warn(changed, UserWarning, stacklevel=2)
    pjson = params_json(params)
    config_id = policy_config_id(spec.name, pjson, digest)
    try:
        policy = spec.build(params)
    except Exception as exc:
        raise policy_error(spec.name, "building it", exc) from None
    if checkpoint:  # what was loaded is what was hashed: the file did not change meanwhile
        check_checkpoints(((spec.name, checkpoint, digest),))
    return PolicyRun(spec, params, pjson, checkpoint, digest, config_id, policy)


def policy_error(name: str, doing: str, exc: Exception) -> Exception:
    """An exception from a policy's own code as one line and exit 2: a plugin's names the
    plugin and its entry point, whatever it raised (RuntimeError, ImportError, a CUDA
    error), since the fix is there and not in the harness; a built-in policy's says why
    it could not be built (a bad value or file), and anything else from one is a bug of
    the harness, re-raised with its traceback."""
    plugin = plugin_of(name)
    if plugin:
        return UsageError(f"policy {name!r}: its plugin ({plugin}) raised {one_line(exc)} while {doing}")
    if isinstance(exc, (ValueError, OSError)) and doing == "building it":
        return UsageError(f"policy {name!r} could not be built: {exc}")
    return exc


def policy_config_id(name: str, pjson: str, digest: str) -> str:
    """A policy configuration's id: its name, validated parameters and checkpoint content."""
    return hashlib.sha256(f"{name}|{pjson}|{digest}".encode()).hexdigest()[:12]


def readopted(rebuild: Callable[[], ResolvedRun], adopted: dict[str, tuple[str, str]]) -> ResolvedRun:
    """A worker's rebuilt run with the parameters and config ids that --resume adopted
    from the recorded rows (harness/run/resume.py), keyed by the id the config resolves to:
    the worker finds each episode it is sent by that id."""
    resolved = rebuild()
    for p in resolved.policies:
        if p.config_id in adopted:
            p.params_json, p.config_id = adopted[p.config_id]
    return resolved


def worker_rebuild(rebuild: Callable[[], ResolvedRun], resolved: ResolvedRun) -> Callable[[], ResolvedRun]:
    """`rebuild`, applying what this run adopted on --resume (none: `rebuild` itself)."""
    adopted = {}
    for p in resolved.policies:
        try:
            resolved_as = params_json(p.params)
        except (TypeError, ValueError):
            continue  # not a registry's parameters (a test's stand-in): nothing was adopted
        if resolved_as != p.params_json:
            adopted[policy_config_id(p.spec.name, resolved_as, p.checkpoint_sha256)] = (
                p.params_json,
                p.config_id,
            )
    return partial(readopted, rebuild, adopted) if adopted else rebuild


class CheckpointChanged(HarnessError):
    """A checkpoint file no longer has the content the run hashed (exit 3)."""


CheckpointPin = tuple[str, str, str]  # policy name, checkpoint path, the sha256 the run recorded


def checkpoint_pins(resolved: ResolvedRun) -> tuple[CheckpointPin, ...]:
    """What a worker must find at each checkpoint path: the content this run hashed."""
    return tuple((p.spec.name, p.checkpoint, p.checkpoint_sha256) for p in resolved.policies if p.checkpoint)


RESUME_ADVICE = "put the original back and --resume, or start a new run (--out) for the new file"


def check_checkpoints(
    pins: tuple[CheckpointPin, ...], resolved: ResolvedRun | None = None, advice: str = RESUME_ADVICE
) -> None:
    """Refuse (CheckpointChanged) a checkpoint whose file, or whose copy in `resolved`
    (a worker's rebuilt run), is not the one the run hashed. Rows name a model by its
    sha256; a worker that loaded other bytes would record another model's episodes
    under it, or (its policy ids no longer matching) lose every episode it is sent.
    `advice` is what the caller's command can do about it (`collect` has no --resume)."""
    built = {p.checkpoint: p.checkpoint_sha256 for p in resolved.policies} if resolved else {}
    for name, path, digest in pins:
        try:
            now = built[path] if path in built else sha256_file(path)
        except OSError as exc:
            now = f"unreadable ({exc.strerror or exc})"
        if now != digest:
            raise CheckpointChanged(
                f"policy {name}: checkpoint {path} changed during the run: the run hashed sha256 "
                f"{digest}, the file now has {now}; {advice}"
            )


def resolve(config: RunConfig, announce: bool = True) -> ResolvedRun:
    """`config` made real: suite, tasks and policies (announce: as resolve_policy)."""
    suite, tasks = resolve_suite(config)
    runs = [resolve_policy(choice, suite, announce) for choice in config.policies]
    seen: dict[str, str] = {}
    for run in runs:
        if run.config_id in seen:
            raise UsageError(f"policy {run.spec.name!r} is listed twice with the same parameters")
        seen[run.config_id] = run.spec.name
    check_latency(parse_latency(config.inference_latency), suite, [r.spec.name for r in runs])
    return ResolvedRun(config, suite, tasks, runs)


def rebuild_from_config(config: RunConfig) -> ResolvedRun:
    """What a worker runs to get its own ResolvedRun (the default `Execution.rebuild`):
    the same config resolved again in its own process (a built policy is not sent
    between processes); what the writing process said once is not said again."""
    return resolve(config, announce=False)
