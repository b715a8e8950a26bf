"""SimplerEnv-like variants as data: axes and levels (simpler_data/variants.toml), which
ones a suite runs, and their names in the episode table.

No simulator import: a suite's variants are parsed, checked and listed without
ManiSkill. Applying a level to a live scene is adapters/simpler.py's job.

`variants=` (a suite option, or `run --variants`) takes `canonical` (ManiSkill3's
canonical scene only), `all` (every level of every axis), `simplerenv` (each task's own
SimplerEnv set, simpler_data/simplerenv_sets.toml), or tokens joined by `+`: an axis
(`lighting`: all its levels) or one level (`lighting.dim`). The canonical scene is always
run too: every variant is judged against it.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from adapters.base import SuiteDataError, UnknownSuiteError

VARIANTS_FILE = Path(__file__).parent / "simpler_data" / "variants.toml"
SETS_FILE = Path(__file__).parent / "simpler_data" / "simplerenv_sets.toml"
CANONICAL = "canonical"
SIMPLERENV = "simplerenv"  # the `variants=` token for each task's own SimplerEnv set
# SimplerEnv's variant aggregation (tools/calc_metrics_evaluation_videos.py): base scene,
# backgrounds, lighting, distractors, table textures; camera is left out ("only when
# investigating the effect of different robustness factors"), and it has no physical axes.
SIMPLERENV_AXES = ("background", "lighting", "distractors", "table")
HARNESS_AXES = ("camera", "friction", "mass")  # the harness's own robustness axes
KINDS = ("visual", "physical")
# What each axis's levels must give, and how many numbers each holds.
PARAMS: dict[str, dict[str, int | None]] = {
    "lighting": {"ambient": 3, "directional": 3},
    "table": {"rgba": 4},
    "camera": {"offset": 3},
    "distractors": {"colors": None},  # one [r, g, b, a] per cube; placed per layout
    "friction": {"scale": 1},
    "mass": {"scale": 1},
    "background": {"rgba": 4},
}


class VariantError(UnknownSuiteError):
    """An unknown axis or level in `variants=`; the message lists the valid ones."""


@dataclass(frozen=True)
class Axis:
    name: str
    kind: str
    what: str
    levels: dict[str, dict[str, Any]]


@dataclass(frozen=True, order=True)
class Variant:
    """One setting of the scene: the canonical one, or one level of one axis."""

    axis: str
    level: str

    @property
    def label(self) -> str:
        """The `variant` column: `canonical` or `<axis>=<level>`."""
        return CANONICAL if self.axis == CANONICAL else f"{self.axis}={self.level}"

    def as_spec(self) -> dict[str, str]:
        return {"axis": self.axis, "level": self.level}


CANONICAL_VARIANT = Variant(CANONICAL, CANONICAL)


def _check_level(axis: str, level: str, values: Any) -> dict[str, Any]:
    where = f"{VARIANTS_FILE.name}: [{axis}] level {level!r}"
    if not isinstance(values, dict) or set(values) != set(PARAMS[axis]):
        raise SuiteDataError(f"{where}: needs exactly {', '.join(PARAMS[axis])}")
    for key, width in PARAMS[axis].items():
        value = values[key]
        if width == 1:
            if not isinstance(value, int | float) or value <= 0:
                raise SuiteDataError(f"{where}: {key} must be a positive number, got {value!r}")
        elif width is not None and (
            len(value) != width or not all(isinstance(v, int | float) for v in value)
        ):
            raise SuiteDataError(f"{where}: {key} must be {width} numbers, got {value!r}")
    if axis == "distractors" and (
        not isinstance(values["colors"], list)
        or not values["colors"]
        or not all(
            isinstance(c, list) and len(c) == 4 and all(isinstance(v, int | float) for v in c)
            for c in values["colors"]
        )
    ):
        raise SuiteDataError(f"{where}: colors must be a list of [r, g, b, a], one per cube")
    return values


@cache
def axes(path: Path = VARIANTS_FILE) -> dict[str, Axis]:
    """The axes in file order, checked: known axis, kind, parameters of the right shape."""
    data = tomllib.loads(path.read_text())
    out = {}
    for name, body in data.items():
        if name not in PARAMS:
            raise SuiteDataError(
                f"{path.name}: unknown axis [{name}]; axes the adapter applies: {', '.join(PARAMS)}"
            )
        if body.get("kind") not in KINDS:
            raise SuiteDataError(f"{path.name}: [{name}] kind must be one of {', '.join(KINDS)}")
        levels = {level: _check_level(name, level, v) for level, v in (body.get("levels") or {}).items()}
        if not levels or CANONICAL in levels:
            raise SuiteDataError(f"{path.name}: [{name}] needs levels, none named {CANONICAL!r}")
        out[name] = Axis(name, body["kind"], body.get("what", ""), levels)
    return out


def all_variants() -> list[Variant]:
    return [Variant(a.name, level) for a in axes().values() for level in a.levels]


def parse(text: str) -> tuple[Variant, ...]:
    """`canonical`, `all`, or `+`-joined axes / `axis.level`s -> the variants to run, the
    canonical first, then in the file's order; each once. `simplerenv` is per task:
    parse_selection."""
    return parse_selection(text).variants


def _level(token: str, text: str) -> list[Variant]:
    """The variants one `axis` or `axis.level` token names; refused when unknown."""
    axis, _, level = token.partition(".")
    if axis not in axes():
        raise VariantError(
            f"unknown variant axis {axis!r} in variants={text}; axes: {', '.join(axes())} "
            f"(or canonical, all, {SIMPLERENV}; a level as axis.level)"
        )
    levels = axes()[axis].levels
    if level and level not in levels:
        raise VariantError(
            f"unknown level {level!r} of axis {axis!r} in variants={text}; its levels: "
            + ", ".join(f"{axis}.{name}" for name in levels)
        )
    return [Variant(axis, name) for name in levels if not level or name == level]


@dataclass(frozen=True)
class Selection:
    """What `variants=` selects: the variants named for every task and, with `simplerenv`,
    each task's own SimplerEnv set besides."""

    variants: tuple[Variant, ...]  # the canonical first, then the file's order
    per_task_sets: bool = False

    def for_task(self, task: str) -> tuple[Variant, ...]:
        """The settings one task runs, the canonical first, then in the file's order."""
        if not self.per_task_sets:
            return self.variants
        wanted = set(self.variants) | set(simplerenv_set(task))
        return (CANONICAL_VARIANT, *(v for v in all_variants() if v in wanted))

    @property
    def name(self) -> str:
        """The canonical option text (what the suite name records): `simplerenv`, then
        what it adds that some task's set lacks."""
        if not self.per_task_sets:
            return name(self.variants)
        if set(self.variants) >= set(all_variants()):
            return "all"
        in_every_set = set.intersection(*(set(simplerenv_set(t)) for t in simplerenv_sets()[1]))
        extra = tuple(v for v in self.variants if v not in in_every_set)
        return "+".join([SIMPLERENV, *([name(extra)] if extra else [])])


