"""Meta-World through the real simulator: the scripted expert, the table, determinism,
and the two layout modes (fixed; upstream, checked against Meta-World's own evaluation)."""

from __future__ import annotations

import pickle

import numpy as np
import pyarrow.parquet as pq
import pytest

from adapters import metaworld as mw
from adapters.registry import load_suite
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS, arrow_schema
from results.store import RunDir

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

NOT_RESULTS = sorted(TIMING_COLUMNS | PROVENANCE_COLUMNS)


def test_task_lists_match_the_installed_metaworld():
    import metaworld.env_dict as env_dict

    assert list(mw.MT10) == list(env_dict.MT10_V3)
    assert set(mw.MT50) == set(env_dict.ALL_V3_ENVIRONMENTS)


def test_episode_specs_are_fixed_and_shared_across_suites():
    mt10, mt1 = load_suite("metaworld/mt10"), load_suite("metaworld/mt1/reach-v3")
    assert mt10.task("reach-v3").episodes == mt1.task("reach-v3").episodes
    specs = mt10.task("push-v3").episodes
    assert len(specs) == 50 and [s.init_state_id for s in specs] == list(range(50))
    assert mt10.task("push-v3").episodes[0].seed != mt10.task("reach-v3").episodes[0].seed


def test_train_split_offers_new_layouts_beyond_the_first_50():
    train = load_suite("metaworld/mt1/reach-v3", "train").tasks[0].episodes
    evaluation = load_suite("metaworld/mt1/reach-v3").tasks[0].episodes
    assert len(evaluation) == 50 and len(train) == mw.LAYOUTS_PER_TASK * mw.TRAIN_LAYOUT_SETS
    # set 0 is the train split's original seed (earlier demonstrations stay reproducible)
    assert {s.seed for s in train[:50]} == {mw.derive_seed("metaworld", "train", "reach-v3")}
    assert [s.init_state_id for s in train[50:100]] == list(range(50))
    assert len({s.seed for s in train}) == mw.TRAIN_LAYOUT_SETS
    assert not {s.seed for s in train} & {s.seed for s in evaluation}
    env = load_suite("metaworld/mt1/reach-v3").make_env(load_suite("metaworld/mt1/reach-v3").tasks[0])
    goals = set()
    for spec in (train[0], train[50], train[100], evaluation[0]):
        obs, _ = env.reset(options={"episode": spec})
        goals.add(tuple(round(float(x), 6) for x in obs[-3:]))
    env.close()
    assert len(goals) == 4  # four different goal positions


def _layout_vectors(tasks) -> set[tuple[float, ...]]:
    """A layout's identity: the random vector Meta-World drew for it (goal and object places)."""
    return {tuple(pickle.loads(t.data)["rand_vec"].tolist()) for t in tasks}


def test_train_layouts_are_disjoint_from_evaluation_in_both_modes():
    """Demonstrations (train split) never start from an evaluation layout, fixed or upstream.

    reach-v3 is MT10's and the check's hard case: a benchmark's first task draws its
    layouts from a freshly seeded stream, as each train set does, so upstream mode could
    equal a train set exactly; the suite refuses those seeds. Later tasks draw from the
    middle of the benchmark's stream."""
    import metaworld

    task = "reach-v3"
    train = load_suite(f"metaworld/mt1/{task}", "train").tasks[0].episodes
    train_seeds = sorted({s.seed for s in train})
    assert len(train_seeds) == mw.TRAIN_LAYOUT_SETS
    fixed_seed = load_suite(f"metaworld/mt1/{task}").tasks[0].episodes[0].seed
    upstream = load_suite(f"metaworld/mt1/{task}:layouts=upstream").tasks[0].episodes
    assert fixed_seed not in train_seeds and mw.DEFAULT_UPSTREAM_SEED not in train_seeds
    # the layouts themselves: the first and last train sets against both evaluation sets
    sets = {
        "train set 0": _layout_vectors(metaworld.MT1(task, seed=train_seeds[0]).train_tasks),
        "train set 19": _layout_vectors(metaworld.MT1(task, seed=train_seeds[-1]).train_tasks),
        "fixed": _layout_vectors(metaworld.MT1(task, seed=fixed_seed).train_tasks),
        "upstream": _layout_vectors(metaworld.MT1(task, seed=upstream[0].seed).train_tasks),
    }
    assert all(len(v) == 50 for v in sets.values())
    names = list(sets)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not sets[a] & sets[b], (a, b)
    # a train seed as the upstream seed would BE the train layouts: refused, for mt1 and mt10
    for suite in (f"metaworld/mt1/{task}", "metaworld/mt10"):
        with pytest.raises(mw.SuiteOptionError, match="train split's layout seed"):
            load_suite(f"{suite}:layouts=upstream,seed={train_seeds[3]}")
    # an upstream suite's own train split is the fixed mode's (disjoint as above)
    up_train = load_suite("metaworld/mt10:layouts=upstream", "train")
    assert [t.episodes for t in up_train.tasks] == [
        t.episodes for t in load_suite("metaworld/mt10", "train").tasks
    ]


