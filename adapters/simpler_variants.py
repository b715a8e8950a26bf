"""SimplerEnv-like variants as data: axes and levels (simpler_data/variants.toml), which
ones a suite runs, and their names in the episode table.

No simulator import: a suite's variants are parsed, checked and listed without
ManiSkill. Applying a level to a live scene is adapters/simpler.py's job.

`variants=` (a suite option, or `run --variants`) takes `canonical` (ManiSkill3's
canonical scene only), `all` (every level of every axis), or
tokens joined by `+`: an axis (`lighting`: all its levels) or one level
(`lighting.dim`). The canonical scene is always run too: every variant is judged
against it.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from adapters.base import SuiteDataError, UnknownSuiteError

VARIANTS_FILE = Path(__file__).parent / "simpler_data" / "variants.toml"
CANONICAL = "canonical"
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
    canonical first, then in the file's order; each once."""
    every = all_variants()
    wanted: set[Variant] = set()
    for token in filter(None, (t.strip() for t in text.split("+"))):
        if token == CANONICAL:
            continue
        if token == "all":
            wanted.update(every)
            continue
        axis, _, level = token.partition(".")
        if axis not in axes():
            raise VariantError(
                f"unknown variant axis {axis!r} in variants={text}; axes: {', '.join(axes())} "
                "(or canonical, all; a level as axis.level)"
            )
        levels = axes()[axis].levels
        if level and level not in levels:
            raise VariantError(
                f"unknown level {level!r} of axis {axis!r} in variants={text}; its levels: "
                + ", ".join(f"{axis}.{name}" for name in levels)
            )
        wanted.update(Variant(axis, name) for name in levels if not level or name == level)
    if not text.strip():
        raise VariantError("variants= is empty; give canonical, all, an axis or axis.level")
    return (CANONICAL_VARIANT, *(v for v in every if v in wanted))


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
