"""Leaderboards and paper tables against hand-computed small tables; the CLI's refusals."""

from __future__ import annotations

import copy
import json
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from results.leaderboard import leaderboard, leaderboards
from results.paper_table import paper_blocks, paper_table
from results.published import libero_column
from results.runs import Run, combined_episodes, load_run
from results.schema import COLUMN_NAMES, SCHEMA_VERSION_KEY, arrow_schema
from results.store import RunDir

MANIFEST: dict[str, Any] = {
    "manifest_version": 1,
    "run_id": "r",
    "suite": {
        "name": "metaworld/mt10",
        "version": "1",
        "tasks": ["a", "b"],
        "render_backend": "none (state observations)",
        "simulator_packages": {"metaworld": "3.1.1", "mujoco": "3.3.0"},
    },
    "environment": {
        "python": "3.11.7",
        "packages": {"mujoco": "3.3.0", "numpy": "2.0"},
        "simulators": {"metaworld": "3.1.1", "libero": None},
        "git_commit": "abc123",
        "platform": "Linux",
        "host": "box1",
        "cpu": "AMD EPYC",
        "cpu_count": 2,
        "gpu": None,
        "mujoco_gl": None,
    },
    "command": ["dvla-harness", "run"],
    "status": "finished",
}
BIDI = '{"checkpoint":"/x/metaworld-mt10-bidirectional.safetensors","steps":12}'
FAST = '{"checkpoint":"/x/metaworld-mt10-fast_dvla.safetensors","tau_conf":0.5}'


def row(policy: str = "bidirectional", params: str = BIDI, config: str = "bidi000001", **kw: Any) -> dict:
    """A complete episode row; `kw` overrides columns."""
    base: dict[str, Any] = {
        "run_id": "r",
        "suite": "metaworld/mt10",
        "suite_version": "1",
        "task": "a",
        "task_index": 0,
        "instruction": "do a",
        "episode_index": 0,
        "seed": 7,
        "init_state_id": 0,
        "policy": policy,
        "policy_params": params,
        "policy_config_id": config,
        "config_label": None,
        "checkpoint": "",
        "checkpoint_sha256": "",
        "replan_every": 0,
        "max_steps": 500,
        "success": True,
        "steps": 50,
        "chunks": 10,
        "nfe_total": 120,
        "nfe_per_chunk": 12.0,
        "action_tokens_total": 320,
        "tokens_per_s": 100.0,
        "policy_time_s": 3.2,
        "env_time_s": 0.5,
        "overhead_s": 0.01,
        "wall_clock_s": 3.71,
        "control_hz": 15.6,
        "loop_hz": 13.5,
        "failure_reason": None,
        "started_at": datetime(2026, 1, 1, tzinfo=UTC),
    }
    unknown = set(kw) - set(base)
    assert not unknown, unknown
    return base | kw


def episodes(policy: str, params: str, config: str, successes: list[int], task: str = "a", **kw: Any):
    """One row per entry of `successes` (episode i, init state i), task `task`."""
    index = {"a": 0, "b": 1}.get(task, 2)
    return [
        row(
            policy,
            params,
            config,
            task=task,
            task_index=index,
            episode_index=i,
            init_state_id=i,
            success=bool(s),
            started_at=datetime(2026, 1, 1, tzinfo=UTC) + timedelta(seconds=i + 100 * index),
            **kw,
        )
        for i, s in enumerate(successes)
    ]


def write_run(path: Path, rows: list[dict], manifest: dict | None = None, **env: Any) -> Path:
    """A real run folder, written through results.store like the runner writes it."""
    m = copy.deepcopy(MANIFEST if manifest is None else manifest)
    m["environment"] |= env
    run_dir = RunDir(path)
    run_dir.create()
    run_dir.write_manifest(m)
    for r in rows:
        run_dir.append_episode(r)
    run_dir.compact()
    return path


def by_label(board):
    return {e.label: e for e in board.entries}


# ---------------------------------------------------------------------------- aggregation


