"""CALVIN-like chain scenes as data: subtasks, the precondition model, the fixed chains.

A scene file (`adapters/chain_data/<scene>.toml`) names a LIBERO task whose BDDL
builds the scene and whose 50 initial states start the chains, and lists subtasks: an
instruction, a goal, preconditions and what stops holding once the goal holds, all in
LIBERO's BDDL predicates (`["In", "butter_1", "wooden_tray_1_contain_region"]`). The
simulator checks goals with LIBERO's own predicate code (adapters/chains.py); this module
only reasons about them symbolically, to sample chains the way CALVIN samples its
evaluation sequences: a subtask is eligible when its preconditions hold and its goal does
not, in the state the chain has reached.

The chains (`<scene>.chains.json`) are sampled once and stored, like CALVIN's
evaluation sequences, so every run and every paper reproducer sees the same ones:

    python -m adapters.chain_scenes generate living_room_scene3 --chains 200 --seed 0

The generator records each chain file's sha256 in `chain_data/chains.sha256` (sha256sum's
format), and loading a chain file refuses one whose bytes no longer match: an edited or
damaged file would otherwise change the protocol while the suite keeps its name and version.

This module imports neither LIBERO nor a simulator: listing and validating chains is cheap.
Only `scene_problem` reads a scene's BDDL, through LIBERO's parser (adapters/libero_sim.py).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import sys
import tomllib
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from adapters import libero_sim
from adapters.base import SuiteDataError

DATA = Path(__file__).resolve().parent / "chain_data"
# CALVIN's protocol (calvin_models/calvin_agent/evaluation/evaluate_policy.py):
# NUM_SEQUENCES chains of 5 subtasks, EP_LEN = 360 steps for each, a chain stops at
# its first failure, no reset between subtasks. shared/notes/dvla-reference.md section 3.
SUBTASKS_PER_CHAIN = 5
STEPS_PER_SUBTASK = 360
# CALVIN evaluates NUM_SEQUENCES = 1000 chains: 200 stored per scene over the five scenes
# `chains/all` runs (CALVIN_SCENES); a scene added later is a suite of its own, so that
# `chains/all` keeps CALVIN's count and the rows and tables made with it keep their meaning.
CHAINS_PER_SCENE = 200
CALVIN_SCENES = ("kitchen_scene1", "kitchen_scene3", "kitchen_scene8", "libero_goal", "living_room_scene3")
# LIBERO's initial-state files hold 50 states per task: chain j starts from state j % 50,
# so the first 50 chains (the documented smoke prefix) start from 50 different states.
INITIAL_STATES = 50
# LIBERO's predicates (libero/libero/envs/predicates/__init__.py VALIDATE_PREDICATE_FN_DICT),
# with their arity; "printjointstate" and "true"/"false" are not goals.
PREDICATES = {"in": 2, "on": 2, "up": 1, "open": 1, "close": 1, "turnon": 1, "turnoff": 1}

# Where a subtask comes from: a LIBERO task's goal and instruction verbatim, or written here.
SOURCES = ("libero_90", "libero_goal", "authored")
LIBERO_SUITES = ("spatial", "object", "goal", "10", "90")  # adapters/libero.py MAX_STEPS keys
Predicate = tuple[str, ...]  # ("in", "butter_1", "wooden_tray_1_contain_region"), lower-case name


class ChainDataError(SuiteDataError):
    """A scene or chain file is wrong; the message names the file, the entry and the fix."""


@dataclass(frozen=True)
class Subtask:
    id: str
    instruction: str
    goal: tuple[Predicate, ...]
    pre: tuple[Predicate, ...]
    unless: tuple[Predicate, ...]  # eligible only while none of these holds
    removes: tuple[Predicate, ...]
    source: str  # one of SOURCES
    # The goal counts only while none of these holds: a take-out's object is on its
    # starting region and no longer in the tray, so carrying the tray there with the
    # object still in it is not a take-out (LIBERO's On and In can hold together).
    goal_not: tuple[Predicate, ...] = ()


@dataclass(frozen=True)
class Scene:
    name: str
    libero_suite: str  # the LIBERO suite key holding that task ("90", "goal", ...)
    libero_task: str  # the LIBERO task whose BDDL builds the scene and whose init states start chains
    subtasks: tuple[Subtask, ...]

    def subtask(self, subtask_id: str) -> Subtask:
        for s in self.subtasks:
            if s.id == subtask_id:
                return s
        raise ChainDataError(
            f"scene {self.name!r} has no subtask {subtask_id!r}; its subtasks: "
            + ", ".join(s.id for s in self.subtasks)
        )

    def predicates(self) -> set[Predicate]:
        """Every predicate a subtask names (what the simulator must be able to evaluate)."""
        return {p for s in self.subtasks for p in (*s.goal, *s.goal_not, *s.pre, *s.unless, *s.removes)}


@dataclass(frozen=True)
class ChainSet:
    scene: str
    seed: int | None  # the sampler's; None in a user's file that does not say
    command: str | None  # what made the file; likewise
    chains: tuple[tuple[str, ...], ...]
    sha256: str  # of the file's bytes (the run manifest carries it); a stored file's as recorded in HASHES


def scene_names() -> list[str]:
    return sorted(p.stem for p in DATA.glob("*.toml"))


def _predicate(raw: object, where: str) -> Predicate:
    if not isinstance(raw, list) or not raw or not all(isinstance(x, str) for x in raw):
        raise ChainDataError(
            f"{where}: a predicate is a list of strings like ['In', 'obj_1', 'region']; got {raw!r}"
        )
    name = raw[0].lower()
    if name not in PREDICATES:
        raise ChainDataError(
            f"{where}: unknown predicate {raw[0]!r}; LIBERO's goal predicates: "
            + ", ".join(sorted(PREDICATES))
        )
    if len(raw) - 1 != PREDICATES[name]:
        raise ChainDataError(f"{where}: {raw[0]} takes {PREDICATES[name]} argument(s), got {len(raw) - 1}")
    return (name, *raw[1:])


def _predicates(entry: dict, key: str, where: str, required: bool = False) -> tuple[Predicate, ...]:
    raw = entry.get(key, [])
    if required and not raw:
        raise ChainDataError(f"{where}: `{key}` is required and must name at least one predicate")
    if not isinstance(raw, list):
        raise ChainDataError(f"{where}: `{key}` must be a list of predicates")
    return tuple(_predicate(p, f"{where} {key}") for p in raw)


@cache
def load_scene(name: str) -> Scene:
    path = DATA / f"{name}.toml"
    if not path.is_file():
        raise ChainDataError(f"unknown chain scene {name!r}; scenes: {', '.join(scene_names()) or '(none)'}")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ChainDataError(f"{path}: not valid TOML ({exc})") from None
    for key in ("scene", "libero_task", "subtask"):
        if key not in data:
            raise ChainDataError(f"{path}: missing `{key}`")
    if data["scene"] != name:
        raise ChainDataError(f"{path}: `scene = {data['scene']!r}` must match the file name {name!r}")
    subtasks = []
    for i, entry in enumerate(data["subtask"]):
        where = f"{path.name} subtask {i} ({entry.get('id', '?')})"
        for key in ("id", "instruction", "source"):
            if not isinstance(entry.get(key), str) or not entry[key]:
                raise ChainDataError(f"{where}: `{key}` must be a non-empty string")
        if entry["source"] not in SOURCES:
            raise ChainDataError(f"{where}: `source` is one of {', '.join(SOURCES)}, not {entry['source']!r}")
        subtasks.append(
            Subtask(
                id=entry["id"],
                instruction=entry["instruction"],
                goal=_predicates(entry, "goal", where, required=True),
                pre=_predicates(entry, "pre", where),
                unless=_predicates(entry, "unless", where),
                removes=_predicates(entry, "removes", where),
                source=entry["source"],
                goal_not=_predicates(entry, "goal_not", where),
            )
        )
    for field in ("id", "instruction"):  # a policy tells subtasks apart by instruction alone
        values = [getattr(s, field) for s in subtasks]
        if len(set(values)) != len(values):
            repeated = sorted({v for v in values if values.count(v) > 1})
            raise ChainDataError(f"{path}: subtask {field}s repeat: {repeated}")
    suite = data.get("libero_suite", "90")
    if suite not in LIBERO_SUITES:
        raise ChainDataError(f"{path}: `libero_suite` is one of {', '.join(LIBERO_SUITES)}, not {suite!r}")
    return Scene(name=name, libero_suite=suite, libero_task=data["libero_task"], subtasks=tuple(subtasks))


def goal_met(subtask: Subtask, state: frozenset[Predicate]) -> bool:
    """Whether the subtask's goal holds in a symbolic state: its `goal` all there, none of
    its `goal_not` (adapters/chain_credit.goal_holds reads the live state the same way)."""
    return set(subtask.goal) <= state and not set(subtask.goal_not) & state


def eligible(scene: Scene, state: frozenset[Predicate]) -> list[Subtask]:
    """Subtasks whose preconditions hold in `state`, none of whose `unless` does, and
    whose goal does not yet."""
    return [
        s
        for s in scene.subtasks
        if set(s.pre) <= state and not set(s.unless) & state and not goal_met(s, state)
    ]


def apply(subtask: Subtask, state: frozenset[Predicate]) -> frozenset[Predicate]:
    """The symbolic state once `subtask`'s goal holds (its `goal_not` then does not)."""
    return frozenset((state - set(subtask.removes) - set(subtask.goal_not)) | set(subtask.goal))


