"""Published numbers from the papers, as data, for labelled reference rows.

These are facts transcribed from Fast-dVLA (arXiv 2603.25661), and LIBERO-PRO's success
under perturbation from its authors' README (at the end of this file), never measurements of
ours: every row says `kind = "published"` and, in `source`, the paper, table and row its
numbers come from, and outputs show them beneath measured rows, never mixed into them.
Every value was checked against the paper's Tables 1, 2 and 4 as its authors publish
them (the arXiv PDF and the table images in the project page's repository; rows are
named as printed, without citation marks). Success values are percentages;
Tables 1 and 2 print them as fractions (0.902 is 90.2 here). Speedups are the paper's
own, printed beside its tokens/s.
"""

from __future__ import annotations

from dataclasses import dataclass

PUBLISHED = "published"
FAST_DVLA = "Fast-dVLA (arXiv 2603.25661)"


@dataclass(frozen=True)
class PublishedRow:
    method: str
    values: dict[str, float]  # column -> value as printed (success in %, avg length, ...)
    tokens_per_s: float | None
    speedup: float | None
    source: str  # paper, table and row the numbers were read from
    kind: str = PUBLISHED


@dataclass(frozen=True)
class PublishedTable:
    name: str
    columns: tuple[str, ...]  # the value columns, in the paper's order
    rows: tuple[PublishedRow, ...]
    source: str  # paper and table
    note: str = ""
    decimals: int = 1  # as printed in the paper (CALVIN's avg len has 2)
    baseline: str = ""  # the row the paper's speedups are over; '' when it prints none

    def text(self, column: str, value: float | None) -> str:
        if value is None:
            return "-"
        return f"{value:.2f}" if column == "avg len" else f"{value:.{self.decimals}f}"


def _rows(source: str, columns: tuple[str, ...], data: list[tuple]) -> tuple[PublishedRow, ...]:
    """data: (method, the paper's row label, *values, tokens/s, speedup) per row."""
    out = []
    for method, paper_row, *values, tok, speedup in data:
        out.append(
            PublishedRow(
                method, dict(zip(columns, values, strict=True)), tok, speedup, f"{source}, row {paper_row}"
            )
        )
    return tuple(out)


_LIBERO_SOURCE = f"{FAST_DVLA}, Table 1 (LIBERO)"
LIBERO_COLUMNS = ("Spatial", "Goal", "Object", "Long", "Avg")
_DREAM, _DD = "under 'Dream-VLA'", "under 'Discrete Diffusion VLA'"
LIBERO = PublishedTable(
    name="LIBERO",
    columns=LIBERO_COLUMNS,
    source=_LIBERO_SOURCE,
    note=(
        "success in % (the paper prints fractions), columns in the paper's order; every "
        "speedup is relative to Dream-VLA's 98.8 tokens/s, even for the DD-VLA rows"
    ),
    baseline="Dream-VLA",
    rows=_rows(
        _LIBERO_SOURCE,
        LIBERO_COLUMNS,
        [
            ("Dream-VLA", "'Dream-VLA'", 90.2, 92.0, 88.0, 72.0, 85.6, 98.8, 1.0),
            ("Dream-VLA + Fast-dLLM", f"'+ Fast-dLLM' {_DREAM}", 88.4, 89.4, 83.4, 70.2, 82.8, 183.2, 1.9),
            (
                "Dream-VLA + Block Diffusion",
                f"'+ Block Diffusion' {_DREAM}",
                91.8,
                90.4,
                88.6,
                72.2,
                85.8,
                181.7,
                1.8,
            ),
            (
                "Dream-VLA + Fast-dVLA",
                f"'+ Fast-dVLA (ours)' {_DREAM}",
                91.2,
                92.0,
                90.2,
                74.6,
                87.0,
                313.1,
                3.2,
            ),
            ("DD-VLA", "'Discrete Diffusion VLA'", 97.2, 98.6, 97.4, 92.0, 96.3, 152.1, 1.5),
            ("DD-VLA + Fast-dLLM", f"'+ Fast-dLLM' {_DD}", 94.0, 95.2, 94.8, 89.8, 93.5, 312.5, 3.2),
            (
                "DD-VLA + Block Diffusion",
                f"'+ Block Diffusion' {_DD}",
                97.6,
                98.6,
                97.2,
                93.2,
                96.7,
                322.1,
                3.3,
            ),
            ("DD-VLA + Fast-dVLA", f"'+ Fast-dVLA (ours)' {_DD}", 97.0, 98.8, 97.6, 92.8, 96.6, 402.7, 4.1),
        ],
    ),
)

