"""CALVIN-like instruction chains: the protocol, chain data, the instruction switch in
both episode loops, the chain columns, and (with the libero extra) the real scenes."""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from rich.console import Console

from adapters import chain_scenes as cs
from adapters import libero as lb
from adapters.base import EpisodeSpec
from harness.episode.nfe import NFECounter
from policies.base import ChunkBatch, EpisodeContext
from results import schema
from results.store import read_table, rows_to_table
from tests.fakes import context, run_batch, run_one

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "living_room_scene3"


def test_protocol_constants_are_calvins():
    assert cs.SUBTASKS_PER_CHAIN == 5  # CALVIN evaluate_policy.py: chains of 5
    assert cs.STEPS_PER_SUBTASK == 360  # CALVIN EP_LEN
    assert cs.CHAINS_PER_SCENE * len(cs.CALVIN_SCENES) == 1000  # CALVIN's NUM_SEQUENCES: chains/all
    assert set(cs.CALVIN_SCENES) < set(cs.scene_names())  # later scenes are suites of their own
    assert cs.INITIAL_STATES == lb.EPISODES_PER_TASK == 50  # chain j from LIBERO's initial state j % 50
    assert lb.SETTLE_STEPS == 10 and lb.ACTION_DIM == 7  # LIBERO's, once at the chain's start


# --- The instruction switch, on a physics-free chain env --------------------------------