def test_every_mt10_task_trains_on_layouts_evaluation_never_uses():
    """The layouts the 50-per-task demonstrations start from (train set 0) against the
    evaluation's, for all ten MT10 tasks: no layout is shared. Disjoint is not far apart:
    where Meta-World randomises one coordinate (drawer-open, drawer-close, window-close)
    the nearest train layout is within 0.1 mm of an evaluation one (docs/demonstrations.md);
    where it randomises five (reach, push, pick-place, peg-insert) it is over 2 mm away."""
    import metaworld

    evaluation = load_suite("metaworld/mt10")
    train = load_suite("metaworld/mt10", "train")
    for ev, tr in zip(evaluation.tasks, train.tasks, strict=True):
        assert ev.name == tr.name
        eval_layouts = _layout_vectors(metaworld.MT1(ev.name, seed=ev.episodes[0].seed).train_tasks)
        train_layouts = _layout_vectors(metaworld.MT1(tr.name, seed=tr.episodes[0].seed).train_tasks)
        assert len(eval_layouts) == len(train_layouts) == 50
        assert not eval_layouts & train_layouts, ev.name
        gaps = np.abs(np.array(sorted(eval_layouts))[:, None] - np.array(sorted(train_layouts))[None]).max(
            axis=2
        )
        assert gaps.min() > 0, ev.name
        if ev.name in ("reach-v3", "push-v3", "pick-place-v3", "peg-insert-side-v3"):
            assert gaps.min() > 2e-3, (ev.name, gaps.min())


def test_layout_options_parse_and_name_the_suite():
    fixed = load_suite("metaworld/mt10:layouts=fixed")
    assert fixed.name == "metaworld/mt10"
    assert [t.episodes for t in fixed.tasks] == [t.episodes for t in load_suite("metaworld/mt10").tasks]
    up = load_suite("metaworld/mt10:layouts=upstream")
    assert up.name == f"metaworld/mt10:layouts=upstream,seed={mw.DEFAULT_UPSTREAM_SEED}"
    assert load_suite("metaworld/mt1/push-v3:seed=42,layouts=upstream").name == (
        "metaworld/mt1/push-v3:layouts=upstream,seed=42"
    )
    picks = mw.upstream_layout_ids(mw.DEFAULT_UPSTREAM_SEED)
    for task in up.tasks:  # every task of a benchmark: its env seeded with the same seed
        assert [s.init_state_id for s in task.episodes] == list(picks)
        assert {s.seed for s in task.episodes} == {mw.DEFAULT_UPSTREAM_SEED}
        assert [s.index for s in task.episodes] == list(range(mw.UPSTREAM_EPISODES))
    assert len(set(picks)) < len(picks)  # with replacement: some layouts twice, some never
    for bad in ("seed=3", "layouts=fixed,seed=3", "layouts=random", "seed=-1", "layout=upstream", "upstream"):
        with pytest.raises(mw.SuiteOptionError):
            load_suite(f"metaworld/mt10:{bad}")


def test_upstream_mode_gives_metaworlds_own_layouts_for_every_mt10_task():
    """Episode j of each task starts where Meta-World's own `evaluation` starts that task's
    j-th episode on `gym.make_vec("Meta-World/MT10", seed=S)`: same layout, same observation.

    One-step episodes (`max_episode_steps=1`) make the upstream loop cheap: every call of
    the agent then sees a new episode's first observation, right after the env's reset."""
    import gymnasium as gym
    from metaworld.evaluation import evaluation

    seed, episodes = mw.DEFAULT_UPSTREAM_SEED, 10
    envs = gym.make_vec("Meta-World/MT10", vector_strategy="sync", seed=seed, max_episode_steps=1)

    class Recorder:  # metaworld.evaluation.Agent
        def __init__(self):
            self.starts = []  # per call: (observations, each env's layout vector)

        def reset(self, env_mask):
            pass

        def eval_action(self, observations):
            self.starts.append((observations.copy(), [np.array(v) for v in envs.get_attr("_last_rand_vec")]))
            return np.zeros((envs.num_envs, 4))

    agent = Recorder()
    evaluation(agent, envs, num_episodes=episodes)
    envs.close()
    assert len(agent.starts) >= episodes

    suite = load_suite(f"metaworld/mt10:layouts=upstream,seed={seed}")
    assert [t.name for t in suite.tasks] == list(mw.MT10)  # MT10_V3's order, the vector env's
    for i, task in enumerate(suite.tasks):
        env = suite.make_env(task)
        for j in range(episodes):
            obs, _ = env.reset(options={"episode": task.episodes[j]})
            upstream_obs, upstream_layouts = agent.starts[j]
            assert np.array_equal(env.unwrapped._last_rand_vec, upstream_layouts[i]), (task.name, j)
            assert np.array_equal(obs, upstream_obs[i]), (task.name, j)
        env.close()


