"""Inference latency in control steps: the model behind --inference-latency and --execution.

Every upstream benchmark stops the world while the policy decodes, so decoding speed
never touches success. Here a policy call takes simulated time: its latency (from
counted forward passes, a published device profile, or this machine's wall clock) is
turned into a delay of d = ceil(latency x control frequency) control steps, during which
the robot either holds still (sync) or keeps executing the chunk it has (async, the
naive asynchronous baseline of real-time chunking). Deterministic modes add no sleep:
the delay is steps in the simulator, not seconds on the clock. docs/latency.md is the
reference; harness/episode/plan.py is each episode's timeline under it.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import numpy as np

from harness.errors import UsageError

EXECUTIONS = ("sync", "async")
MODES_HELP = "none, passes:MS[+FIXED_MS], profile:NAME, measured"

# Control frequency (Hz) of the built-in suites, by name prefix; a Suite's own
# `control_hz` (plugins) wins. Sources: LIBERO's bddl_base_domain control_freq=20;
# Meta-World v3 MuJoCo timestep 0.0025 s x frame_skip 5 = 12.5 ms; ManiSkill3
# SimConfig.control_freq = 20 (the tabletop tasks keep the default).
CONTROL_HZ = {"libero/": 20.0, "chains/": 20.0, "metaworld/": 80.0, "simpler/": 20.0}

# The gripper command a hold uses before the episode's first action: open. LIBERO's
# dummy action has -1 (open); Meta-World's scripted experts open with -1; ManiSkill's
# Panda gripper (pd_joint_pos, normalised) maps +1 to its open limit.
GRIPPER_OPEN = {"libero/": -1.0, "chains/": -1.0, "metaworld/": -1.0, "simpler/": 1.0}


@dataclass(frozen=True)
class LatencyMode:
    """A parsed --inference-latency value; `text` is what rows and manifests record."""

    text: str = "none"
    kind: str = "none"  # none | passes | profile | measured
    ms_per_pass: float = 0.0
    fixed_ms: float = 0.0
    profile: str = ""
    chunk_ms: dict[str, float] = field(default_factory=dict)

    @property
    def deterministic(self) -> bool:
        return self.kind != "measured"


def load_profiles() -> dict[str, dict[str, Any]]:
    """The shipped device profiles (harness/defaults/latency_profiles.toml)."""
    text = resources.files("harness").joinpath("defaults/latency_profiles.toml").read_text()
    return tomllib.loads(text)["profiles"]


def _number(text: str, what: str, mode: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise UsageError(f"--inference-latency {mode!r}: {what} must be a number >= 0, got {text!r}")
    return value


def _shown(value: float) -> str:
    """A milliseconds value as the recorded text: the shortest form that reads back as the
    same float (Python's repr), integral values without a fraction (`1000000`, not
    `1e+06`) and exponents without a '+' (which separates FIXED_MS): the text a run
    records is parsed again by every process and resume, so it must mean the same."""
    if value == int(value) and abs(value) < 1e16:
        return str(int(value))
    return repr(value).replace("e+", "e")


def _split_fixed(rest: str) -> tuple[str, str, str]:
    """`MS+FIXED_MS` at its '+', one not part of an exponent (`1e+3+5` is 1e+3 and 5)."""
    for i, c in enumerate(rest):
        if c == "+" and i > 0 and rest[i - 1] not in "eE":
            return rest[:i], "+", rest[i + 1 :]
    return rest, "", ""


def parse_latency(mode: Any) -> LatencyMode:
    """A --inference-latency value checked, or a UsageError naming the valid modes."""
    if not isinstance(mode, str):
        raise UsageError(f"inference_latency must be a string ({MODES_HELP}), got {mode!r}")
    kind, colon, rest = mode.strip().partition(":")
    if kind in ("none", "measured") and not colon:
        return LatencyMode(text=kind, kind=kind)
    if kind == "passes" and colon:
        per_pass, plus, fixed = _split_fixed(rest)
        ms = _number(per_pass, "MS (milliseconds per forward pass)", mode)
        fixed_ms = _number(fixed, "FIXED_MS", mode) if plus else 0.0
        text = f"passes:{_shown(ms)}" + (f"+{_shown(fixed_ms)}" if plus else "")
        return LatencyMode(text=text, kind="passes", ms_per_pass=ms, fixed_ms=fixed_ms)
    if kind == "profile" and colon:
        profiles = load_profiles()
        if rest not in profiles:
            raise UsageError(
                f"--inference-latency {mode!r}: no profile {rest!r}; shipped profiles: "
                f"{', '.join(sorted(profiles))} (see `dvla-harness list latency-profiles`)"
            )
        chunk_ms = {str(k): float(v) for k, v in profiles[rest]["chunk_ms"].items()}
        return LatencyMode(text=f"profile:{rest}", kind="profile", profile=rest, chunk_ms=chunk_ms)
    raise UsageError(f"--inference-latency {mode!r} is not valid; choose one of {MODES_HELP}")


def check_execution(value: Any) -> str:
    if value not in EXECUTIONS:
        raise UsageError(f"execution {value!r} is not valid; choose one of {', '.join(EXECUTIONS)}")
    return str(value)


def _by_prefix(table: dict[str, float], suite: str) -> float | None:
    return next((v for prefix, v in table.items() if suite.startswith(prefix)), None)


def control_hz(suite: Any) -> float:
    """The suite's control frequency; UsageError for a suite that declares none."""
    own = getattr(suite, "control_hz", None)
    hz = own if own else _by_prefix(CONTROL_HZ, suite.name)
    if not hz:
        known = ", ".join(p + "*" for p in CONTROL_HZ)
        raise UsageError(
            f"suite {suite.name!r} declares no control frequency, so an inference latency cannot "
            f"be turned into control steps; suites that do: {known} (a plugin suite sets control_hz)"
        )
    return float(hz)


