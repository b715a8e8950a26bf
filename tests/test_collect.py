"""Demonstrations through the ordinary episode loop, on layouts disjoint from evaluation."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import numpy as np
import pyarrow.parquet as pq
import pytest

from adapters.registry import load_suite
from harness.collect import collect
from harness.errors import UsageError
from tests.fakes import ChunkPolicy, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def test_collect_keeps_successful_episodes_from_the_train_split(cli, tmp_path):
    out = tmp_path / "demos"
    code, stdout, _ = cli(
        "collect",
        "--suite",
        "metaworld/mt10",
        "--tasks",
        "reach-v3,drawer-close-v3",
        "--policy",
        "scripted",
        "--episodes-per-task",
        "2",
        "--out",
        str(out),
        "--quiet",
    )
    assert code == 0 and "2 / 2" in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["split"] == "train" and manifest["episodes_kept"] == {"reach-v3": 2, "drawer-close-v3": 2}
    assert manifest["observation_dim"] == 39 and manifest["action_dim"] == 4
    df = pq.read_table(out / "steps.parquet").to_pandas()
    assert df["episode_id"].nunique() == 4 and len(df) == manifest["steps"]
    assert (df.groupby("episode_id")["step"].min() == 0).all()
    actions = np.stack(df["action"].to_numpy())
    assert actions.min() >= -1.0 and actions.max() <= 1.0  # the expert's own go beyond; the env clips
    assert (np.abs(actions[:, :3]) == 1.0).any()  # saturated steps are kept at the bound
    eval_seeds = {t.episodes[0].seed for t in load_suite("metaworld/mt10").tasks}
    assert not set(df["seed"]) & eval_seeds  # never an evaluation layout
    assert not (tmp_path / "demos.tmp").exists()


def test_collect_refuses_to_overwrite_and_saves_nothing_without_successes(cli, tmp_path):
    out = tmp_path / "demos"
    args = [
        "collect",
        "--suite",
        "metaworld/mt1/reach-v3",
        "--episodes-per-task",
        "1",
        "--out",
        str(out),
        "--quiet",
    ]
    assert cli(*args, "--policy", "scripted")[0] == 0
    code, _, err = cli(*args, "--policy", "scripted")
    assert code == 2 and "pass --overwrite" in err
    empty = tmp_path / "none"
    code, _, err = cli(
        "collect",
        "--suite",
        "metaworld/mt1/pick-place-v3",
        "--episodes-per-task",
        "1",
        "--policy",
        "random",
        "--out",
        str(empty),
        "--quiet",
    )
    assert code == 2 and "no episode succeeded" in err and not empty.exists()


def test_collect_on_two_workers_writes_the_folder_one_worker_writes(cli, tmp_path):
    """Episodes are cut into ranges run by two processes and merged in the suite's order,
    with DART noise seeded per episode: the steps file is byte for byte the same."""
    args = ["collect", "--suite", "metaworld/mt10", "--tasks", "reach-v3,drawer-close-v3"]
    args += ["--policy", "scripted", "--episodes-per-task", "3", "--action-noise", "0.1", "--quiet"]
    assert cli(*args, "--out", str(tmp_path / "one"))[0] == 0
    code, _, err = cli(*args, "--workers", "2", "--out", str(tmp_path / "two"))
    assert code == 0, err
    one, two = (json.loads((tmp_path / d / "manifest.json").read_text()) for d in ("one", "two"))
    assert one["steps_sha256"] == two["steps_sha256"] and one["episodes_kept"] == two["episodes_kept"]
    assert (tmp_path / "one" / "steps.parquet").read_bytes() == (
        tmp_path / "two" / "steps.parquet"
    ).read_bytes()
    df = pq.read_table(tmp_path / "two" / "steps.parquet").to_pandas()
    assert list(df.drop_duplicates("episode_id")["task"]) == ["reach-v3"] * 3 + ["drawer-close-v3"] * 3
    code, _, err = cli(*args, "--workers", "0", "--out", str(tmp_path / "zero"))
    assert code == 2 and "--workers must be at least 1" in err and not (tmp_path / "zero").exists()


def test_a_collection_worker_refuses_a_checkpoint_swapped_after_the_parent_hashed_it(tmp_path):
    """Workers build their policy from the bytes the parent hashed, as run's workers do:
    a file that changed in between stops the collection instead of mixing two models."""
    import harness.collect_pool as hc
    from harness.config import CheckpointChanged

    swapped = tmp_path / "model.safetensors"
    swapped.write_bytes(b"another model")
    pins = (("bidirectional", str(swapped), "0" * 64),)
    with pytest.raises(CheckpointChanged, match="changed during the run") as refused:
        hc._worker_job(None, (0, 0, 1), 0.0, None, pins)
    assert hc._WORKER_RUN is None  # nothing was built from the swapped file
    # the advice is collect's own: it has no --resume to offer
    assert "collect again" in str(refused.value) and "--resume" not in str(refused.value)


class _KillsTheProcessThatUnpicklesIt:
    """A run config (the real one, to the parent) whose arrival in a worker ends that
    worker, as the out-of-memory killer or a crashing simulator would, before it has
    collected anything."""

    def __init__(self, config):
        self.config = config

    def __getattr__(self, name):
        return getattr(self.__dict__["config"], name)

    def __reduce__(self):
        from tests.fakes import suffer

        return (suffer, ("exit",))


def test_a_dead_collection_worker_stops_the_collection_in_one_line_and_writes_nothing(tmp_path):
    from harness.errors import HarnessError

    resolved = fake_resolved(ChunkPolicy(chunk=4), episodes=2, succeed_at=6)
    resolved.config = _KillsTheProcessThatUnpicklesIt(resolved.config)  # type: ignore[assignment]
    with pytest.raises(HarnessError, match="a collection worker process died") as died:
        collect(resolved, tmp_path / "demos", workers=2)
    assert "nothing was written" in str(died.value) and "\n" not in str(died.value)
    assert not (tmp_path / "demos").exists()


class SlowPolicy(ChunkPolicy):
    """Actions 0, 0.1, 0.2 ...: inside the action space, so noise is not clipped away."""

    def act(self, observations):
        batch = super().act(observations)
        batch.actions = batch.actions / 10
        return batch


def _noisy_collection(tmp_path, name, sigma):
    resolved = fake_resolved(SlowPolicy(chunk=4), episodes=2, succeed_at=6)
    make = resolved.suite.make_env

    def unit_env(task):  # a [-1, 1] space: the noise's scale is half its width
        env = make(task)
        env.action_space = gym.spaces.Box(-1.0, 1.0, (2,))
        return env

    resolved.suite = dataclasses.replace(resolved.suite, make_env=unit_env)
    collect(resolved, tmp_path / name, action_noise=sigma)
    executed = [np.stack(env.actions) for env in resolved.made_envs]  # type: ignore[attr-defined]
    df = pq.read_table(tmp_path / name / "steps.parquet").to_pandas()
    manifest = json.loads((tmp_path / name / "manifest.json").read_text())
    return np.concatenate(executed), np.stack(df["action"].to_numpy()), manifest


def test_dart_collection_records_the_demonstrators_action_and_executes_a_noisy_one(tmp_path):
    executed, recorded, manifest = _noisy_collection(tmp_path, "a", 0.2)
    assert manifest["action_noise"] == 0.2
    clean = np.tile(np.arange(6.0), 2) / 10
    assert np.allclose(recorded, clean[:, None])
    assert np.allclose(executed[:, 1], clean, rtol=0, atol=1e-6)  # the gripper (last dimension) is left alone
    noise = executed[:, 0] - clean
    assert (noise != 0).all() and np.abs(executed).max() <= 1.0
    assert not np.allclose(noise[:6], noise[6:])  # each episode draws its own noise
    again, _, _ = _noisy_collection(tmp_path, "b", 0.2)
    assert np.array_equal(again, executed)  # reproducible
    quiet, _, manifest = _noisy_collection(tmp_path, "c", 0.0)
    assert np.array_equal(quiet[:, 0], clean) and manifest["action_noise"] == 0.0


def test_action_noise_outside_zero_one_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(UsageError, match=r"--action-noise must be in \[0, 1\]"):
        collect(fake_resolved(ChunkPolicy()), tmp_path / "d", action_noise=1.5)
    assert not (tmp_path / "d").exists() and not (tmp_path / "d.tmp").exists()


def test_action_noise_on_discrete_actions_is_refused_and_the_env_closed(tmp_path):
    import gymnasium as gym

    resolved = fake_resolved(ChunkPolicy())
    make = resolved.suite.make_env

    def discrete(task):
        env = make(task)
        env.action_space = gym.spaces.Discrete(3)
        return env

    resolved.suite = dataclasses.replace(resolved.suite, make_env=discrete)
    with pytest.raises(UsageError, match=r"needs continuous \(Box\) actions"):
        collect(resolved, tmp_path / "d", action_noise=0.1)
    assert resolved.made_envs and all(env.closed for env in resolved.made_envs)
    assert not (tmp_path / "d").exists() and not (tmp_path / "d.tmp").exists()