def test_success_per_task_and_overall_with_wilson_bounds(tmp_path):
    rows = episodes("bidirectional", BIDI, "bidi000001", [1] * 7 + [0] * 3)
    rows += episodes("bidirectional", BIDI, "bidi000001", [1, 0], task="b")
    (board,) = leaderboards([load_run(write_run(tmp_path / "r", rows))])
    assert board.groups == ("a", "b")
    (entry,) = board.entries
    a = entry.success["a"]
    assert (a.successes, a.episodes) == (7, 10)
    low, high = a.interval  # 7/10, hand-computed: centre 0.64449, half-width 0.24772
    assert low == pytest.approx(0.3968, abs=1e-4) and high == pytest.approx(0.8922, abs=1e-4)
    assert a.text() == "70.0% [40, 89] (7/10)"
    assert (entry.overall.successes, entry.overall.episodes) == (8, 12)
    frame = board.frame()
    assert frame.loc[0, "success[overall]"] == pytest.approx(8 / 12)
    assert frame.loc[0, "success_low[a]"] == pytest.approx(0.3968, abs=1e-4)


def test_speedup_over_the_baseline_on_the_same_machine(tmp_path):
    rows = episodes("bidirectional", BIDI, "bidi000001", [1, 1])
    rows[1]["tokens_per_s"] = 200.0  # baseline mean 150
    fast = episodes("fast_dvla", FAST, "fast000001", [1, 0], tokens_per_s=300.0, nfe_per_chunk=6.0)
    scripted = episodes("scripted", "{}", "scri000001", [1, 1], tokens_per_s=None, nfe_per_chunk=0.0)
    (board,) = leaderboards([load_run(write_run(tmp_path / "r", rows + fast + scripted))])
    e = by_label(board)
    assert e["bidirectional"].tokens_per_s == 150.0 and e["bidirectional"].speedup == 1.0
    assert e["fast_dvla"].speedup == pytest.approx(2.0) and e["fast_dvla"].nfe_per_chunk == 6.0
    assert e["scripted"].speedup is None and e["scripted"].speedup_note == "n/a: no tokens"
    headers, cells = board.cells()
    speed = {r[0].value: r[headers.index("speedup vs bidirectional")].text for r in cells}
    assert speed == {"bidirectional": "1.00x", "fast_dvla": "2.00x", "scripted": "n/a: no tokens"}


def test_no_speedup_across_machines_and_the_cell_says_why(tmp_path):
    here = write_run(tmp_path / "a", episodes("bidirectional", BIDI, "bidi000001", [1, 1]))
    there_rows = episodes("fast_dvla", FAST, "fast000001", [1, 1], tokens_per_s=400.0)
    there = write_run(tmp_path / "b", there_rows, gpu="NVIDIA H100")
    (board,) = leaderboards([load_run(here), load_run(there)])
    e = by_label(board)
    assert e["fast_dvla"].speedup is None and e["fast_dvla"].speedup_note == "n/a: other machine"
    headers, _ = board.cells()
    assert "machine" in headers  # two machines: the table says which row ran where


def test_baseline_by_name_or_config_id_and_missing_baseline(tmp_path):
    rows = episodes("bidirectional", BIDI, "bidi000001", [1])
    rows += episodes("fast_dvla", FAST, "fast000001", [1], tokens_per_s=250.0)
    run = load_run(write_run(tmp_path / "r", rows))
    (board,) = leaderboards([run], baseline="fast000001")
    assert by_label(board)["bidirectional"].speedup == pytest.approx(100 / 250)
    (board,) = leaderboards([run], baseline="autoregressive")
    assert {e.speedup_note for e in board.entries} == {"n/a: no autoregressive row"}


def test_labels_show_parameters_that_differ_from_defaults_or_between_rows(tmp_path):
    low = FAST.replace("0.5", "0.3")
    rows = episodes("fast_dvla", FAST, "fast000001", [1]) + episodes("fast_dvla", low, "fast000002", [1])
    (board,) = leaderboards([load_run(write_run(tmp_path / "r", rows))])
    assert [e.label for e in board.entries] == ["fast_dvla (tau_conf=0.5)", "fast_dvla (tau_conf=0.3)"]