def check_chain(
    scene: Scene, chain: tuple[str, ...], start: frozenset[Predicate], where: str, fix: str | None = None
) -> None:
    """Refuse a chain of the wrong length, with unknown subtasks or a subtask that is not
    eligible where the chain reaches it; `fix` says what to do (a stored file: regenerate it)."""
    fix = (
        fix
        or f"regenerate the chains (python -m adapters.chain_scenes generate {scene.name}) or fix the scene file"
    )
    if len(chain) != SUBTASKS_PER_CHAIN:
        raise ChainDataError(f"{where}: {len(chain)} subtasks; a chain has {SUBTASKS_PER_CHAIN}")
    state = start
    for k, subtask_id in enumerate(chain):
        subtask = scene.subtask(subtask_id)
        if subtask not in eligible(scene, state):
            missing = sorted(set(subtask.pre) - state)
            blocking = sorted(set(subtask.unless) & state)
            why = (
                f"preconditions {missing} do not hold"
                if missing
                else f"{blocking} hold (its `unless`)"
                if blocking
                else "its goal already holds"
            )
            raise ChainDataError(f"{where}: subtask {k} ({subtask_id}) is not eligible there: {why}; {fix}")
        state = apply(subtask, state)


def check_distinct(
    chains: tuple[tuple[str, ...], ...], starts: int, where: str, fix: str | None = None
) -> None:
    """Refuse two chains that would be one episode: the same subtasks from the same initial
    state (chain j starts from state j % `starts`), which would count one measurement
    twice. The same subtasks from another initial state are another episode: the sampler
    draws every chain independently, and the shipped files repeat a few that way."""
    seen: dict[tuple[tuple[str, ...], int], int] = {}
    for j, chain in enumerate(chains):
        key = (chain, j % starts)
        if key in seen:
            raise ChainDataError(
                f"{where}: chain {j} repeats chain {seen[key]} from the same initial state "
                f"({j % starts}), so one episode would count twice; "
                + (
                    fix
                    or "remove it, or regenerate the chains (python -m adapters.chain_scenes generate SCENE)"
                )
            )
        seen[key] = j