_CALVIN_SOURCE = f"{FAST_DVLA}, Table 2 (CALVIN ABCD->D, UD-VLA base)"
CALVIN_COLUMNS = ("1/5", "2/5", "3/5", "4/5", "5/5", "avg len")
CALVIN = PublishedTable(
    name="CALVIN ABCD->D",
    columns=CALVIN_COLUMNS,
    source=_CALVIN_SOURCE,
    note=(
        "success (%) of reaching the i-th instruction of a 5-chain (the paper prints "
        "fractions); avg len = instructions completed (0-5); speedups relative to UD-VLA's "
        "67.3 tokens/s"
    ),
    baseline="UD-VLA",
    rows=_rows(
        _CALVIN_SOURCE,
        CALVIN_COLUMNS,
        [
            ("UD-VLA", "'UD-VLA'", 99.2, 96.8, 93.6, 90.4, 84.0, 4.64, 67.3, 1.0),
            ("UD-VLA + Fast-dLLM", "'+ Fast-dLLM'", 97.2, 92.0, 85.8, 80.8, 76.2, 4.32, 132.5, 2.0),
            (
                "UD-VLA + Block Diffusion",
                "'+ Block Diffusion'",
                98.8,
                94.4,
                89.4,
                86.2,
                80.4,
                4.50,
                129.5,
                1.9,
            ),
            ("UD-VLA + Fast-dVLA", "'+ Fast-dVLA (ours)'", 98.4, 95.2, 92.2, 87.0, 81.2, 4.54, 186.7, 2.8),
        ],
    ),
)

_SIMPLER_SOURCE = f"{FAST_DVLA}, Table 4 (SimplerEnv, WidowX robot tasks)"
SIMPLERENV = PublishedTable(
    name="SimplerEnv (WidowX)",
    columns=("Avg",),
    source=_SIMPLER_SOURCE,
    note=(
        "task success in %, averaged over SimplerEnv's four WidowX (Bridge) tasks: spoon on "
        "towel, carrot on plate, stack green block, eggplant in basket; no speedup column"
    ),
    rows=_rows(
        _SIMPLER_SOURCE,
        ("Avg",),
        [
            ("Dream-VLA", "'Dream-VLA'", 51.0, 100.1, None),
            ("Dream-VLA + Fast-dLLM", "'+ Fast-dLLM'", 41.7, 214.2, None),
            ("Dream-VLA + Block Diffusion", "'+ Block Diffusion'", 55.2, 226.4, None),
            ("Dream-VLA + Fast-dVLA", "'+ Fast-dVLA (ours)'", 59.3, 366.4, None),
        ],
    ),
)

TABLES: tuple[PublishedTable, ...] = (LIBERO, CALVIN, SIMPLERENV)


def libero_column(suite: str) -> str | None:
    """The LIBERO table column a measured suite name corresponds to, if any.

    Lets paper-table put measured LIBERO suites under the paper's own columns; any
    other suite gets no column, and the published rows then go in a table of their own.
    """
    name = suite.lower()
    if "libero" not in name:
        return None
    tail = name.split(":", 1)[0].rsplit("/", 1)[-1]  # "libero/10:obs=images" -> "10"
    tail = tail.removeprefix("libero_").removeprefix("libero-")
    return {"spatial": "Spatial", "goal": "Goal", "object": "Object", "10": "Long", "long": "Long"}.get(tail)


# --- observation regimes ------------------------------------------------------------
# The published LIBERO rows come from models that read camera images (and proprioception);
# a row measured on privileged state (object and fixture poses) answers an easier question.
PRIVILEGED = "privileged state"
ALLOW_PRIVILEGED_FLAG = "--allow-privileged"


class PrivilegedRowsError(ValueError):
    """Rows measured on privileged state would share a table with published image-based rows."""


def _suite_options(suite: str) -> dict[str, str]:
    _, _, opts = suite.partition(":")
    pairs = (item.strip().partition("=") for item in opts.split(",") if item.strip())
    return {key: value for key, _, value in pairs}