def test_warnings_on_mujoco_render_backend_and_episode_count_differences(tmp_path):
    a = write_run(tmp_path / "a", episodes("bidirectional", BIDI, "bidi000001", [1, 1, 0]))
    other = copy.deepcopy(MANIFEST)
    other["suite"]["simulator_packages"]["mujoco"] = "3.2.7"
    other["environment"]["packages"]["mujoco"] = "3.2.7"
    other["suite"]["render_backend"] = "egl"
    b = write_run(tmp_path / "b", episodes("fast_dvla", FAST, "fast000001", [1, 0]), other)
    (board,) = leaderboards([load_run(a), load_run(b)])
    text = "\n".join(board.warnings)
    assert board.warnings[0].startswith(f"simulator versions differ (mujoco 3.3.0 ({a}) vs 3.2.7 ({b})): ")
    assert "runs differ in render backend" in text and "egl" in text
    assert "episode counts differ between rows: bidirectional 3, fast_dvla 2" in text
    (same,) = leaderboards([load_run(a)])
    assert same.warnings == ()


def test_warning_when_rows_start_from_different_seeds_or_initial_states(tmp_path):
    rows = episodes("bidirectional", BIDI, "bidi000001", [1, 1])
    rows += episodes("fast_dvla", FAST, "fast000001", [1, 1], seed=8)
    (board,) = leaderboards([load_run(write_run(tmp_path / "r", rows))])
    assert any("seeds or initial states differ between rows for 2 episode(s)" in w for w in board.warnings)


def test_many_tasks_collapse_to_the_overall_column_and_groups_can_be_chosen(tmp_path):
    rows = []
    for t in range(12):
        rows += episodes("bidirectional", BIDI, "bidi000001", [t % 2], task=f"t{t:02d}")
    run = load_run(write_run(tmp_path / "r", rows))
    (board,) = leaderboards([run])
    assert board.groups == () and board.entries[0].overall.successes == 6
    (board,) = leaderboards([run], group_by=lambda task: "even" if int(task[1:]) % 2 == 0 else "odd")
    assert board.groups == ("even", "odd") and board.entries[0].success["odd"].successes == 6


def test_a_dataframe_without_run_columns_works_in_a_notebook(tmp_path):
    run = load_run(write_run(tmp_path / "r", episodes("bidirectional", BIDI, "bidi000001", [1, 0])))
    board = leaderboard(run.episodes)
    assert board.entries[0].overall.episodes == 2 and board.entries[0].speedup == 1.0
    assert len(combined_episodes([run])) == 2


def test_paper_table_lines_up_libero_suites_and_puts_published_rows_beneath(tmp_path):
    rows = []
    for suite, wins in (("libero/spatial", [1, 1, 1, 0]), ("libero/goal", [1, 0, 0, 0])):
        rows += [r | {"suite": suite} for r in episodes("bidirectional", BIDI, "bidi000001", wins)]
        rows += [
            r | {"suite": suite}
            for r in episodes("fast_dvla", FAST, "fast000001", wins[::-1], tokens_per_s=300.0)
        ]
    run: Run = load_run(write_run(tmp_path / "r", rows))
    table = paper_table([run])
    fast = next(r for r in table.rows if r.label == "fast_dvla")
    assert fast.success["libero/spatial"].successes == 3 and fast.average == pytest.approx(50.0)
    assert fast.speedup == pytest.approx(3.0)
    block, paper = paper_blocks(table, allow_privileged=True)  # measured, then published: two sections
    assert block.headers[1:3] == ["Spatial (libero/spatial)", "Goal (libero/goal)"]
    assert block.headers[4:6] == ["tokens/s (measured)", "speedup vs bidirectional (measured)"]
    measured = [r[0].text for r in block.rows]
    assert measured == ["bidirectional [privileged state]", "fast_dvla [privileged state]"]
    assert block.published_from is None and paper.published_from == 0
    assert paper.headers == [
        "method", "Spatial", "Goal", "Object", "Long", "Avg", "tokens/s (published)",
        "speedup vs Dream-VLA (published)", "source",
    ]  # fmt: skip
    published = paper.rows
    assert len(published) == 8 and all(r[0].text.endswith("(published)") for r in published)
    assert all(r[-1].text.startswith("published: Fast-dVLA (arXiv 2603.25661)") for r in published)
    dream = published[0]
    assert [c.text for c in dream[1:8]] == ["90.2", "92.0", "88.0", "72.0", "85.6", "98.8", "1.0x"]