def _completable(scene: Scene, state: frozenset[Predicate], remaining: int, memo: dict) -> bool:
    """Whether some chain of `remaining` more subtasks can follow `state`."""
    if remaining == 0:
        return True
    key = (state, remaining)
    if key not in memo:
        memo[key] = any(
            _completable(scene, apply(s, state), remaining - 1, memo) for s in eligible(scene, state)
        )
    return memo[key]


def sample_chains(
    scene: Scene, start: frozenset[Predicate], n: int, seed: int, starts: int | None = None
) -> list[tuple[str, ...]]:
    """`n` chains, each subtask drawn uniformly among the eligible ones from which a chain
    of 5 can still be completed (CALVIN's sampler draws from the tasks whose
    preconditions hold in the reached state; a dead end is never entered).

    With `starts` (chain j starts from initial state j % starts), a chain that repeats one
    already drawn for the same initial state is drawn again, so no episode counts twice
    (`check_distinct`). The first `starts` chains are never redrawn, so a longer file with
    the same seed begins with the chains of a shorter one."""
    rng = random.Random(seed)
    memo: dict = {}
    if not _completable(scene, start, SUBTASKS_PER_CHAIN, memo):
        raise ChainDataError(
            f"scene {scene.name!r}: no chain of {SUBTASKS_PER_CHAIN} subtasks is possible from the "
            "scene's start; add subtasks (or complements that undo others) to the scene file"
        )
    chains: list[tuple[str, ...]] = []
    taken: set[tuple[tuple[str, ...], int]] = set()
    for j in range(n):
        for _ in range(MAX_REDRAWS):
            chain = _draw(scene, start, rng, memo)
            key = (chain, j % starts if starts else j)
            if key not in taken:
                break
        else:
            raise ChainDataError(
                f"scene {scene.name!r}: no chain for initial state {j % (starts or n)} that another "
                f"chain from it does not repeat after {MAX_REDRAWS} draws; ask for fewer chains"
            )
        taken.add(key)
        chains.append(chain)
    return chains