class FakeChainEnv(gym.Env):
    """Three instructions; subtask k's goal holds after `every` steps in it."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,))
    action_space = gym.spaces.Box(-10.0, 10.0, (2,))  # RecordingPolicy's numbered actions lie inside
    INSTRUCTIONS = ("open the drawer", "push the block", "close the drawer")

    def __init__(self, every: int = 3):
        self.every, self.k, self.t = every, 0, 0
        self.actions: list[float] = []

    def _info(self):
        done = self.k == len(self.INSTRUCTIONS)
        records = [
            {"id": f"s{i}", "instruction": s, "success": i < self.k, "steps": self.every if i < self.k else 0}
            for i, s in enumerate(self.INSTRUCTIONS)
        ]
        return {
            "success": done,
            "instruction": self.INSTRUCTIONS[min(self.k, 2)],
            "subtask_index": min(self.k, 2),
            "subtasks_completed": self.k,
            "subtasks": records,
        }

    def reset(self, *, seed=None, options=None):
        self.k = self.t = 0
        return np.zeros(1), self._info()

    def step(self, action):
        self.actions.append(float(np.asarray(action)[0]))
        self.t += 1
        if self.t == self.every:
            self.k, self.t = self.k + 1, 0
        return np.zeros(1), 0.0, self.k == 3, False, self._info()


class RecordingPolicy:
    """Records every context it is reset with; chunks of 5 actions numbered per call."""

    def __init__(self):
        self.resets: list[EpisodeContext] = []
        self.calls = 0

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.resets.extend(episodes)

    def _chunk(self) -> np.ndarray:
        self.calls += 1
        return np.full((5, 2), float(self.calls))

    def act(self, observations):
        return ChunkBatch(actions=self._chunk()[None])

    def act_batch(self, episodes, observations):
        return ChunkBatch(actions=np.stack([self._chunk() for _ in observations]))


def test_every_instruction_reaches_the_policy_in_order_and_a_switch_drops_the_chunk():
    env, policy = FakeChainEnv(every=3), RecordingPolicy()
    spec = EpisodeSpec(index=0, chain=("s0", "s1", "s2"))
    out = run_one(env, policy, context(max_steps=100), spec)
    assert [(c.instruction, c.subtask_index) for c in policy.resets] == [
        ("open the drawer", 0),
        ("push the block", 1),
        ("close the drawer", 2),
    ]
    # 3 steps a subtask from 5-action chunks: the last 2 of each chunk are dropped.
    assert env.actions == [1, 1, 1, 2, 2, 2, 3, 3, 3]
    assert out.success and out.steps == 9 and out.chunks == 3
    assert out.subtasks_completed == 3 and [r["success"] for r in out.subtasks] == [True] * 3


def test_the_batched_loop_switches_instructions_per_episode():
    policy = RecordingPolicy()
    specs = [EpisodeSpec(index=i, chain=("s0", "s1", "s2")) for i in range(3)]
    envs = [FakeChainEnv(every=2 + i) for i in range(2)]
    counter = NFECounter()
    outcomes = dict(
        run_batch(
            specs, lambda: FakeChainEnv(), policy, lambda _s, _e: context(100), 2, envs=envs, counter=counter
        )
    )
    assert sorted(outcomes) == [0, 1, 2]
    assert all(o.success and o.subtasks_completed == 3 for o in outcomes.values())
    instructions = [c.instruction for c in policy.resets]
    assert len(instructions) == 9  # 3 episodes x 3 subtasks
    for k, text in enumerate(FakeChainEnv.INSTRUCTIONS):  # each episode saw them in order
        assert instructions.count(text) == 3 and all(
            c.subtask_index == k for c in policy.resets if c.instruction == text
        )


def test_a_single_instruction_env_never_resets_the_policy_twice():
    from tests.fakes import ChunkPolicy, CountdownEnv

    class Counting(ChunkPolicy):
        resets = 0

        def reset(self, episodes):
            Counting.resets += 1
            super().reset(episodes)

    out = run_one(CountdownEnv(succeed_at=12), Counting(), context(), EpisodeSpec(index=0))
    assert out.success and Counting.resets == 1 and out.subtasks is None


# --- Chain data: validation, the precondition model, the stored chains ------------------


def _scene_dir(tmp_path, monkeypatch, edit=None, chains=None):
    """A copy of the shipped scene data in tmp_path, optionally edited."""
    for path in cs.DATA.iterdir():
        shutil.copy(path, tmp_path / path.name)
    if edit is not None:
        path = tmp_path / f"{SCENE}.toml"
        path.write_text(edit(path.read_text()))
    if chains is not None:
        path = tmp_path / f"{SCENE}.chains.json"
        data = json.loads(path.read_text())
        data["chains"] = chains
        path.write_text(json.dumps(data))
    monkeypatch.setattr(cs, "DATA", tmp_path)
    if chains is not None:  # a deliberate edit, its hash recorded: the checks behind the hash see it
        cs.record_chains_hash(SCENE)
    cs.load_scene.cache_clear()
    cs.load_chains.cache_clear()


@pytest.fixture(autouse=True)
def _fresh_caches():
    yield
    cs.load_scene.cache_clear()
    cs.load_chains.cache_clear()


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda t: t.replace('"In", "butter_1"', '"Inside", "butter_1"'), "unknown predicate 'Inside'"),
        (
            lambda t: t.replace('["In", "butter_1", "wooden_tray_1_contain_region"]', '["In", "butter_1"]'),
            "takes 2",
        ),
        (lambda t: t.replace('id = "ketchup_in_tray"', 'id = "butter_in_tray"'), "ids repeat"),
        (lambda t: t.replace('\nsource = "libero_90"', '\nsource = "dreamt"', 1), "source"),
    ],
)
def test_a_bad_scene_file_names_the_problem(tmp_path, monkeypatch, edit, needle):
    _scene_dir(tmp_path, monkeypatch, edit=edit)
    with pytest.raises(cs.ChainDataError, match=needle):
        cs.load_scene(SCENE)


def test_the_precondition_model_refuses_chains_it_would_not_sample():
    scene = cs.load_scene(SCENE)
    start = frozenset(
        ("on", f"{o}_1", f"living_room_table_{o}_init_region")
        for o in ("alphabet_soup", "butter", "cream_cheese", "ketchup", "tomato_sauce")
    )
    ok = (
        "butter_in_tray",
        "ketchup_in_tray",
        "alphabet_soup_in_tray",
        "cream_cheese_in_tray",
        "tomato_sauce_in_tray",
    )
    cs.check_chain(scene, ok, start, "test")
    with pytest.raises(cs.ChainDataError, match="not eligible"):  # the butter is in the tray already
        cs.check_chain(scene, ("butter_in_tray", "butter_in_tray", *ok[2:]), start, "test")
    with pytest.raises(cs.ChainDataError, match="has no subtask 'fly'"):
        cs.check_chain(scene, ("fly", *ok[1:]), start, "test")
    with pytest.raises(cs.ChainDataError, match="a chain has 5"):
        cs.check_chain(scene, ok[:4], start, "test")
    chains = cs.sample_chains(scene, start, 20, seed=3)
    assert chains == cs.sample_chains(scene, start, 20, seed=3)  # deterministic for a seed
    for chain in chains:
        cs.check_chain(scene, chain, start, "sampled")


# --- The chain columns ------------------------------------------------------------------


def test_chain_columns_round_trip_and_version_1_tables_still_read(tmp_path):
    from tests.test_leaderboard import row as a_row  # one valid row of the episode table

    records = [{"id": "a", "instruction": "x", "success": True, "steps": 12}]
    row = {**a_row(), "chain_id": "scene/0", "subtasks_completed": 1, "subtasks": records}
    path = tmp_path / "v2.parquet"
    pq.write_table(rows_to_table([row]), path)
    back = read_table(path).to_pylist()[0]
    assert [{k: r[k] for k in records[0]} for r in back["subtasks"]] == records
    assert back["subtasks"][0]["outcome"] is None and back["subtasks_completed"] == 1  # not given: null
    # A version-1 file (no chain columns) reads with them null.
    old = rows_to_table([a_row()]).drop_columns(["chain_id", "subtasks_completed", "subtasks"])
    old = old.replace_schema_metadata({schema.SCHEMA_VERSION_KEY: b"1"})
    pq.write_table(old, tmp_path / "v1.parquet")
    table = read_table(tmp_path / "v1.parquet")
    assert table.column("subtasks").null_count == 1 and table.column("chain_id").null_count == 1
    future = old.replace_schema_metadata({schema.SCHEMA_VERSION_KEY: b"9"})
    pq.write_table(future, tmp_path / "v9.parquet")
    with pytest.raises(Exception, match="reads versions 1, 2"):
        read_table(tmp_path / "v9.parquet")
    assert schema.SCHEMA_VERSION == "5" and isinstance(
        schema.arrow_schema().field("subtasks").type, pa.ListType
    )


# --- The real scene (libero extra) --------------------------------------------------------


@needs_libero
def test_the_suite_is_the_stored_chains_from_the_scene_tasks_initial_states():
    from adapters import chains

    suite = chains.load_suite(f"chains/{SCENE}")
    (task,) = suite.tasks
    stored = cs.load_chains(SCENE)
    assert [e.chain for e in task.episodes] == list(stored.chains) and len(stored.chains) == 200
    assert [e.init_state_id for e in task.episodes] == [j % 50 for j in range(200)]
    assert task.max_steps == 5 * 360 and suite.name == f"chains/{SCENE}:seeding=openvla"
    # The stored chains are what their recorded command samples.
    scene = cs.load_scene(SCENE)
    start = cs.initial_state(cs.scene_problem(scene))
    assert cs.sample_chains(scene, start, len(stored.chains), stored.seed, cs.INITIAL_STATES) == list(
        stored.chains
    )
    assert [s.name for s in chains.load_suite("chains/all").tasks] == list(cs.CALVIN_SCENES)


@needs_libero
def test_chain_goals_agree_with_liberos_own_success_check():
    """The scene is built from LIBERO-90's butter task, so LIBERO's `_check_success` is the
    butter_in_tray goal: the chain env's predicate must agree with it on every state."""
    from adapters import chains
    from policies.experts.libero_scripted import LiberoScripted, LiberoScriptedParams

    suite = chains.load_suite(f"chains/{SCENE}")
    task = suite.tasks[0]
    env = suite.make_env(task)
    chain = (
        "butter_in_tray",
        "ketchup_in_tray",
        "alphabet_soup_in_tray",
        "cream_cheese_in_tray",
        "tomato_sauce_in_tray",
    )
    spec = EpisodeSpec(index=0, seed=0, init_state_id=0, chain=chain)
    try:
        obs, info = env.reset(options={"episode": spec})
        assert (
            info["instruction"] == "pick up the butter and put it in the tray" and info["subtask_index"] == 0
        )
        assert env.inner.libero.env.horizon >= lb.SETTLE_STEPS + 5 * 360  # robosuite must not stop a chain
        ctx = EpisodeContext(
            suite.name, task.name, info["instruction"], env.action_space, env.observation_space, 360, 0
        )
        expert = LiberoScripted(LiberoScriptedParams())
        expert.reset([ctx])
        agreed = []
        for _ in range(360):
            obs, _, _, _, info = env.step(expert.act([obs]).actions[0, 0])
            libero_says = bool(env.inner.libero.env._check_success())
            agreed.append(libero_says == env.holds(("in", "butter_1", "wooden_tray_1_contain_region")))
            if info["subtask_index"] == 1:
                assert libero_says  # the switch happened on LIBERO's own success
                break
        assert all(agreed) and info["subtasks_completed"] == 1
        assert info["instruction"] == "pick up the ketchup and put it in the tray"
    finally:
        env.close()