@pytest.mark.parametrize(
    ("suite", "column"),
    [
        ("libero/spatial", "Spatial"),
        ("libero/10", "Long"),
        ("libero/goal:obs=images", "Goal"),
        ("libero/90", None),
    ],
)
def test_measured_libero_suites_map_to_the_paper_columns(suite, column):
    assert libero_column(suite) == column


# ---------------------------------------------------------------------------- CLI


def test_cli_markdown_to_a_file_and_warnings_on_stderr(cli, tmp_path):
    a = write_run(tmp_path / "a", episodes("bidirectional", BIDI, "bidi000001", [1, 1, 0]))
    b = write_run(tmp_path / "b", episodes("fast_dvla", FAST, "fast000001", [1, 0], tokens_per_s=300.0))
    out = tmp_path / "board.md"
    code, stdout, stderr = cli("leaderboard", str(a), str(b), "--out", str(out))
    assert code == 0 and f"wrote {out}" in stdout
    text = out.read_text()
    assert "| fast_dvla [privileged state] | 50.0% [9, 91] (1/2) |" in text and "3.00x" in text
    assert "warning: metaworld/mt10: episode counts differ" in stderr.replace("\n", " ")
    code, stdout, _ = cli("leaderboard", str(a), str(b), "--format", "csv")
    assert code == 0 and stdout.splitlines()[0].startswith("suite,policy,label,policy_config_id")


def _foreign_parquet(path: Path) -> Path:
    pq.write_table(pa.table({"x": [1, 2]}), path)
    return path