MAX_REDRAWS = 1000  # draws for one chain before the scene is judged too small for the count


def _draw(scene: Scene, start: frozenset[Predicate], rng: random.Random, memo: dict) -> tuple[str, ...]:
    state, chain = start, []
    for k in range(SUBTASKS_PER_CHAIN):
        left = SUBTASKS_PER_CHAIN - k - 1
        options = [s for s in eligible(scene, state) if _completable(scene, apply(s, state), left, memo)]
        subtask = rng.choice(options)
        chain.append(subtask.id)
        state = apply(subtask, state)
    return tuple(chain)


def chains_path(name: str) -> Path:
    return DATA / f"{name}.chains.json"


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose keys are distinct (json keeps the last of a repeated key, so a
    second "chains" would silently replace the first)."""
    keys = [k for k, _ in pairs]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ValueError(f"key {repeated[0]!r} appears twice")
    return dict(pairs)


@cache
def load_chains(name: str) -> ChainSet:
    path = chains_path(name)
    if not path.is_file():
        raise ChainDataError(
            f"{path}: no chains for scene {name!r}; make them with "
            f"python -m adapters.chain_scenes generate {name}"
        )
    raw = path.read_bytes()  # hashed and parsed from one read: what is checked is what runs
    return _parse_chains(raw, path, check_chains_hash(name, raw), stored=True)


def load_user_chains(path: Path, scene: str) -> ChainSet:
    """A researcher's own chain file (`chains/<scene>:chains=PATH`), in the stored files'
    format ("seed" and "command" optional). The suite checks its chains as it checks the
    stored ones; its sha256 is its own bytes', which the run's manifest records (HASHES
    locks the stored files only)."""
    if not path.is_file():
        raise ChainDataError(
            f"chains={path}: no such file (a JSON chain file; docs/chains.md, 'Your own chains')"
        )
    raw = path.read_bytes()
    chains = _parse_chains(raw, path, hashlib.sha256(raw).hexdigest(), stored=False)
    if chains.scene != scene:
        raise ChainDataError(
            f"{path}: its chains are for scene {chains.scene!r}, not {scene!r}; run them as "
            f"chains/{chains.scene}:chains={path}"
        )
    return chains


CHAIN_FILE_KEYS = ("scene", "chains", "seed", "command")


def _parse_chains(raw: bytes, path: Path, sha256: str, stored: bool) -> ChainSet:
    """The chain file's fields, each checked by name, so a wrong file is refused with
    what is wrong in it and what a chain file holds (docs/chains.md, "Your own chains")."""
    layout = (
        '{"scene": "<scene>", "chains": [["<subtask id>", ... 5 ids], ...]} '
        '(optional: "seed" an integer, "command" a string)'
    )

    def refuse(problem: str) -> ChainDataError:
        return ChainDataError(f"{path}: not a chain file: {problem}; a chain file is {layout}")

    try:
        data = json.loads(raw.decode(), object_pairs_hook=_unique_keys)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise refuse(f"not valid JSON ({exc})") from None
    except ValueError as exc:  # a repeated key (_unique_keys)
        raise refuse(str(exc)) from None
    if not isinstance(data, dict):
        raise refuse(f"the top level is a JSON {type(data).__name__}, not an object")
    unknown = sorted(set(data) - set(CHAIN_FILE_KEYS))
    if unknown:
        raise refuse(f"unknown keys {unknown}")
    required = ("scene", "chains", "seed", "command") if stored else ("scene", "chains")
    missing = [k for k in required if k not in data]
    if missing:
        raise refuse(f"missing {', '.join(repr(k) for k in missing)}")
    if not isinstance(data["scene"], str) or not data["scene"]:
        raise refuse(f'"scene" must be a scene name (a string), not {data["scene"]!r}')
    chains = data["chains"]
    if not isinstance(chains, list) or not chains:
        raise refuse('"chains" must be a non-empty list of chains')
    for j, chain in enumerate(chains):
        if not isinstance(chain, list) or not all(isinstance(s, str) for s in chain):
            raise refuse(f"chain {j} is not a list of subtask ids")
    seed, command = data.get("seed"), data.get("command")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise refuse(f'"seed" must be an integer or null, not {seed!r}')
    if command is not None and not isinstance(command, str):
        raise refuse(f'"command" must be a string or null, not {command!r}')
    return ChainSet(
        scene=data["scene"], seed=seed, command=command, chains=tuple(tuple(c) for c in chains), sha256=sha256
    )


# The recorded sha256 of every chain file, one line each in sha256sum's format
# ("<64 hex>  <scene>.chains.json"), so `sha256sum -c chains.sha256` in the folder checks
# them without the harness. Written by the generator only, never by hand.
HASHES = "chains.sha256"
_HASH_LINE = re.compile(r"([0-9a-f]{64})  (\S+\.chains\.json)")


def recorded_hashes() -> dict[str, str]:
    """Chain file name -> its recorded sha256 (hex)."""
    path = DATA / HASHES
    if not path.is_file():
        return {}
    hashes: dict[str, str] = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        match = _HASH_LINE.fullmatch(line)
        if match is None or match[2] in hashes:
            raise ChainDataError(
                f"{path} line {i}: expected one '<sha256 hex>  <scene>.chains.json' per chain file, "
                f"got {line!r}; restore the file from git (git checkout -- adapters/chain_data/{HASHES})"
            )
        hashes[match[2]] = match[1]
    return hashes


def check_chains_hash(name: str, raw: bytes) -> str:
    """The sha256 of a chain file's bytes, refused unless it is the recorded one: the
    chains are the protocol, so a changed file is a different suite, not a quiet edit."""
    path = chains_path(name)
    actual = hashlib.sha256(raw).hexdigest()
    expected = recorded_hashes().get(path.name)
    regenerate = f"python -m adapters.chain_scenes generate {name}"
    if expected is None:
        raise ChainDataError(
            f"{path}: no sha256 recorded for it in {DATA / HASHES}; the generator records it "
            f"({regenerate}), so regenerate the chains rather than edit the list"
        )
    if actual != expected:
        raise ChainDataError(
            f"{path}: sha256 {actual} is not the {expected} recorded in {DATA / HASHES}, so these "
            f"are not the suite's fixed chains; restore the file (git checkout -- "
            f"adapters/chain_data/{path.name}), or, for a deliberate change, regenerate it "
            f"({regenerate}), which records the new hash, and bump SUITE_VERSION in adapters/chains.py"
        )
    return actual


def record_chains_hash(name: str) -> str:
    """Record the chain file's current sha256 (the generator's last step), keeping the
    other scenes' lines; written whole or not at all."""
    actual = hashlib.sha256(chains_path(name).read_bytes()).hexdigest()
    hashes = recorded_hashes() | {chains_path(name).name: actual}
    path = DATA / HASHES
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text("".join(f"{h}  {f}\n" for f, h in sorted(hashes.items())))
    os.replace(temporary, path)
    return actual


