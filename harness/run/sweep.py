"""Sweeps: the Cartesian product of policy-parameter values, run as one ordinary run.

A sweep adds nothing to the run folder's format: its config's policy list is the grid's
points, so resume, interleaving (every point sees the same machine load), manifests and
rows are the run's, and each row's `policy_params` already records its point. All the
checking happens here and in `resolve`, before anything is written.

A sweep may carry fixed reference configurations (`--reference bidirectional`): run
beside the grid's points, episode by episode, so that a speedup over them is measured
under the same machine load, and never crossed with the grid (they need not have its
parameters). Plots draw them as lines and compute `speedup` against them.

Grid keys are policy parameters. The training-time noise schedule is not one: it is
fixed when a checkpoint is trained and recorded in its header, so an ablation over it
sweeps checkpoints (`--grid checkpoint=a.safetensors,b.safetensors`) and plots group
by the header field (`--hue noise_schedule`); see docs/sweeps-and-plots.md.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence

from harness.config import PolicyChoice, RunConfig
from harness.errors import UsageError
from policies.dvla.recipes import NOISE_SCHEDULES
from policies.registry import PolicyParamError, UnknownPolicyError, get_policy, param_types, parse_params

Grid = dict[str, list[str]]  # parameter -> values as typed, in the order given


def parse_grid(items: Sequence[str]) -> Grid:
    """`KEY=V1,V2,...` flags into a grid; malformed, empty or repeated entries refused."""
    if not items:
        raise UsageError("no --grid given; e.g. --grid block_size=4,8,16 (keys are policy parameters)")
    grid: Grid = {}
    for item in items:
        key, eq, rest = item.partition("=")
        key = key.strip()
        values = [v.strip() for v in rest.split(",") if v.strip()]
        if not eq or not key:
            raise UsageError(f"--grid {item!r}: expected KEY=V1,V2,..., e.g. --grid block_size=4,8,16")
        if not values:
            raise UsageError(f"--grid {item!r}: no values; give at least one, comma-separated")
        if key in grid:
            raise UsageError(f"--grid {key} is given twice; put all its values in one flag")
        repeated = sorted({v for v in values if values.count(v) > 1})
        if repeated:
            raise UsageError(f"--grid {key}: value {repeated[0]!r} is listed twice")
        grid[key] = values
    return grid


def _unknown_key(policy: str, key: str, valid: Sequence[str]) -> str:
    message = (
        f"--grid {key}: policy {policy!r} has no parameter {key!r}; grid keys are its "
        f"parameters: {', '.join(valid)} (to run {policy} unchanged beside the grid, as the "
        f"baseline of its speedups, pass --reference {policy})"
    )
    if key == "noise_schedule":
        unmask = (
            f"{policy}'s inference-time unmasking schedule is `--grid schedule=linear,cosine`"
            if "schedule" in valid
            else "the inference-time unmasking schedule is a parameter of block_diffusion and "
            "bidirectional (`--policy block_diffusion --grid schedule=linear,cosine`)"
        )
        message += (
            ". The noise schedule is fixed when a checkpoint is trained (`dvla-harness train "
            f"--noise-schedule {'|'.join(NOISE_SCHEDULES)}`) and recorded in its header: sweep "
            "checkpoints trained with each, `--grid checkpoint=a.safetensors,b.safetensors`, and "
            f"plot with `--hue noise_schedule`; {unmask}"
        )
    return message


def _check_block_sizes(points: list[dict[str, str]]) -> None:
    """A block size that does not divide the chunk's tokens, caught from the checkpoint's
    header (no torch) with the same message the policy gives when it is built."""
    from policies.dvla.policy import block_size_error, checkpoint_fields

    for point in points:
        fields = checkpoint_fields(str(point["checkpoint"])) if point.get("checkpoint") else {}
        if "block_size" in point and fields.get("action_tokens"):
            error = block_size_error(int(point["block_size"]), fields["action_tokens"], fields["block_size"])
            if error:
                raise UsageError(f"--grid block_size: {error} (checkpoint {point['checkpoint']})")


def add_references(config: RunConfig, references: Sequence[PolicyChoice]) -> RunConfig:
    """`config` with fixed reference configurations first in its policy list: not crossed
    with the grid, interleaved with its points like any of the run's policies."""
    for ref in references:
        try:
            parse_params(get_policy(ref.name), ref.params)
        except (UnknownPolicyError, PolicyParamError) as exc:
            raise UsageError(f"--reference {ref.name}: {exc}") from None
        if ref in config.policies:
            raise UsageError(f"--reference {ref.name}: already a point of the grid; give it once")
    return dataclasses.replace(config, policies=(*references, *config.policies))


def expand(config: RunConfig, grid: Grid) -> RunConfig:
    """`config` with each policy replaced by one configuration per grid point (policy
    order, then the grid's keys in the order given, the last varying fastest)."""
    points: list[PolicyChoice] = []
    for base in config.policies:
        try:
            spec = get_policy(base.name)
        except UnknownPolicyError as exc:
            raise UsageError(str(exc)) from None
        valid = list(param_types(spec.params))
        for key, values in grid.items():
            if key not in valid:
                raise UsageError(_unknown_key(spec.name, key, valid))
            if key in base.params:
                raise UsageError(
                    f"--grid {key} and --policy {base.name}:{key}=... both set {key}; give it in one place"
                )
            for value in values:
                try:
                    parse_params(spec, {**base.params, key: value})
                except PolicyParamError as exc:
                    raise UsageError(f"--grid {key}={value}: {exc}") from None
        combos = [dict(zip(grid, combo, strict=True)) for combo in itertools.product(*grid.values())]
        for combo in combos:
            try:
                typed = parse_params(spec, {**base.params, **combo})
            except PolicyParamError as exc:
                shown = ",".join(f"{k}={v}" for k, v in combo.items())
                raise UsageError(f"--grid point {shown}: {exc}") from None
            if "block_size" in combo:
                _check_block_sizes([{"checkpoint": getattr(typed, "checkpoint", "")} | combo])
            points.append(PolicyChoice(base.name, {**base.params, **combo}))
    return dataclasses.replace(config, policies=tuple(points))