def observation_regime(suite: str) -> str:
    """What a suite's policies observed, from its name (the suite options ride on it):
    'privileged state' for LIBERO's default obs=state and Meta-World's 39-D state,
    'privileged state + images' for LIBERO obs=images (the state key is still there),
    'upstream images + proprio' for LIBERO obs=upstream; '' when the suite is not known."""
    base = suite.partition(":")[0].lower()
    if base.startswith("libero/"):
        obs = _suite_options(suite).get("obs", "state")
        return {
            "state": PRIVILEGED,
            "images": f"{PRIVILEGED} + images",
            "upstream": "upstream images + proprio",
        }.get(obs, f"obs={obs}")
    if base.startswith("metaworld/"):
        return PRIVILEGED  # hand, gripper, object and goal positions
    return ""


def is_privileged(suite: str) -> bool:
    return observation_regime(suite).startswith(PRIVILEGED)


def privileged_label(suites: list[str] | tuple[str, ...]) -> str:
    """' [privileged state]' (or '+ images') for a row measured on any such suite, else ''."""
    regimes = list(dict.fromkeys(observation_regime(s) for s in suites if is_privileged(s)))
    return f" [{'; '.join(regimes)}]" if regimes else ""


def check_comparable(suites: list[str] | tuple[str, ...], allow_privileged: bool = False) -> list[str]:
    """The measured suites that have published image-based rows and were measured on
    privileged state; raises PrivilegedRowsError for them unless `allow_privileged`."""
    found = [s for s in suites if is_privileged(s) and libero_column(s)]
    if found and not allow_privileged:
        raise PrivilegedRowsError(
            f"{', '.join(found)}: measured on privileged state (object and fixture poses), "
            "while the published LIBERO rows read camera images; measure with obs=upstream "
            f"(e.g. libero/spatial:obs=upstream), or pass {ALLOW_PRIVILEGED_FLAG} to print them "
            f"in one table anyway, each of ours labelled '{PRIVILEGED}'"
        )
    return found


def is_libero(suite: str) -> bool:
    """A LIBERO suite (`libero/spatial`, `libero/10:obs=upstream`): the suites the
    published LIBERO rows belong beside. Instruction chains on LIBERO scenes are not."""
    return suite.lower().split(":", 1)[0].startswith("libero")


def tables_for(suites: list[str]) -> list[PublishedTable]:
    """The published tables worth showing beside these measured suites: LIBERO's, when
    one of them is a LIBERO suite, and none beside a Meta-World or plugin suite.
    CALVIN's and SimplerEnv's rows go beneath each instruction-chain or SimplerEnv-like
    suite in that benchmark's own layout instead (results.paper_table.calvin_blocks and
    simpler_blocks)."""
    return [LIBERO] if any(is_libero(s) for s in suites) else []


# --- LIBERO-PRO (generalization under perturbation) ---------------------------------
# Success rates the LIBERO-PRO authors publish for image-based models on the standard
# suites and under their perturbations. They go beneath measured rows in the
# generalization-gap table (results/generalization.py), per suite, never mixed into them.
# The arXiv paper's own tables could not be read where these were transcribed; both tables
# below are the authors' README tables in their repository (the leaderboard the README
# says summarises "model performance under five generalization perturbations"). The
# README prints fractions (0.96); values here are percentages (96.0); '-' is None.
LIBERO_PRO = "LIBERO-PRO (Zhou et al., 2025, arXiv 2510.03827)"
_PRO_README = f"{LIBERO_PRO}, README of github.com/Zxy-MLlab/LIBERO-PRO (commit 2b910b5)"
PRO_SUITES = ("goal", "spatial", "10", "object")  # the README's column-group order
PRO_PERTURBATIONS = ("object", "swap", "lan", "task", "env")  # Obj. Pos. Sem. Task Env.


@dataclass(frozen=True)
class PublishedGapRow:
    """One model on one suite: success (%) on the standard suite (`standard`) and under
    each perturbation it was published for (keys of PRO_PERTURBATIONS)."""

    method: str
    suite: str  # spatial, object, goal or 10
    values: dict[str, float | None]
    source: str  # paper or repository, table and row the numbers were read from
    table: str  # a short name of the source table, printed beside the method
    kind: str = PUBLISHED