def libero_task_index(scene: Scene) -> int:
    names = [t.name for t in libero_sim.benchmark(scene.libero_suite).tasks]
    if scene.libero_task not in names:
        raise ChainDataError(
            f"scene {scene.name!r}: {scene.libero_task!r} is not a task of LIBERO's libero_{scene.libero_suite}"
        )
    return names.index(scene.libero_task)


@cache
def scene_problem(scene: Scene) -> dict[str, Any]:
    """The scene's BDDL problem with every subtask's goal as its goal list, so the state
    layout (adapters/libero_layout.state_layout) holds every region any subtask names, in one
    order for the whole scene."""
    problem = dict(libero_sim.task_problem(scene.libero_suite, libero_task_index(scene)))
    goals: list[list[str]] = []
    for s in scene.subtasks:
        for p in (*s.goal, *s.goal_not, *s.pre, *s.unless):
            if list(p) not in goals:
                goals.append(list(p))
    problem["goal_state"] = goals
    return problem


def initial_state(problem: dict) -> frozenset[Predicate]:
    """The symbolic start: the BDDL's :init predicates (every chain starts from one of the
    LIBERO task's initial states, which satisfy them; tests check that on the simulator)."""
    return frozenset(tuple(p) for p in problem["initial_state"])


def check_scene_names(scene: Scene, problem: dict) -> None:
    """Every object and region a subtask names exists in the scene's BDDL."""
    known = {n for names in problem["objects"].values() for n in names}
    known |= {n for names in problem["fixtures"].values() for n in names}
    known |= set(problem["regions"])
    for p in sorted(scene.predicates()):
        for arg in p[1:]:
            if arg not in known:
                raise ChainDataError(
                    f"scene {scene.name!r}: {list(p)} names {arg!r}, which {scene.libero_task} does not "
                    f"have; its objects and regions: {', '.join(sorted(known))}"
                )


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m adapters.chain_scenes",
        description="Sample a chain scene's fixed evaluation chains from its precondition model, "
        "write adapters/chain_data/<scene>.chains.json and record its sha256 in "
        f"adapters/chain_data/{HASHES} (needs the libero extra for the BDDL).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="sample and write the chains of a scene")
    gen.add_argument("scene", help=f"scene name ({', '.join(scene_names())})")
    gen.add_argument(
        "--chains", type=int, default=CHAINS_PER_SCENE, help=f"how many (default {CHAINS_PER_SCENE})"
    )
    gen.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    args = parser.parse_args(argv)
    try:
        scene = load_scene(args.scene)
        problem = scene_problem(scene)
        check_scene_names(scene, problem)
        chains = sample_chains(scene, initial_state(problem), args.chains, args.seed, INITIAL_STATES)
    except ChainDataError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    command = (
        f"python -m adapters.chain_scenes generate {args.scene} --chains {args.chains} --seed {args.seed}"
    )
    text = json.dumps(
        {"scene": args.scene, "seed": args.seed, "command": command, "chains": [list(c) for c in chains]},
        indent=1,
    )
    path = chains_path(args.scene)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text + "\n")
    os.replace(temporary, path)  # a killed generator leaves the old file, never half a new one
    sha256 = record_chains_hash(args.scene)
    print(f"wrote {len(chains)} chains to {path} (sha256 {sha256}, recorded in {DATA / HASHES})")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