def delay_steps(latency_s: float, hz: float) -> int:
    """d = ceil(latency / control period); rounded first so 50 ms at 20 Hz is 1, not 2."""
    return max(0, math.ceil(round(latency_s * hz, 9)))


@dataclass(frozen=True)
class LatencyPlan:
    """A run's latency in its suite: the mode, the execution, the clock and the hold."""

    mode: LatencyMode
    execution: str
    hz: float
    gripper_open: float = 0.0

    def delay(self, passes: int, wall_s: float, policy: str) -> int:
        """Control steps one chunk of `policy` (a profile's key) takes to arrive, from its
        call's passes or wall clock."""
        if self.mode.kind == "passes":
            ms = passes * self.mode.ms_per_pass + self.mode.fixed_ms
        elif self.mode.kind == "profile":
            ms = self.mode.chunk_ms[policy]
        elif self.mode.kind == "measured":
            ms = wall_s * 1000.0
        else:
            ms = 0.0
        return delay_steps(ms / 1000.0, self.hz)

    def hold(self, last: np.ndarray | None, action_dim: int) -> np.ndarray:
        """Still: zero for every delta dimension, the last dimension (the gripper) kept
        as last commanded, or open before the episode's first action."""
        action = np.zeros(action_dim)
        action[-1] = self.gripper_open if last is None else last[-1]
        return action


def latency_plan(mode: LatencyMode, execution: str, suite: Any) -> LatencyPlan | None:
    """The plan for a run in `suite`; None at `none` (the world waits for every chunk)."""
    if mode.kind == "none":
        return None
    return LatencyPlan(mode, execution, control_hz(suite), _by_prefix(GRIPPER_OPEN, suite.name) or 0.0)


def check_run(mode: LatencyMode, suite: Any, policies: list[str]) -> None:
    """Refuse (exit 2), before anything runs, what this latency mode cannot model. Any
    --batch-envs may run: each slot keeps its own timeline (harness/episode/plan.py)."""
    if mode.kind == "none":
        return
    control_hz(suite)
    if mode.kind == "profile":
        missing = [p for p in policies if p not in mode.chunk_ms]
        if missing:
            raise UsageError(
                f"--inference-latency {mode.text} has no chunk latency for policy {missing[0]!r}; "
                f"it covers: {', '.join(sorted(mode.chunk_ms))}"
            )


def profile_rows() -> list[tuple[str, str, str]]:
    """(name, chunk latencies, source) per shipped profile, for `list latency-profiles`."""
    rows = []
    for name, profile in sorted(load_profiles().items()):
        chunks = ", ".join(f"{k} {v:g} ms" for k, v in profile["chunk_ms"].items())
        rows.append((name, chunks, str(profile.get("source", ""))))
    return rows
