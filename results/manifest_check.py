"""What a run's manifest.json must look like to be read: a JSON object whose known fields
have the types the harness writes. A hand-edited or foreign manifest is refused with one
line naming the field, instead of failing deep inside whichever command reads it.

Readers (show, leaderboard, gate, plots) need no field at all: a manifest lacking one
just says less about the run. `--resume` needs the fields it continues from
(RESUME_FIELDS), since it writes the manifest back.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

NoneType = type(None)
NUMBER = (int, float)

# dotted path -> the JSON types it may have (checked only where present)
FIELD_TYPES: dict[str, tuple[type, ...]] = {
    "manifest_version": (int,),
    "run_id": (str,),
    "config": (dict,),
    "config_fingerprint": (str,),
    "suite": (dict,),
    "suite.name": (str,),
    "suite.version": (str,),
    "suite.tasks": (list,),
    "suite.render_backend": (str, NoneType),
    "suite.simulator_packages": (dict,),
    "policies": (list,),
    "environment": (dict,),
    "environment.packages": (dict,),
    "environment.simulators": (dict,),
    "calibration": (dict, NoneType),
    "calibration.start": (dict, NoneType),
    "calibration.end": (dict, NoneType),
    "calibration.start.passes_per_s": NUMBER,
    "calibration.end.passes_per_s": NUMBER,
    "calibration.torch_threads": (int, NoneType),
    "command": (list,),
    "started_at": (str, NoneType),
    "finished_at": (str, NoneType),
    "resumed_at": (list,),
    "status": (str,),
    "speed_reliable": (bool,),
    "speed_warning": (str,),
    "starvation": (dict,),  # starved episodes counted at the run's end (harness/run/manifest.py)
    "starvation.starved_episodes": (int,),
    "starvation.judged_episodes": (int,),
    "starvation.factor": NUMBER,
    "starvation.worst_ratio": (int, float, NoneType),
    "traces": (bool,),
    "extended": (list,),  # --resume with more episodes per task (harness/run/resume.py)
}
# what `--resume` reads and writes back
RESUME_FIELDS = ("run_id", "config", "suite", "policies", "resumed_at", "status")

_JSON_NAMES = {
    dict: "an object",
    list: "a list",
    str: "a string",
    int: "an integer",
    float: "a number",
    bool: "true or false",
    NoneType: "null",
}


class ManifestError(ValueError):
    """The manifest is not the object the harness writes; the message names the field."""


def _lookup(data: Mapping[str, Any], dotted: str) -> tuple[bool, Any]:
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False, None
        node = node[part]
    return True, node


def _is(value: Any, types: tuple[type, ...]) -> bool:
    if isinstance(value, bool) and bool not in types:
        return False  # JSON true is not a number
    return isinstance(value, types)


def check_manifest(data: Any, path: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """`data` (parsed JSON) if it is a usable manifest, else ManifestError naming the problem."""
    if not isinstance(data, dict):
        raise ManifestError(
            f"{path}: not a run manifest (a JSON object), got {_JSON_NAMES.get(type(data), 'JSON')}"
        )
    for dotted, types in FIELD_TYPES.items():
        present, value = _lookup(data, dotted)
        if present and not _is(value, types):
            names = [_JSON_NAMES[t] for t in types if not (t is int and float in types)]
            want = " or ".join(names)
            raise ManifestError(f"{path}: field {dotted!r} must be {want}, got {value!r:.80}")
    policies = data.get("policies") or []
    bad = [i for i, p in enumerate(policies) if not isinstance(p, dict)]
    if bad:
        raise ManifestError(f"{path}: field 'policies' entry {bad[0]} must be an object")
    missing = [f for f in required if f not in data]
    if missing:
        raise ManifestError(f"{path}: lacks field {missing[0]!r} (a run manifest has {', '.join(required)})")
    return data
