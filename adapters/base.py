"""The suite contract: what every simulator adapter gives the runner.

A suite is data: a named, versioned tuple of tasks, each with its instruction, step
budget and a fixed list of episode specs. Only `make_env` touches a simulator, so the
suite can be listed, validated and planned without the simulator installed.

The environment contract is Gymnasium's (`reset`/`step`) plus two conventions:
- `reset(seed=spec.seed, options={"episode": spec})` puts the env in that episode's
  initial condition (layout, fixed initial state, visual variant). Protocol steps that
  do not count (e.g. LIBERO's no-op settle steps) happen inside `reset`.
- `info["success"]` is a bool on every step. Chains of instructions (CALVIN-like,
  adapters/chains.py) also report, from `reset` on, the instruction in force in
  `info["instruction"]` and its position `info["subtask_index"]`, and
  `info["subtasks_completed"]` and `info["subtasks"]` (one record per planned subtask);
  the runner gives a changed instruction to the policy (policies/base.py).

An env may also say where world-frame 3-D positions sit in its state vector:
`state_positions`, a tuple of start indices, the end effector's first. `collect` records
it, and `train --state-features relative` gives the model each position's offset from
the end effector (policies/observations.py). An env may also say how many leading entries
of its state are the robot's own (`proprio_dim`: hand pose, gripper, joints); `train
--state-features proprio` then reads only those, so a camera policy cannot lean on the
privileged object poses the scripted experts need.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym


@dataclass(frozen=True)
class EpisodeSpec:
    """One reproducible episode of a task: the same spec gives the same start."""

    index: int
    seed: int | None = None
    init_state_id: int | None = None
    # Visual/physical variant (SimplerEnv-like): e.g. {"lighting": "dim"}.
    variant: Mapping[str, Any] = field(default_factory=dict, hash=False)
    # The subtask ids of an instruction chain (CALVIN-like), in order; empty otherwise.
    chain: tuple[str, ...] = ()


@dataclass(frozen=True)
class TaskSpec:
    """A task of a suite. For chain suites a task is a scene, its episodes are chains and
    `instruction` only describes them: each episode's instructions come from its env."""

    name: str
    instruction: str
    max_steps: int
    episodes: tuple[EpisodeSpec, ...]
    index: int = 0


@dataclass(frozen=True)
class Suite:
    """A named, versioned list of tasks and how to build an environment for one."""

    name: str
    version: str
    tasks: tuple[TaskSpec, ...]
    make_env: Callable[[TaskSpec], gym.Env]
    description: str = ""
    # The pip extra that provides the simulator, e.g. "metaworld".
    extra: str = ""
    # Which simulator packages matter for provenance (recorded in the manifest).
    simulator_packages: tuple[str, ...] = ()
    # How observations are rendered: "none (state)" or e.g. "egl"; recorded per run.
    render_backend: str = "none (state observations)"
    # Anything else that can move scores and belongs in the manifest beside the versions,
    # e.g. the Vulkan driver SAPIEN renders and builds its scene with.
    provenance: Mapping[str, str] = field(default_factory=dict)
    # Control steps per second, which turns an inference latency into steps
    # (docs/latency.md); None: the built-in table in harness/episode/latency.py, by suite name.
    control_hz: float | None = None

    def task(self, name_or_index: str) -> TaskSpec:
        """Look a task up by name or by its position in the suite."""
        for task in self.tasks:
            if task.name == name_or_index:
                return task
        if name_or_index.isdigit() and int(name_or_index) < len(self.tasks):
            return self.tasks[int(name_or_index)]
        raise KeyError(name_or_index)


@dataclass(frozen=True)
class SuiteInfo:
    """What `list suites` shows; cheap to build, no simulator import."""

    name: str
    description: str
    num_tasks: int
    episodes_per_task: int
    extra: str
    installed: bool
    # The distribution the extra belongs to: this harness, or the plugin that lists the suite
    # (set by adapters.registry.list_suites), so `list suites` says what to pip install.
    package: str = "dvla-harness"


# What a provider raises on bad input (the CLI prints the message, exit 2), beside the
# contract: below every adapter and the registry, so each imports them from here.
class UnknownSuiteError(LookupError):
    """The name matches no suite; the message lists the valid ones."""


class SuiteOptionError(UnknownSuiteError):
    """A `:key=value` suite option is unknown or out of range; the message says which."""


def refuse_repeated_options(text: str) -> None:
    """Refuse a suite option given twice (`perturb=swap,perturb=lan`): a parser keeping the
    last value would run another suite than the one written first, and pass a value the
    rules for combining options never saw (LIBERO-PRO's `task`, which combines with nothing)."""
    seen: set[str] = set()
    for item in filter(None, (s.strip() for s in text.split(","))):
        key = item.partition("=")[0].strip()
        if key in seen:
            raise SuiteOptionError(
                f"suite option {key!r} is given twice in {text!r}; give each option once "
                "(several LIBERO-PRO perturbations are one option: perturb=swap+lan)"
                if key == "perturb"
                else f"suite option {key!r} is given twice in {text!r}; give each option once"
            )
        seen.add(key)


class SuiteDataError(ValueError):
    """A suite's own definition files are wrong (e.g. a chain file naming an unknown
    subtask); the message names the file, the entry and the fix."""


class MissingExtraError(RuntimeError):
    """The suite's simulator is not installed; the message names the pip extra."""


@dataclass(frozen=True)
class SuiteProvider:
    prefix: str
    list_suites: Callable[[], list[SuiteInfo]]
    # load_suite(name, split): "eval" is the protocol's episodes; "train" gives episodes
    # disjoint from them where the suite can (for demonstrations), else the same ones.
    load_suite: Callable[[str, str], Suite]


def derive_seed(*parts: object) -> int:
    """A stable 31-bit seed from a tuple of names and numbers.

    Python's `hash` is salted per process, so it cannot make seeds that two runs share.
    """
    text = "/".join(str(p) for p in parts)
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "big") >> 1
