"""Fresh LIBERO initial states for demonstrations: drawn, deterministic, disjoint from evaluation."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from adapters import libero as lb
from adapters import libero_states

pytestmark = pytest.mark.libero
needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
TASK = 3  # spatial: a bowl, a plate, a ramekin, cookies, a cabinet and a stove


@pytest.fixture(scope="module")
def fresh_env():
    suite = lb.load_suite("libero/spatial", "train")
    task = suite.tasks[TASK]
    env = suite.make_env(task)
    yield task, env
    env.close()


def _start(env, spec) -> tuple[str, np.ndarray]:
    """The restored initial state's hash, and the state itself, of one episode."""
    _, info = env.reset(seed=spec.seed, options={"episode": spec})
    state = libero_states.sample_state(env._resets, spec.seed)  # drawn again: the same
    return info["initial_state_sha256"], state


def test_options_name_the_initial_states_and_the_split_picks_them():
    train, evaluation = lb.resolve_initial_states, lb.parse_options
    assert train(evaluation(""), "train").suffix() == ":seeding=openvla,initial_states=fresh,states_seed=0"
    assert train(evaluation(""), "eval").suffix() == ":seeding=openvla"  # the protocol's states
    explicit = train(evaluation("initial_states=evaluation"), "train")
    assert explicit.initial_states == "evaluation" and explicit.states_seed is None
    assert train(evaluation("initial_states=fresh,states_seed=4"), "eval").states_seed == 4
    with pytest.raises(lb.SuiteOptionError, match="states_seed needs initial_states=fresh"):
        train(evaluation("states_seed=4"), "eval")
    with pytest.raises(lb.SuiteOptionError, match="choose evaluation or fresh"):
        evaluation("initial_states=random")


@needs_libero
def test_fresh_states_are_deterministic_per_seed_and_differ_between_seeds(fresh_env):
    task, env = fresh_env
    first, second = task.episodes[:2]
    assert first.init_state_id is None and first.seed == libero_states.fresh_seed(0, task.name, 0)
    a, state_a = _start(env, first)
    b, _ = _start(env, second)
    again, state_again = _start(env, first)  # after another draw: the seed alone decides
    assert a == again and np.array_equal(state_a, state_again)
    assert a != b
    other = lb.load_suite("libero/spatial:states_seed=1", "train").tasks[TASK].episodes[0]
    assert other.seed != first.seed and _start(env, other)[0] not in (a, b)
    assert a == libero_states.state_sha256(state_a)  # the hash is of the restored state


@needs_libero
def test_fresh_states_are_disjoint_from_every_evaluation_state(fresh_env):
    task, env = fresh_env
    evaluation = np.asarray(env.init_states, dtype=np.float64)
    assert evaluation.shape[0] == 50
    slices = libero_states.object_position_slices(env.libero.env.sim.model)
    assert len(slices) == 5  # the task's five loose objects
    for spec in task.episodes[:8]:
        digest, state = _start(env, spec)
        assert state.shape == evaluation.shape[1:]
        assert digest not in {libero_states.state_sha256(s) for s in evaluation}
        assert not (evaluation == state).all(axis=1).any()
        # objects stand elsewhere, not just a velocity or a clock apart
        gaps = np.linalg.norm(
            libero_states.object_positions(evaluation, slices)
            - libero_states.object_positions(state, slices),
            axis=2,
        ).max(axis=1)
        assert gaps.min() > 1e-3, gaps.min()
        _, info = env.reset(seed=spec.seed, options={"episode": spec})
        assert info["initial_state_distance"] == pytest.approx(gaps.min())


@needs_libero
def test_collect_records_fresh_states_and_refuses_an_evaluation_state(cli, tmp_path, monkeypatch):
    out = tmp_path / "demos"
    args = ["collect", "--suite", "libero/spatial", "--tasks", str(TASK), "--policy", "libero_scripted"]
    code, stdout, err = cli(*args, "--episodes-per-task", "1", "--out", str(out), "--quiet")
    assert code == 0, err
    assert "fresh draws" in stdout and "none equals an evaluation state" in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["suite"] == "libero/spatial:seeding=openvla,initial_states=fresh,states_seed=0"
    rows = pq.read_table(out / "steps.parquet").to_pandas()
    assert rows["init_state_id"].isna().all() and rows["initial_state_sha256"].nunique() == 1
    suite = lb.load_suite("libero/spatial", "train")
    env = suite.make_env(suite.tasks[TASK])
    try:
        digest, _ = _start(env, suite.tasks[TASK].episodes[0])
        evaluation = env.init_states
    finally:
        env.close()
    assert rows["initial_state_sha256"][0] == digest
    (record,) = manifest["initial_states"].values()
    assert record["fresh"] == 1 and record["evaluation_overlap"] == 0
    assert record["closest_to_evaluation_m"] == pytest.approx(rows["initial_state_distance"][0])
    assert record["closest_to_evaluation_m"] > 1e-3

    # a sampler that returns an evaluation state is refused: exit 2, nothing written
    monkeypatch.setattr(libero_states, "sample_state", lambda resets, seed: np.array(evaluation[7]))
    refused = tmp_path / "refused"
    code, _, err = cli(*args, "--episodes-per-task", "1", "--out", str(refused), "--quiet")
    assert code == 2 and "equals evaluation initial state 7" in err, err
    assert not refused.exists() and not refused.with_name("refused.tmp").exists()