@needs_libero
def test_the_expert_completes_a_chain_and_resume_extends_the_run(cli, tmp_path):
    from results.store import RunDir

    out = tmp_path / "chain"
    args = ("run", "--suite", f"chains/{SCENE}", "--policy", "libero_scripted", "--out", str(out), "--quiet")
    code, _, err = cli(*args, "--episodes-per-task", "1")
    assert code == 0, err
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "2", "--quiet")
    assert code == 0, err
    df = RunDir(out).read_episodes().sort_values("episode_index")
    assert list(df["chain_id"]) == [f"{SCENE}/0", f"{SCENE}/1"]
    first = df.iloc[0]
    # both complete (revision 4's free spot in the tray: revision 3 put chain 1's fifth can
    # on top of the other four, above the contain region, and timed out)
    assert df["success"].all() and list(df["subtasks_completed"]) == [5, 5]
    stored = cs.load_chains(SCENE).chains[0]
    assert [r["id"] for r in first["subtasks"]] == list(stored)
    assert first["instruction"].split(" | ")[0] == cs.load_scene(SCENE).subtask(stored[0]).instruction
    assert sum(r["steps"] for r in first["subtasks"]) == first["steps"]
    assert all(0 < r["steps"] <= 360 for r in first["subtasks"])


@pytest.mark.parametrize(
    ("suite", "chains", "needle"),
    [
        ("chains/nope", None, "chain suites: chains/"),
        (f"chains/{SCENE}", [["fly", "b", "c", "d", "e"]], "has no subtask 'fly'"),
        (f"chains/{SCENE}", [["butter_in_tray"] * 5], "its goal already holds"),
    ],
)
def test_bad_chain_input_exits_2_and_writes_nothing(cli, tmp_path, monkeypatch, suite, chains, needle):
    if chains is not None:
        if not lb.installed():
            pytest.skip("needs the libero extra")
        (tmp_path / "data").mkdir()
        _scene_dir(tmp_path / "data", monkeypatch, chains=chains)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", suite, "--policy", "libero_scripted", "--episodes-per-task", "1", "--out", str(out)
    )
    assert code == 2
    assert needle in err
    assert not out.exists()


