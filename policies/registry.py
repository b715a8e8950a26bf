"""Finds policies by name and turns `key=value` strings into typed, validated parameters.

Each policy declares its parameters as a frozen dataclass whose fields carry a help
text and a valid range (`param(...)`). That one declaration drives parsing, validation,
`dvla-harness list policies`, and the JSON recorded in every result row. Third-party
packages add policies through the `dvla_harness.policies` entry-point group; each entry
point names a `PolicySpec`.
"""

from __future__ import annotations

import dataclasses
import fractions
import functools
import importlib
import json
import math
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from harness.plugins import HARNESS, load_plugins, origin, warn

# The policy contract (policies/spec.py), which plugins import from here (docs/plugins.md).
from policies.spec import NoParams as NoParams
from policies.spec import PolicySpec
from policies.spec import param as param

ENTRY_POINT_GROUP = "dvla_harness.policies"
# The shipped checkpoint sets (policies.dvla.policy.SHIPPED), named in `list policies`.
SHIPPED_CHECKPOINTS = Path(__file__).resolve().parent / "checkpoints"


class UnknownPolicyError(LookupError):
    """No policy has that name; the message lists the valid ones."""


class PolicyParamError(ValueError):
    """A parameter is unknown, of the wrong type or out of range; the message says which."""


# The built-in policies, as "module:NAME" (a PolicySpec, or a list of them: one per dVLA
# decoder), in the order `list policies` shows them: imported when policies are asked
# for, the way a plugin's entry point is, so the policies need not import the registry.
BUILTIN = (
    "policies.experts.scripted:SCRIPTED",
    "policies.experts.scripted:RANDOM",
    "policies.experts.libero_scripted:LIBERO_SCRIPTED",
    "policies.experts.maniskill_scripted:MANISKILL_SCRIPTED",
    "policies.remote:REMOTE",
    "policies.lerobot:LEROBOT",
    "policies.vlaeval:VLAEVAL",
    "policies.playback:PLAYBACK",
    "policies.dvla.policy:SPECS",
)


def _builtin_specs() -> list[PolicySpec]:
    specs: list[PolicySpec] = []
    for where in BUILTIN:
        module, _, name = where.partition(":")
        found = getattr(importlib.import_module(module), name)
        specs += found if isinstance(found, list) else [found]
    return specs


def all_policies() -> dict[str, PolicySpec]:
    """Built-in policies, then plugins'. A plugin may not take a name that is already
    registered (a built-in's or an earlier plugin's): it is refused with a warning naming
    both providers, never a silent replacement."""
    specs = {spec.name: spec for spec in _builtin_specs()}
    providers = dict.fromkeys(specs, HARNESS)
    ENTRY_POINTS.clear()
    for plugin in load_plugins(ENTRY_POINT_GROUP, PolicySpec):
        name = plugin.obj.name
        if name in specs:
            warn(
                f"plugin {plugin.provider} registers policy {name!r}, which {providers[name]} already "
                "provides; the plugin's is ignored (give it another name)"
            )
            continue
        specs[name], providers[name] = plugin.obj, plugin.provider
        ENTRY_POINTS[name] = plugin.entry_point
    PROVIDERS.clear()
    PROVIDERS.update(providers)
    return specs


# Who provided each policy name, as of the last all_policies(): "dvla-harness" or a plugin's
# "<distribution> <version>"; recorded in every run's manifest.
PROVIDERS: dict[str, str] = {}
# A plugin policy's entry point ("'constant' in dvla_harness.policies"), for its errors.
ENTRY_POINTS: dict[str, str] = {}


def plugin_of(name: str) -> str:
    """The plugin that provides policy `name`, with its entry point; '' for the harness's
    own policies (an exception from one of those is a bug of the harness: a traceback)."""
    provider = PROVIDERS.get(name, HARNESS)
    return "" if provider == HARNESS else origin(provider, ENTRY_POINTS.get(name, ""))


def get_policy(name: str) -> PolicySpec:
    specs = all_policies()
    if name not in specs:
        raise UnknownPolicyError(f"unknown policy {name!r}; valid policies: {', '.join(sorted(specs))}")
    return specs[name]


