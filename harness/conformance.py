"""Conformance checks for suites and policies, in the spirit of Gymnasium's `check_env`:
the contract of adapters/base.py and policies/base.py as rules a plugin author can run.

Each rule returns a `Finding` (its name, whether it held, and what was seen), so the
command prints one line per rule and exits 1 if any failed; nothing is written. The
checks use the real env and policy, a few steps of each, so they are cheap enough to run
while writing a plugin.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
import numpy as np

from adapters.base import Suite, TaskSpec
from harness.episode.actions import box_bounds, describe
from harness.episode.context import episode_context

# `check policy` asks for this many chunks in each of this many episodes.
EPISODES, CHUNKS = 2, 4


@dataclass(frozen=True)
class Finding:
    rule: str
    ok: bool
    detail: str = ""


def _rule(rule: str, check: Callable[[], str | None]) -> Finding:
    """Run one check: None or a text means it held (the text says what was seen); an
    AssertionError or any exception means it failed, with its message."""
    try:
        seen = check()
    except AssertionError as exc:
        return Finding(rule, False, str(exc))
    except Exception as exc:
        return Finding(rule, False, f"{type(exc).__name__}: {exc}")
    return Finding(rule, True, seen or "")


def _inside(space: gym.Space, obs: Any) -> bool:
    """Shape and bounds, not dtype: a float64 observation of a float32 Box is what many
    envs return and what the runner takes (Gymnasium's check_env only warns on it)."""
    if isinstance(space, gym.spaces.Dict):
        return isinstance(obs, dict) and all(k in obs and _inside(s, obs[k]) for k, s in space.spaces.items())
    if isinstance(space, gym.spaces.Box):
        x = np.asarray(obs)
        return x.shape == space.shape and bool(
            np.all(x >= space.low - 1e-6) and np.all(x <= space.high + 1e-6)
        )
    return space.contains(obs)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return np.array_equal(np.asarray(a), np.asarray(b))


def check_suite(suite: Suite, steps: int = 5) -> Iterator[Finding]:
    """The suite as data, then each task's env: reset/step contract, success on every
    step, a spec reproducing its first observation."""
    yield _rule(
        "the suite has tasks", lambda: f"{len(suite.tasks)} task(s)" if suite.tasks else _fail("no tasks")
    )
    for task in suite.tasks:
        yield from _check_task(suite, task, steps)


def _fail(text: str) -> None:
    raise AssertionError(text)


def _check_task(suite: Suite, task: TaskSpec, steps: int) -> Iterator[Finding]:
    name = f"{task.name}:"
    indices = [s.index for s in task.episodes]
    yield _rule(
        f"{name} episodes are fixed and distinct",
        lambda: (
            f"{len(indices)} episodes"
            if indices and len(set(indices)) == len(indices)
            else _fail(f"episode indices {indices[:10]} (empty or repeated)")
        ),
    )
    yield _rule(
        f"{name} a step budget and an instruction",
        lambda: (
            None
            if task.max_steps > 0 and task.instruction.strip()
            else _fail("max_steps <= 0 or no instruction")
        ),
    )
    env: gym.Env | None = None
    try:
        env = suite.make_env(task)
    except Exception as exc:
        yield Finding(f"{name} make_env builds the env", False, f"{type(exc).__name__}: {exc}")
        return
    try:
        yield _rule(
            f"{name} spaces are Gymnasium spaces",
            lambda: (
                None
                if isinstance(env.observation_space, gym.Space) and isinstance(env.action_space, gym.Space)
                else _fail("observation_space or action_space is not a gymnasium.Space")
            ),
        )
        if not task.episodes:
            return
        spec = task.episodes[0]
        first: dict[str, Any] = {}

        def reset() -> str:
            obs, info = env.reset(seed=spec.seed, options={"episode": spec})
            assert isinstance(info, dict) and isinstance(info.get("success"), bool), (
                f"reset's info must hold a bool 'success', got {info!r}"[:300]
            )
            assert _inside(env.observation_space, obs), "reset's observation is outside observation_space"
            first["obs"] = obs
            return ""

        yield _rule(f"{name} reset(options={{'episode': spec}}) returns (obs, info)", reset)
        if "obs" not in first:
            return

        def step() -> str:
            rng = np.random.default_rng(0)
            space = env.action_space
            for i in range(steps):
                action = rng.uniform(space.low, space.high).astype(space.dtype)
                result = env.step(action)
                assert len(result) == 5, f"step returned {len(result)} values, Gymnasium's contract is 5"
                obs, _, terminated, truncated, info = result
                assert isinstance(info.get("success"), bool), f"step {i}: info['success'] must be a bool"
                assert _inside(env.observation_space, obs), f"step {i}: observation outside observation_space"
                if terminated or truncated or info["success"]:
                    break
            return f"{i + 1} step(s)"

        yield _rule(f"{name} step returns 5 values and info['success'] every step", step)

        def reproduces() -> str:
            again, _ = env.reset(seed=spec.seed, options={"episode": spec})
            assert _same(again, first["obs"]), "the same episode spec gave another first observation"
            return ""

        yield _rule(f"{name} a spec reproduces its first observation", reproduces)
    finally:
        env.close()


def _checked_chunk(batch: Any, space: gym.Space, first_step: int, where: str) -> np.ndarray:
    """The chunk of one `act` result (chunk x dim) after the contract's checks, each
    failure naming `where` (episode, chunk, env step) and the first offending action."""
    actions = np.asarray(batch.actions)
    dim = int(np.prod(space.shape))
    assert actions.ndim == 3 and actions.shape[0] == 1 and actions.shape[2] == dim, (
        f"{where}: actions of shape {actions.shape}; the contract is (batch 1, chunk, {dim})"
    )
    assert actions.shape[1] >= 1, f"{where}: an empty chunk"
    assert np.issubdtype(actions.dtype, np.floating) and np.isfinite(actions).all(), (
        f"{where}: actions must be finite floats"
    )
    bounds = box_bounds(space)
    outside = describe(actions[0], *bounds, first_step) if bounds is not None else None
    assert outside is None, f"{where}: {outside}"
    assert isinstance(batch.action_tokens, int | np.integer) and batch.action_tokens >= 0, (
        f"{where}: action_tokens must be an int >= 0, got {batch.action_tokens!r}"
    )
    return actions[0]


def check_policy(
    spec: Any, raw_params: dict[str, Any], suite: Suite, chunks: int = CHUNKS
) -> Iterator[Finding]:
    """Parameters round-trip through their JSON form; the built policy accepts the suite
    (check_spaces), and reset/act return chunks of the right shape inside the action space
    over `chunks` calls of each of two episodes, the env stepped through every chunk."""
    from policies.registry import access_params, params_json, parse_params

    state: dict[str, Any] = {}

    def round_trip() -> str:
        params = parse_params(spec, raw_params)
        text = params_json(params)
        # what the JSON leaves out (where a key is read from) comes from the config, not it
        again = replace(parse_params(spec, json.loads(text)), **access_params(params))
        assert again == params, f"{text} parses back as {again!r}, not {params!r}"
        state["params"] = params
        return text

    yield _rule("parameters round-trip through JSON", round_trip)
    if "params" not in state:
        return

    def build() -> str:
        state["policy"] = spec.build(state["params"])
        return type(state["policy"]).__name__

    yield _rule("build(params) makes the policy", build)
    if "policy" not in state:
        return
    policy = state["policy"]
    task = suite.tasks[0]
    env = suite.make_env(task)
    try:
        check = getattr(policy, "check_spaces", None)
        if callable(check):
            yield _rule(
                "check_spaces accepts the suite", lambda: check(env.observation_space, env.action_space)
            )
        # Two episodes (the first task's first two specs; its only spec twice), several
        # chunks each, the env stepped through each chunk: a policy that keeps state between
        # calls or episodes breaks the contract on a later call as easily as on the first.
        specs = (list(task.episodes) * EPISODES)[:EPISODES]

        def act() -> str:
            calls = steps_total = 0
            for e, episode in enumerate(specs):
                obs, _ = env.reset(seed=episode.seed, options={"episode": episode})
                policy.reset([episode_context(suite.name, task, episode, env)])
                steps = 0
                for c in range(chunks):
                    where = f"episode {e} (spec {episode.index} of {task.name}), chunk {c} (env step {steps})"
                    actions = _checked_chunk(policy.act([obs]), env.action_space, steps, where)
                    calls += 1
                    done = False
                    for action in actions:
                        obs, _, terminated, truncated, info = env.step(action)
                        steps += 1
                        done = bool(terminated or truncated or info.get("success")) or steps >= task.max_steps
                        if done:
                            break
                    if done:
                        break
                steps_total += steps
            return f"{calls} chunk(s) over {len(specs)} episodes, {steps_total} env step(s)"

        yield _rule(
            f"reset + act return chunks inside the action space ({EPISODES} episodes x {chunks} chunks)", act
        )
    finally:
        env.close()