def test_the_calvin_table_from_hand_made_rows():
    from results.chain_table import chain_summary, chain_table, length_interval

    def rows(policy, lengths, tokens):
        return [
            {
                "policy_config_id": policy,
                "policy": policy,
                "subtasks_completed": n,
                "nfe_per_chunk": 12.0,
                "tokens_per_s": tokens,
                "started_at": i,
            }
            for i, n in enumerate(lengths)
        ]

    lengths = [5, 5, 3, 0, 1, 5, 2, 4, 5, 0]  # reach 1/5: 8 of 10; 5/5: 4 of 10
    df = pd.DataFrame(rows("bidirectional", lengths, 100.0) + rows("fast_dvla", [5] * 4, 250.0))
    summary = chain_summary(df).set_index("policy")
    bidi = summary.loc["bidirectional"]
    assert [bidi[f"reach_{k}"] for k in range(1, 6)] == [0.8, 0.7, 0.6, 0.5, 0.4]
    assert bidi["avg_len"] == pytest.approx(3.0) and bidi["chains"] == 10
    low, high = bidi["reach_5_low"], bidi["reach_5_high"]
    assert low == pytest.approx(0.1682, abs=1e-3) and high == pytest.approx(0.6873, abs=1e-3)  # Wilson 4/10
    assert (
        bidi["avg_len_low"] < 3.0 < bidi["avg_len_high"]
        and 0 <= bidi["avg_len_low"]
        and bidi["avg_len_high"] <= 5
    )
    assert length_interval(np.array([5.0] * 4)) == (5.0, 5.0)
    assert summary.loc["fast_dvla", "reach_5"] == 1.0
    console = Console(width=200, record=True)
    console.print(chain_table(chain_summary(df)))
    text = console.export_text()
    assert "40.0 [17, 69]" in text and "3.00 [" in text and "2.50x" in text
    labelled = Console(width=200, record=True)
    labelled.print(chain_table(chain_summary(df), labels={"fast_dvla": "fast_dvla (tau_conf=0.5)"}))
    assert "fast_dvla (tau_conf=0.5)" in labelled.export_text()  # the name the summary table prints