def describe_param(f: dataclasses.Field, type_name: str) -> str:
    """One line of `list policies`: a parameter as a person reads it (2/7 rather than
    0.2857142857142857, "any integer >= 0" rather than the int64 limit, a shipped
    checkpoint by its set's name rather than an install path)."""
    meta = f.metadata
    rng = ""
    low, high = meta.get("low"), meta.get("high")
    if meta.get("choices"):
        rng = " one of " + "|".join(str(c) for c in meta["choices"])
    elif type_name == "int" and low in (None, INT64[0]) and high in (None, INT64[1]):
        rng = ", any integer"
    elif type_name == "int" and high in (None, INT64[1]):
        rng = f", any integer >= {low}"
    elif low is not None or high is not None:
        lo = "-inf" if low in (None, INT64[0]) else show_number(low)
        hi = "inf" if high in (None, INT64[1]) else show_number(high)
        rng = f" in [{lo}, {hi}]"
    return f"{f.name}: {type_name} = {show_default(f.default)}{rng}  {meta.get('help', '')}"


def show_number(value: Any) -> str:
    """A float to 4 significant digits, with the small fraction it is when it is one:
    0.2857142857142857 -> '0.2857 (2/7)'; 0.5 -> '0.5'; an int as it is."""
    if not isinstance(value, float) or not math.isfinite(value):
        return str(value)
    short = format(value, ".4g")
    if "." not in short and "e" not in short:
        short += ".0"  # still reads as a float
    if float(short) == value:
        return short
    frac = fractions.Fraction(value).limit_denominator(64)
    return f"{short} ({frac})" if abs(float(frac) - value) < 1e-12 else short


# The known sha256 of every shipped checkpoint, in `sha256sum` format (`sha256sum -c
# checkpoints.sha256` in the folder checks them too); a test keeps it equal to the files.
SHIPPED_SUMS = "checkpoints.sha256"


@functools.cache
def shipped_digests(folder: Path) -> dict[str, str]:
    """file name -> known sha256 of each checkpoint shipped in `folder` ({} without a list)."""
    try:
        lines = (folder / SHIPPED_SUMS).read_text().splitlines()
    except OSError:
        return {}
    pairs = (line.split(None, 1) for line in lines)
    return {pair[1].strip().lstrip("*"): pair[0] for pair in pairs if len(pair) == 2}


def shipped_changed(checkpoint: str, digest: str) -> str:
    """Why a shipped checkpoint's bytes are not the ones it was shipped with ('' when they
    are, or the file is not a shipped name). Its rows would carry a sha256 no published
    figure has, under a name every reader takes for the shipped model."""
    if not checkpoint:
        return ""
    path = Path(checkpoint).resolve()
    known = (
        shipped_digests(SHIPPED_CHECKPOINTS).get(path.name) if path.parent == SHIPPED_CHECKPOINTS else None
    )
    if known is None or known == digest:
        return ""
    return (
        f"shipped checkpoint {path.name} does not hold the bytes it was shipped with (sha256 "
        f"{digest[:12]}, known {known[:12]} in {SHIPPED_CHECKPOINTS.name}/{SHIPPED_SUMS}): it was "
        "modified or damaged, so its rows are not the shipped model's; restore it (git checkout, "
        "or reinstall dvla-harness)"
    )


def show_default(value: Any) -> str:
    if isinstance(value, float):
        return show_number(value)
    if isinstance(value, str):
        path = Path(value)
        if path.is_absolute() and path.parent == SHIPPED_CHECKPOINTS and path.suffix == ".safetensors":
            return f"{path.stem.rsplit('-', 1)[0]} (shipped set)"
    return repr(value)