def test_upstream_episode_alone_equals_episode_in_sequence():
    """Meta-World's MT1 env reset after reset (its shared generator) against our episodes
    run alone, in reverse order, each on a fresh env."""
    import gymnasium as gym

    seed, episodes = 7, 8
    upstream = gym.make("Meta-World/MT1", env_name="push-v3", seed=seed, disable_env_checker=True)
    in_sequence = [upstream.reset()[0] for _ in range(episodes)]
    upstream.close()
    suite = load_suite(f"metaworld/mt1/push-v3:layouts=upstream,seed={seed}")
    task = suite.tasks[0]
    for j in reversed(range(episodes)):
        env = suite.make_env(task)
        alone, _ = env.reset(options={"episode": task.episodes[j]})
        env.close()
        assert np.array_equal(alone, in_sequence[j]), j


def test_same_episode_spec_gives_the_same_start():
    suite = load_suite("metaworld/mt1/pick-place-v3")
    task = suite.tasks[0]
    env = suite.make_env(task)
    first, _ = env.reset(options={"episode": task.episodes[3]})
    env.reset(options={"episode": task.episodes[4]})
    again, _ = env.reset(options={"episode": task.episodes[3]})
    assert (first == again).all()
    other, _ = env.reset(options={"episode": task.episodes[4]})
    assert not (first == other).all()


def test_scripted_expert_succeeds_and_rows_match_the_schema(cli, tmp_path):
    out = tmp_path / "demo"
    code, stdout, _ = cli(
        "run",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        "reach-v3,4",
        "--policy",
        "scripted",
        "--episodes-per-task",
        "3",
        "--out",
        str(out),
        "--quiet",
    )
    assert code == 0
    assert "ALL" in stdout and "Wilson" in stdout
    table = pq.read_table(out / "episodes.parquet")
    expected = arrow_schema()
    for field in expected:
        assert table.schema.field(field.name).type == field.type, field.name
    assert table.schema.metadata[b"dvla_harness.schema_version"] == b"5"  # + the out-of-space columns
    df = RunDir(out).read_episodes()
    assert len(df) == 6
    assert set(df["task"]) == {"reach-v3", "drawer-open-v3"}
    assert df["success"].all() and df["failure_reason"].isna().all()
    assert (df["nfe_total"] == 0).all() and (df["steps"] < 500).all()


def test_two_runs_give_identical_rows_apart_from_timing(cli, tmp_path):
    args = [
        "run",
        "--suite",
        "metaworld/mt1/push-v3",
        "--policy",
        "scripted:action_noise=0.3",
        "--policy",
        "random",
        "--episodes-per-task",
        "2",
        "--quiet",
    ]
    assert cli(*args, "--out", str(tmp_path / "a"))[0] == 0
    assert cli(*args, "--out", str(tmp_path / "b"))[0] == 0
    a = RunDir(tmp_path / "a").read_episodes().drop(columns=NOT_RESULTS)
    b = RunDir(tmp_path / "b").read_episodes().drop(columns=NOT_RESULTS)
    assert len(a) == 4
    assert a.equals(b)


def test_manifest_records_config_and_provenance(cli, tmp_path):
    import json

    out = tmp_path / "run"
    assert (
        cli(
            "run",
            "--suite",
            "metaworld/mt1/reach-v3",
            "--policy",
            "scripted",
            "--episodes-per-task",
            "1",
            "--out",
            str(out),
            "--quiet",
        )[0]
        == 0
    )
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["suite"] == "metaworld/mt1/reach-v3"
    assert manifest["config"]["policies"] == [{"name": "scripted", "params": {}}]
    assert manifest["policies"][0]["params"] == '{"action_noise":0.0,"seed":0}'
    env = manifest["environment"]
    for package in ("numpy", "torch", "gymnasium", "mujoco", "pandas", "pyarrow"):
        assert env["packages"][package], package
    assert env["simulators"]["metaworld"] == "3.1.1"
    assert manifest["suite"]["simulator_packages"]["mujoco"] == env["packages"]["mujoco"]
    assert manifest["suite"]["render_backend"].startswith("none")
    assert env["cpu"] and env["python"] and env["platform"]
    assert manifest["started_at"] <= manifest["finished_at"] and manifest["status"] == "finished"


def test_rows_and_manifest_record_the_layout_mode_and_seed(cli, tmp_path):
    import json

    out = tmp_path / "up"
    suite = "metaworld/mt1/reach-v3:layouts=upstream,seed=3"
    args = ["run", "--suite", suite, "--policy", "scripted", "--episodes-per-task", "2", "--quiet"]
    assert cli(*args, "--out", str(out))[0] == 0
    df = RunDir(out).read_episodes()
    assert set(df["suite"]) == {suite} and set(df["seed"]) == {3}
    assert list(df.sort_values("episode_index")["init_state_id"]) == list(mw.upstream_layout_ids(3)[:2])
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"]["name"] == suite and manifest["config"]["suite"] == suite