def test_listing_chain_suites_never_imports_the_simulator():
    import subprocess
    import sys

    code = (
        "import sys\nfrom adapters.registry import list_suites\n"
        "names = [s.name for s in list_suites()]\n"
        "assert 'chains/all' in names and 'chains/libero_goal' in names, names\n"
        "assert not any(m.startswith(('libero', 'robosuite', 'mujoco')) for m in sys.modules)\nprint('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert out.stdout.strip() == "ok", out.stderr


@needs_libero
def test_collect_records_the_instruction_in_force_at_every_step(cli, tmp_path):
    out = tmp_path / "demos"
    args = (
        "collect",
        "--suite",
        f"chains/{SCENE}",
        "--policy",
        "libero_scripted",
        "--episodes-per-task",
        "1",
    )
    code, _, err = cli(*args, "--out", str(out), "--quiet")
    assert code == 0, err
    steps = pq.read_table(out / "steps.parquet").to_pandas()
    from adapters import chains

    # the train split: fresh starts held out from the evaluation's, chains of its own
    train = chains.load_suite(f"chains/{SCENE}", "train").tasks[0]
    scene, chain = cs.load_scene(SCENE), train.episodes[0].chain
    assert train.episodes[0].init_state_id is None and train.episodes[0].seed is not None
    in_order = list(dict.fromkeys(steps["instruction"]))  # distinct, in order of first step
    manifest = json.loads((out / "manifest.json").read_text())
    completed = manifest["subtasks_kept"][SCENE]  # a failed chain keeps its completed subtasks
    assert completed >= 1 and manifest["episodes_kept"][SCENE] == 1
    assert in_order == [scene.subtask(i).instruction for i in chain][:completed]
    assert steps["instruction"].is_monotonic_increasing is False  # not one label for the episode
    assert (steps.groupby("instruction", sort=False).size() > 10).all()


def test_a_failed_chain_keeps_the_steps_of_its_completed_subtasks_only():
    from datetime import UTC, datetime
    from types import SimpleNamespace

    from harness.collect import _kept_steps
    from harness.episode.outcome import EpisodeOutcome

    def outcome(completed: int, steps: list[int], success: bool = False) -> EpisodeOutcome:
        records = [
            {"id": f"s{k}", "instruction": f"do {k}", "success": k < completed, "steps": n}
            for k, n in enumerate(steps)
        ]
        return EpisodeOutcome(
            success, sum(steps), 1, 1, 1, 0.0, 0.0, 0.0, datetime.now(UTC),
            subtasks=records, subtasks_completed=completed,
        )  # fmt: skip

    labels = ["do 0"] * 3 + ["do 1"] * 4 + ["do 2"] * 360  # the third subtask ran out of steps
    env = SimpleNamespace(instructions=labels, actions=[0] * len(labels))
    assert _kept_steps(outcome(2, [3, 4, 360, 0, 0]), env) == 7
    assert _kept_steps(outcome(0, [360, 0, 0, 0, 0]), env) == 0
    shifted = SimpleNamespace(instructions=["do 0"] * 4 + labels[4:], actions=env.actions)
    with pytest.raises(RuntimeError, match="do not line up"):
        _kept_steps(outcome(2, [3, 4, 360, 0, 0]), shifted)
    plain = EpisodeOutcome(True, 5, 1, 1, 1, 0.0, 0.0, 0.0, datetime.now(UTC))
    assert _kept_steps(plain, SimpleNamespace(instructions=[None] * 5, actions=[0] * 5)) == 5
    assert _kept_steps(dataclasses.replace(plain, success=False), env) == 0