def portable_checkpoint(spec: PolicySpec, value: str) -> str:
    """A shipped checkpoint file as its set name (`metaworld-mt10`), which `checkpoint=`
    turns back into the same file for this policy, so a results file committed to the
    repository names no folder of the machine that wrote it; a shipped file the set name
    would not give back is named by its path in the package. Any other value unchanged:
    a user's own checkpoint is wherever they keep it."""
    path = Path(value)
    if not (path.is_absolute() and path.parent == SHIPPED_CHECKPOINTS and path.suffix == ".safetensors"):
        return value
    name = path.stem.rsplit("-", 1)[0]
    try:
        same = getattr(parse_params(spec, {"checkpoint": name}), "checkpoint", None) == value
    except PolicyParamError:
        same = False
    return name if same else f"{SHIPPED_CHECKPOINTS.parent.name}/{SHIPPED_CHECKPOINTS.name}/{path.name}"


def param_types(params_cls: type) -> dict[str, type]:
    hints = typing.get_type_hints(params_cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(params_cls)}


INT64 = (-(2**63), 2**63 - 1)  # what an integer parameter may hold when it names no range


def _coerce(policy: str, name: str, kind: type, raw: Any) -> Any:
    value = _coerce_type(policy, name, kind, raw)
    if kind is float and not math.isfinite(value):
        raise PolicyParamError(f"policy {policy!r}: parameter {name!r} must be a finite number, got {raw!r}")
    return value


def _coerce_type(policy: str, name: str, kind: type, raw: Any) -> Any:
    if isinstance(raw, str):
        text = raw.strip()
        try:
            if kind is bool:
                low = text.lower()
                if low not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError
                return low in ("true", "1", "yes")
            if kind is int:
                return int(text)
            if kind is float:
                return float(text)
        except ValueError:
            raise PolicyParamError(
                f"policy {policy!r}: parameter {name!r} must be {kind.__name__}, got {raw!r}"
            ) from None
        return text
    if kind is float and isinstance(raw, int) and not isinstance(raw, bool):
        return float(raw)
    if not isinstance(raw, kind) or (kind is int and isinstance(raw, bool)):
        raise PolicyParamError(f"policy {policy!r}: parameter {name!r} must be {kind.__name__}, got {raw!r}")
    return raw


def parse_params(spec: PolicySpec, raw: Mapping[str, Any]) -> Any:
    """Build the policy's parameter dataclass from strings or native values, validated."""
    types = param_types(spec.params)
    unknown = sorted(set(raw) - set(types))
    if unknown:
        valid = ", ".join(types) or "(none)"
        raise PolicyParamError(
            f"policy {spec.name!r} has no parameter {unknown[0]!r}; valid parameters: {valid}"
        )
    values = {k: _coerce(spec.name, k, types[k], v) for k, v in raw.items()}
    for f in dataclasses.fields(spec.params):
        value = values.get(f.name, f.default)
        meta = f.metadata
        choices = meta.get("choices")
        if choices and value not in choices:
            raise PolicyParamError(
                f"policy {spec.name!r}: {f.name}={value!r} is not valid; "
                f"choose one of {', '.join(map(str, choices))}"
            )
        low, high = meta.get("low"), meta.get("high")
        if isinstance(value, int) and not isinstance(value, bool):  # stays a machine integer
            low = INT64[0] if low is None else low
            high = INT64[1] if high is None else high
        if (low is not None and value < low) or (high is not None and value > high):
            lo = "-inf" if low is None else low
            hi = "inf" if high is None else high
            raise PolicyParamError(
                f"policy {spec.name!r}: {f.name}={value!r} is out of range; valid range [{lo}, {hi}]"
            )
    params = spec.params(**values)
    validate = getattr(params, "validate", None)
    if validate is not None:
        try:
            validate()
        except ValueError as exc:
            raise PolicyParamError(f"policy {spec.name!r}: {exc}") from None
    return params


def access_params(params: Any) -> dict[str, Any]:
    """The parameters declared `identity=False` (how to reach the policy), by name."""
    return {
        f.name: getattr(params, f.name)
        for f in dataclasses.fields(params)
        if not f.metadata.get("identity", True)
    }


def params_json(params: Any) -> str:
    """Canonical JSON of the full parameter set (defaults included), for rows and keys;
    without the `identity=False` ones (access_params), which no results file records."""
    access = access_params(params)
    values = {k: v for k, v in dataclasses.asdict(params).items() if k not in access}
    return json.dumps(values, sort_keys=True, separators=(",", ":"), allow_nan=False)