def _pro_rows(
    tag: str, table: str, columns: tuple[str, ...], data: list[tuple[str, str]]
) -> tuple[PublishedGapRow, ...]:
    """data: (model as the table prints it, the row's values as printed: one group of
    `columns` per suite in PRO_SUITES order, fractions, '-' for no value)."""
    out = []
    for method, printed in data:
        numbers = [None if v == "-" else round(100 * float(v), 1) for v in printed.split()]
        if len(numbers) != len(columns) * len(PRO_SUITES):
            raise ValueError(f"{table}, row {method!r}: {len(numbers)} values")
        for i, suite in enumerate(PRO_SUITES):
            group = numbers[i * len(columns) : (i + 1) * len(columns)]
            source = f"{_PRO_README}, {table}, row '{method}', LIBERO-{suite.capitalize()} columns"
            out.append(PublishedGapRow(method, suite, dict(zip(columns, group, strict=True)), source, tag))
    return tuple(out)


# "LIBERO-Pro Model Leaderboard": per suite Obj, Pos, Sem, Task, Env (its Total column left out).
LIBERO_PRO_LEADERBOARD = _pro_rows(
    "leaderboard",
    "table 'LIBERO-Pro Model Leaderboard'",
    PRO_PERTURBATIONS,
    [
        (
            "OpenVLA",
            "0.96 0.00 0.98 0.00 0.98  0.97 0.00 0.97 0.00 0.89  0.81 0.00 0.96 0.00 0.85  0.98 0.00 0.98 0.00 0.00",
        ),
        (
            "Pi0",
            "0.94 0.00 0.93 0.00 0.39  0.95 0.00 0.97 0.00 0.60  0.79 0.00 0.82 0.00 0.27  0.94 0.00 0.90 0.00 0.29",
        ),
        (
            "Pi0.5",
            "0.97 0.38 0.97 0.00 0.46  0.97 0.20 0.97 0.01 0.46  0.92 0.08 0.93 0.01 0.46  0.98 0.17 0.96 0.01 0.73",
        ),
        (
            "Molmoact",
            "0.68 0.00 0.85 0.00 -  0.90 0.00 0.88 0.00 -  0.54 0.00 0.74 0.06 -  0.92 0.06 0.96 0.00 -",
        ),
        (
            "NORA",
            "0.58 0.00 0.88 0.00 -  0.92 0.00 0.91 0.00 -  0.46 0.00 0.74 0.00 -  0.86 0.00 0.92 0.00 -",
        ),
        (
            "x-VLA",
            "0.68 0.01 0.98 0.09 -  0.97 0.00 0.96 0.00 -  0.62 0.00 0.95 0.10 -  0.89 0.02 0.98 0.08 -",
        ),
    ],
)
# "Motivation": per suite Original, + P1 (task perturbation), + P2 (position perturbation).
LIBERO_PRO_MOTIVATION = _pro_rows(
    "motivation",
    "table under 'Motivation' (Original, + P1: Task, + P2: Position)",
    ("standard", "task", "swap"),
    [
        ("OpenVLA", "0.98 0.0 0.0  0.95 0.0 0.0  0.93 0.0 0.0  0.99 0.0 0.0"),
        ("Pi0", "0.92 0.0 0.0  0.90 0.0 0.0  0.82 0.0 0.0  0.98 0.0 0.0"),
        ("Pi0.5", "0.97 0.0 0.4  0.96 0.0 0.2  0.93 0.0 0.1  0.98 0.0 0.2"),
        ("UniVLA", "0.89 0.0 0.1  0.85 0.0 0.1  0.61 0.0 0.0  0.98 0.0 0.0"),
    ],
)
LIBERO_PRO_ROWS = LIBERO_PRO_MOTIVATION + LIBERO_PRO_LEADERBOARD
LIBERO_PRO_NOT_COMPARABLE = "(published, LIBERO-PRO: not comparable)"


def libero_pro_rows(suite: str) -> tuple[PublishedGapRow, ...]:
    """The published LIBERO-PRO rows for a measured LIBERO suite (`libero/goal:seeding=openvla`),
    none for any other suite (a plugin suite with a `perturb=` option of its own included)."""
    base = suite.partition(":")[0].lower()
    if not base.startswith("libero/"):
        return ()
    key = base.removeprefix("libero/")
    return tuple(r for r in LIBERO_PRO_ROWS if r.suite == key)


def libero_pro_label(suite: str) -> str:
    """The label of published LIBERO-PRO rows beside a measured suite: they read camera
    images, so beside rows measured on privileged state they are 'not comparable'."""
    return LIBERO_PRO_NOT_COMPARABLE if is_privileged(suite) else "(published, LIBERO-PRO)"