def _other_version_parquet(path: Path) -> Path:
    schema = arrow_schema()
    table = pa.Table.from_pylist([row()], schema=schema)
    meta = dict(schema.metadata) | {SCHEMA_VERSION_KEY: b"999"}
    pq.write_table(table.replace_schema_metadata(meta), path)
    return path


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "missing", "no such run folder or file"),
        (lambda d: (d / "empty").mkdir() or d / "empty", "not a run folder (no manifest.json"),
        (lambda d: _foreign_parquet(d / "x.parquet"), "not a dvla-harness episode table"),
        (
            lambda d: _other_version_parquet(d / "v.parquet"),
            "schema version 999, but this dvla-harness reads",
        ),
    ],
)
@pytest.mark.parametrize("command", [["leaderboard"], ["report", "paper-table"], ["report", "html"]])
def test_cli_bad_runs_exit_2_and_write_nothing(cli, tmp_path, make, message, command):
    src = tmp_path / "in"
    src.mkdir()
    bad = make(src)
    before = sorted(p.name for p in src.iterdir())
    out = tmp_path / ("report" if command[-1] == "html" else "board.md")
    extra = ["--out", str(out)] if command != ["report", "paper-table"] else []
    code, _, stderr = cli(*command, str(bad), *extra)
    assert code == 2 and message in stderr and len(stderr.strip().splitlines()) == 1
    assert not out.exists() and sorted(p.name for p in src.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_cli_other_bad_input_exits_2(cli, tmp_path):
    run = write_run(tmp_path / "r", episodes("bidirectional", BIDI, "bidi000001", [1]))
    cases = [
        (["leaderboard", str(run), "--baseline", "nope"], "--baseline 'nope' is not in these runs"),
        (["leaderboard", str(run), "--out", str(tmp_path / "no" / "b.md")], "does not exist"),
        (["leaderboard", str(run), "--out", str(tmp_path / "b.txt")], "cannot tell the format"),
        (["leaderboard", str(run), str(run)], "is given twice"),
        (["report", "html", str(run), "--out", str(run), "--overwrite"], "not a dvla-harness report folder"),
    ]
    for argv, message in cases:
        code, _, stderr = cli(*argv)
        assert code == 2 and message in stderr, (argv, stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]
    assert json.loads((run / "manifest.json").read_text())["status"] == "finished"


def test_numbers_come_from_the_parquet_rows(tmp_path):
    rows = episodes("bidirectional", BIDI, "bidi000001", [1, 0, 1])
    for i, r in enumerate(rows):
        r |= {"tokens_per_s": 90.0 + i, "control_hz": 10.0 * (i + 1), "wall_clock_s": 1.0 + i}
    path = write_run(tmp_path / "r", rows)
    df = pq.read_table(path / "episodes.parquet").to_pandas()
    assert list(df.columns) == list(COLUMN_NAMES)
    (board,) = leaderboards([load_run(path)])
    frame = board.frame().iloc[0]
    for column in ("tokens_per_s", "control_hz", "wall_clock_s", "nfe_per_chunk"):
        assert frame[column] == pytest.approx(df[column].mean())
    assert frame["successes[overall]"] == int(df["success"].sum())


def test_every_output_counts_an_episode_given_twice_once(tmp_path):
    """A run folder and a copy of it (or a resumed folder given twice): leaderboard,
    plots and reports (the HTML page's header too) all read through combined_episodes and
    count the same rows."""
    import shutil

    from results.html_report import render_page
    from results.plots import pareto_plot, plot_frame
    from results.runs import combined_episodes

    rows = episodes("bidirectional", BIDI, "bidi000001", [1, 1, 0]) + episodes(
        "fast_dvla", FAST, "fast000001", [1, 0, 0], tokens_per_s=200.0
    )
    a = write_run(tmp_path / "a", rows)
    shutil.copytree(a, tmp_path / "b")
    runs = [load_run(a), load_run(tmp_path / "b")]
    combined = combined_episodes(runs)
    assert len(combined) == 6 and combined.attrs["duplicates"] == 6
    (board,) = leaderboards(runs)
    assert by_label(board)["fast_dvla"].overall.episodes == 3
    assert any("appear in more than one run" in w for w in board.warnings)
    frame = plot_frame(combined)
    assert frame.groupby("policy").size().to_dict() == {"bidirectional": 3, "fast_dvla": 3}
    pareto_plot(frame, out=tmp_path / "p.png")
    page = render_page(runs, [board], figures=False)
    assert "2 run(s), 6 episodes (6 duplicate row(s) of an episode given twice not counted)." in page


def test_paper_table_speedups_are_taken_within_each_suite(tmp_path):
    """An MT10 teacher never becomes the baseline of a LIBERO row: each suite's speedup
    uses that suite's baseline, and a row's speedup averages its suites'."""
    mt10 = episodes("bidirectional", BIDI, "bidi000001", [1, 1], tokens_per_s=1000.0)
    lib_bidi = '{"checkpoint":"/x/libero-spatial-bidirectional.safetensors","steps":12}'
    lib_fast = '{"checkpoint":"/x/libero-spatial-fast_dvla.safetensors","tau_conf":0.5}'
    spatial = [
        r | {"suite": "libero/spatial"}
        for r in episodes("bidirectional", lib_bidi, "bidilib001", [1, 0], tokens_per_s=100.0)
        + episodes("fast_dvla", lib_fast, "fastlib001", [1, 1], tokens_per_s=300.0)
    ]
    table = paper_table([load_run(write_run(tmp_path / "r", mt10 + spatial))])
    fast = next(r for r in table.rows if r.policy_config_id == "fastlib001")
    assert fast.speedup == pytest.approx(3.0)  # 300 / the spatial teacher's 100, not / 1000


# ---------------------------------------------------------------------------- observation regimes


@pytest.mark.parametrize(
    ("suite", "regime"),
    [
        ("libero/spatial:seeding=openvla", "privileged state"),
        ("libero/spatial", "privileged state"),  # rows from before the seeding option
        ("libero/goal:obs=images,image_size=64,seeding=openpi", "privileged state + images"),
        ("libero/10:obs=upstream,seeding=openvla", "upstream images + proprio"),
        ("metaworld/mt10:layouts=upstream,seed=1", "privileged state"),
        ("fake/countdown", ""),
    ],
)
def test_the_observation_regime_comes_from_the_suite_name(suite, regime):
    from results.published import is_privileged, observation_regime

    assert observation_regime(suite) == regime
    assert is_privileged(suite) == regime.startswith("privileged state")


def _libero_rows(obs: str = "") -> list[dict]:
    """Spatial and goal rows of two policies; `obs` is the suite option (e.g. 'obs=upstream,')."""
    rows = []
    for key, wins in (("spatial", [1, 1, 0]), ("goal", [1, 0, 0])):
        suite = f"libero/{key}:{obs}seeding=openvla"
        rows += [r | {"suite": suite} for r in episodes("bidirectional", BIDI, "bidi000001", wins)]
        rows += [
            r | {"suite": suite} for r in episodes("fast_dvla", FAST, "fast000001", wins, tokens_per_s=300.0)
        ]
    return rows


def test_leaderboard_labels_rows_measured_on_privileged_state(cli, tmp_path):
    state = write_run(tmp_path / "state", _libero_rows())
    upstream = write_run(tmp_path / "upstream", _libero_rows("obs=upstream,"))
    boards = {b.suite: b for b in leaderboards([load_run(state), load_run(upstream)])}
    for suite, label in (
        ("libero/spatial:seeding=openvla", "fast_dvla [privileged state]"),
        ("libero/spatial:obs=upstream,seeding=openvla", "fast_dvla"),
    ):
        _, cells = boards[suite].cells()
        assert [r[0].text for r in cells][1] == label
    frame = boards["libero/goal:seeding=openvla"].frame()
    assert set(frame["observations"]) == {"privileged state"}
    code, stdout, _ = cli("leaderboard", str(state), str(upstream), "--format", "md")
    assert code == 0
    assert (
        "## libero/spatial:seeding=openvla" in stdout
        and "## libero/spatial:obs=upstream,seeding=openvla" in stdout
    )
    assert (
        stdout.count("| bidirectional [privileged state] |") == 2
    )  # spatial and goal; not the upstream rows
    assert "| bidirectional |" in stdout


@pytest.mark.parametrize("command", [["report", "paper-table"], ["report", "html"]])
def test_paper_table_refuses_privileged_rows_beside_published_ones_without_the_flag(cli, tmp_path, command):
    run = write_run(tmp_path / "state", _libero_rows())
    out = tmp_path / "report"
    extra = ["--out", str(out)] if command[-1] == "html" else []
    code, stdout, stderr = cli(*command, str(run), *extra)
    assert code == 2 and not out.exists()
    assert "--allow-privileged" in stderr and "privileged state" in stderr and "obs=upstream" in stderr
    assert "libero/spatial:seeding=openvla" in stderr and len(stderr.strip().splitlines()) == 1
    assert "(published)" not in stdout
    code, stdout, _ = cli(*command, str(run), *extra, "--allow-privileged")
    assert code == 0
    text = (out / "paper-table.md").read_text() if extra else stdout
    assert "| fast_dvla [privileged state] |" in text and "Dream-VLA (published)" in text
    assert "were measured on object and fixture poses" in text


def test_paper_table_takes_upstream_observation_rows_without_the_flag(cli, tmp_path):
    run = write_run(tmp_path / "upstream", _libero_rows("obs=upstream,"))
    code, stdout, _ = cli("report", "paper-table", str(run))
    assert code == 0 and "Spatial (libero/spatial:obs=upstream,seeding=openvla)" in stdout
    assert "| fast_dvla |" in stdout and "privileged" not in stdout and "Dream-VLA (published)" in stdout


def test_step_budgets_warn_only_when_one_task_ran_under_two(tmp_path):
    per_task = episodes("bidirectional", BIDI, "bidi000001", [1, 0], task="a", max_steps=220)
    per_task += episodes("bidirectional", BIDI, "bidi000001", [1, 1], task="b", max_steps=300)
    (board,) = leaderboards([load_run(write_run(tmp_path / "r", per_task))])
    assert not any("step budgets" in w for w in board.warnings)  # the suite's own per-task budgets
    other = episodes("fast_dvla", FAST, "fast000001", [1, 0], task="a", max_steps=500)
    other += episodes("fast_dvla", FAST, "fast000001", [1, 1], task="b", max_steps=300)
    (board,) = leaderboards([load_run(write_run(tmp_path / "s", per_task + other))])
    assert "rows differ in step budgets for the same task (a: [220, 500])" in board.warnings