CANONICAL_SELECTION = Selection((CANONICAL_VARIANT,))


def parse_selection(text: str) -> Selection:
    every = all_variants()
    wanted: set[Variant] = set()
    per_task = False
    for token in filter(None, (t.strip() for t in text.split("+"))):
        if token == SIMPLERENV:
            per_task = True
        elif token == "all":
            wanted.update(every)
        elif token != CANONICAL:
            wanted.update(_level(token, text))
    if not text.strip():
        raise VariantError(f"variants= is empty; give canonical, all, {SIMPLERENV}, an axis or axis.level")
    return Selection((CANONICAL_VARIANT, *(v for v in every if v in wanted)), per_task)


def name(variants: tuple[Variant, ...]) -> str:
    """The canonical option text for a selection (what the suite name records)."""
    chosen = [v for v in variants if v != CANONICAL_VARIANT]
    if not chosen:
        return CANONICAL
    if set(chosen) == set(all_variants()):
        return "all"
    out = []
    for axis in axes().values():
        mine = [v for v in chosen if v.axis == axis.name]
        if len(mine) == len(axis.levels):
            out.append(axis.name)
        else:
            out += [f"{v.axis}.{v.level}" for v in mine]
    return "+".join(out)


def of_spec(variant: dict[str, Any] | Any) -> Variant | None:
    """The Variant an EpisodeSpec.variant mapping names; None for suites without variants."""
    if not variant:
        return None
    return Variant(str(variant["axis"]), str(variant["level"]))


def label(variant: dict[str, Any] | Any) -> str | None:
    """The `variant` column for an EpisodeSpec.variant: None for suites without variants."""
    v = of_spec(variant)
    return None if v is None else v.label


# --- SimplerEnv's own set per task (simpler_data/simplerenv_sets.toml) -------------------


@dataclass(frozen=True)
class SimplerEnvSet:
    name: str
    simplerenv_task: str  # the SimplerEnv task whose settings it follows
    what: str
    variants: tuple[Variant, ...]  # besides the canonical scene, in the set's order


@cache
def simplerenv_sets(path: Path = SETS_FILE) -> tuple[dict[str, SimplerEnvSet], dict[str, str]]:
    """(set name -> set, ManiSkill3 task -> the set it follows), checked: every level is
    one of the variants file's on SimplerEnv's axes, named once."""
    data = tomllib.loads(path.read_text())
    sets = {}
    for set_name, body in (data.get("sets") or {}).items():
        where = f"{path.name}: [sets.{set_name}]"
        if not isinstance(body, dict) or set(body) != {"simplerenv_task", "what", "variants"}:
            raise SuiteDataError(f"{where}: needs exactly simplerenv_task, what, variants")
        variants = []
        for token in body["variants"]:
            axis, _, level = str(token).partition(".")
            if axis not in SIMPLERENV_AXES or level not in axes().get(axis, Axis("", "", "", {})).levels:
                raise SuiteDataError(
                    f"{where}: {token!r} is not a level of SimplerEnv's axes ({', '.join(SIMPLERENV_AXES)}) "
                    f"in {VARIANTS_FILE.name}"
                )
            variants.append(Variant(axis, level))
        if len(set(variants)) != len(variants):
            raise SuiteDataError(f"{where}: a level is named twice")
        sets[set_name] = SimplerEnvSet(set_name, body["simplerenv_task"], body["what"], tuple(variants))
    tasks = {str(t): str(s) for t, s in (data.get("tasks") or {}).items()}
    unknown = sorted(s for s in tasks.values() if s not in sets)
    if unknown:
        raise SuiteDataError(f"{path.name}: [tasks] names unknown sets {unknown}; sets: {', '.join(sets)}")
    return sets, tasks


def simplerenv_set(task: str) -> tuple[Variant, ...]:
    """The canonical scene and the task's SimplerEnv set, in the set's order."""
    sets, tasks = simplerenv_sets()
    if task not in tasks:
        raise VariantError(
            f"task {task!r} follows no SimplerEnv task in {SETS_FILE.name}, so variants={SIMPLERENV} "
            f"cannot choose its settings; tasks with a set: {', '.join(tasks)}"
        )
    return (CANONICAL_VARIANT, *sets[tasks[task]].variants)
