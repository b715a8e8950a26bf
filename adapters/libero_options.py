"""LIBERO suite options: what rides on the suite's name (`libero/spatial:obs=images,...`).

Kept apart from adapters/libero.py so the options can be parsed, named and checked
without the simulator: the canonical suffix is what every row records, so two runs that
differ in a score-moving option (seeding, initial states) never share a suite name.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from adapters.base import SuiteOptionError, refuse_repeated_options
from adapters.libero_seeding import DEFAULT_SEEDING, SEEDINGS
from adapters.libero_states import DEFAULT_STATES_SEED, INITIAL_STATES

# OpenVLA (libero_utils.get_libero_env, resolution=256) and openpi (LIBERO_ENV_RESOLUTION)
# both render 256 px; each model then resizes to 224 its own way (OpenVLA: JPEG round trip
# and lanczos3, openpi: resize_with_pad), which is the policy's business, not the env's.
UPSTREAM_IMAGE_SIZE = 256
DEFAULT_IMAGE_SIZE = 128  # obs=images: CPU rendering of two 256 px cameras is ~4x slower
OBS = ("state", "images", "upstream")  # the observation regimes (docs/libero.md)
# Where the policy's instruction comes from (docs/libero-pro.md, "The instruction"):
# `filename`, LIBERO's task.language (the task's file name in words), as OpenVLA's
# run_libero_eval and openpi's LIBERO example give it, and so LIBERO-PRO's published
# table; `bddl`, the BDDL file's (:language ...), as LIBERO-PRO's libero/evaluation
# runner gives it (env.language_instruction): under perturb=lan the paraphrase.
INSTRUCTIONS = ("filename", "bddl")
DEFAULT_INSTRUCTION = "filename"


@dataclass(frozen=True)
class Options:
    obs: str = "state"  # a key of OBS: state, images (state + raw cameras), upstream
    image_size: int | None = None  # None: the regime's default (`size`)
    shadows: bool = True  # MuJoCo's defaults; off renders 2-10x faster on a CPU
    reflections: bool = True
    seeding: str = DEFAULT_SEEDING  # a key of SEEDINGS
    # evaluation: the init files' 50 states; fresh: new draws (adapters/libero_states.py).
    # None until the split decides: fresh for train (collect), evaluation for eval.
    initial_states: str | None = None
    states_seed: int | None = None  # fresh only; None: DEFAULT_STATES_SEED
    # LIBERO-PRO perturbations in its order of application, () for the standard suite
    # (adapters/libero_pro.py)
    perturb: tuple[str, ...] = ()
    instruction: str = DEFAULT_INSTRUCTION  # a key of INSTRUCTIONS

    @property
    def size(self) -> int:
        """Square image size: as given, else 256 for upstream (what its models were trained
        on) and 128 for images."""
        if self.image_size is not None:
            return self.image_size
        return UPSTREAM_IMAGE_SIZE if self.obs == "upstream" else DEFAULT_IMAGE_SIZE

    @property
    def cameras(self) -> bool:
        return self.obs in ("images", "upstream")

    def suffix(self) -> str:
        """The canonical option string: the options not at their defaults, and always the
        seeding (it moves scores, and the default changed: earlier runs seeded per episode).
        Every regime but state is named (`obs=images`, `obs=upstream`), so a row says what
        its policy saw. The instruction source is named when it is `bddl`, and under `lan`
        and `task` always: there the two sources give other words (the paraphrase, the new
        goal's), and such a name without it is read as `bddl` (results/generalization.py).
        Elsewhere `filename` stays unnamed, so a scene perturbation's name and rows are
        those of the standard words."""
        default_size = UPSTREAM_IMAGE_SIZE if self.obs == "upstream" else DEFAULT_IMAGE_SIZE
        parts = [f"perturb={'+'.join(self.perturb)}"] if self.perturb else []
        if self.instruction != DEFAULT_INSTRUCTION or {"lan", "task"} & set(self.perturb):
            parts.append(f"instruction={self.instruction}")
        for key, value, default in (
            ("obs", self.obs, "state"),
            ("image_size", self.size, default_size),
            ("shadows", self.shadows, True),
            ("reflections", self.reflections, True),
        ):
            if value != default:
                parts.append(f"{key}={'on' if value is True else 'off' if value is False else value}")
        parts.append(f"seeding={self.seeding}")
        if self.initial_states == "fresh":  # evaluation states are the protocol: unnamed
            parts.append(f"initial_states=fresh,states_seed={self.states_seed}")
        return ":" + ",".join(parts)


def parse_bool(key: str, text: str) -> bool:
    low = text.lower()
    if low in ("on", "true", "1", "yes"):
        return True
    if low in ("off", "false", "0", "no"):
        return False
    raise SuiteOptionError(f"suite option {key}={text!r}: expected on or off")


def parse_options(text: str) -> Options:
    refuse_repeated_options(text)
    values: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq:
            raise SuiteOptionError(f"suite option {item!r}: expected key=value")
        if key == "obs":
            if value not in OBS:
                raise SuiteOptionError(f"suite option obs={value!r}: choose {', '.join(OBS)}")
            values[key] = value
        elif key == "image_size":
            if not value.isdigit() or not 1 <= int(value) <= 1024:
                raise SuiteOptionError(f"suite option image_size={value!r}: expected an integer in [1, 1024]")
            values[key] = int(value)
        elif key in ("shadows", "reflections"):
            values[key] = parse_bool(key, value)
        elif key == "seeding":
            if value not in SEEDINGS:
                raise SuiteOptionError(f"suite option seeding={value!r}: choose {' or '.join(SEEDINGS)}")
            values[key] = value
        elif key == "initial_states":
            if value not in INITIAL_STATES:
                raise SuiteOptionError(
                    f"suite option initial_states={value!r}: choose {' or '.join(INITIAL_STATES)}"
                )
            values[key] = value
        elif key == "perturb":
            from adapters.libero_pro import parse_perturb

            values[key] = parse_perturb(value)
        elif key == "instruction":
            if value not in INSTRUCTIONS:
                raise SuiteOptionError(
                    f"suite option instruction={value!r}: choose {' or '.join(INSTRUCTIONS)}"
                )
            values[key] = value
        elif key == "states_seed":
            if not value.isdigit():
                raise SuiteOptionError(f"suite option states_seed={value!r}: expected a non-negative integer")
            values[key] = int(value)
        else:
            raise SuiteOptionError(
                f"unknown suite option {key!r}; valid options: obs={'|'.join(OBS)}, image_size=N, "
                f"shadows=on|off, reflections=on|off, seeding={'|'.join(SEEDINGS)}, "
                f"initial_states={'|'.join(INITIAL_STATES)}, states_seed=N, perturb=swap|env|object|lan|task, "
                f"instruction={'|'.join(INSTRUCTIONS)}"
            )
    return Options(**values)


def resolve_initial_states(options: Options, split: str) -> Options:
    """LIBERO ships one set of initial states, the evaluation's, so the train split (what
    `collect` reads) draws fresh ones unless told `initial_states=evaluation`."""
    states = options.initial_states or ("fresh" if split == "train" else "evaluation")
    if states == "evaluation" and options.states_seed is not None:
        raise SuiteOptionError("suite option states_seed needs initial_states=fresh")
    seed = DEFAULT_STATES_SEED if options.states_seed is None else options.states_seed
    return replace(options, initial_states=states, states_seed=seed if states == "fresh" else None)
