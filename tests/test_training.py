"""Training: every recipe learns, runs are deterministic, checkpoints load as policies."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch

from harness.commands.train import trained_on
from policies.dvla.checkpoint import load
from policies.dvla.losses import block_ratios
from policies.dvla.recipes import NOISE_SCHEDULES, TrainConfig
from policies.dvla.training import train
from results.store import RunDir
from tests.fakes import TINY_TRAIN

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

TINY = TINY_TRAIN


def _mean(xs):
    return sum(xs) / len(xs)


@pytest.mark.parametrize("recipe", ["bidirectional", "autoregressive", "block_diffusion"])
def test_each_recipe_lowers_its_loss(demos, tmp_path, recipe):
    report = train(TrainConfig(recipe=recipe, **TINY), demos, tmp_path / "m.safetensors")
    assert _mean(report.losses[-5:]) < 0.8 * _mean(report.losses[:5])
    ckpt = load(tmp_path / "m.safetensors")
    assert ckpt.meta["recipe"] == recipe and ckpt.meta["data_sha256"]
    assert ckpt.meta["train_config"]["device"] == "cpu"  # the default, recorded
    # what it was trained on, per folder: a Meta-World train split, no fresh LIBERO states
    (source,) = ckpt.meta["data_sources"]
    assert source["suite"].startswith("metaworld/") and source["split"] == "train"
    assert source["steps_sha256"] == ckpt.meta["data_sha256"] and not source["fresh_initial_states"]
    assert trained_on(ckpt.meta).endswith("train split (held-out starts)")
    assert "evaluation's own starts" in trained_on({"data_sources": [{**source, "split": "eval"}]})
    libero = {"suite": "libero/spatial", "split": "train", "fresh_initial_states": False}
    assert "evaluation's own starts" in trained_on({"data_sources": [libero]})
    assert "held-out" in trained_on({"data_sources": [{**libero, "fresh_initial_states": True}]})
    assert 0 < ckpt.meta["tokenizer_round_trip_error"] < 2 / 63  # under one bin of the 64 here
    header = json.loads((tmp_path / "m.json").read_text())
    assert (
        header["model"]["pattern"]
        == {"bidirectional": "bidirectional", "autoregressive": "causal", "block_diffusion": "block_causal"}[
            recipe
        ]
    )
    assert (tmp_path / "m.loss.csv").read_text().count("\n") == TINY["steps"] + 1
    assert (tmp_path / "m.loss.png").stat().st_size > 1000


def test_training_is_deterministic_given_a_seed(demos, tmp_path):
    cfg = TrainConfig(recipe="block_diffusion", **{**TINY, "steps": 8})
    a = train(cfg, demos, tmp_path / "a.safetensors").losses
    b = train(cfg, demos, tmp_path / "b.safetensors").losses
    assert a == b
    wa, wb = (
        load(tmp_path / "a.safetensors").model.state_dict(),
        load(tmp_path / "b.safetensors").model.state_dict(),
    )
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_distilled_student_runs_as_fast_dvla(demos, tmp_path, cli):
    teacher = tmp_path / "teacher.safetensors"
    train(TrainConfig(recipe="bidirectional", **TINY), demos, teacher)
    report = train(
        TrainConfig(recipe="distill", teacher=str(teacher), **TINY), demos, tmp_path / "s.safetensors"
    )
    assert _mean(report.losses[-5:]) < _mean(report.losses[:5])
    student = load(tmp_path / "s.safetensors")
    assert student.model.cfg.pattern == "block_causal" and student.vocab == load(teacher).vocab
    code, _, err = cli(
        "run",
        "--suite",
        "metaworld/mt1/reach-v3",
        "--episodes-per-task",
        "1",
        "--quiet",
        "--policy",
        f"fast_dvla:checkpoint={tmp_path / 's.safetensors'}",
        "--out",
        str(tmp_path / "r"),
    )
    assert code == 0, err
    row = RunDir(tmp_path / "r").read_episodes().iloc[0]
    assert row["policy"] == "fast_dvla" and row["chunks"] > 0 and row["nfe_total"] >= row["chunks"]


@pytest.mark.parametrize("schedule", [s for s in NOISE_SCHEDULES if s != "clean_context"])
def test_noise_schedules_are_non_decreasing_ratios(schedule):
    ratios = block_ratios(schedule, 512, 8, torch.Generator().manual_seed(0))
    assert ratios.shape == (512, 8) and (ratios >= 0).all() and (ratios <= 1).all()
    assert (ratios.diff(dim=1) >= -1e-6).all()
    if schedule == "frontier":  # decoding's start: some block near fully masked after cleaner ones
        assert ((ratios[:, 1:] > 0.9) & (ratios[:, :1] < 0.3)).any()


def test_train_cli_rejects_bad_input(cli, demos, tmp_path):
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "distill", "--out", str(tmp_path / "s.safetensors")
    )
    assert code == 2 and "needs --teacher" in err
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--out", str(tmp_path / "x.pt")
    )
    assert code == 2 and "must end in .safetensors" in err
    code, _, err = cli(
        "train",
        "--demos",
        str(tmp_path / "nope"),
        "--recipe",
        "bidirectional",
        "--out",
        str(tmp_path / "y.safetensors"),
    )
    assert code == 2 and "is not a folder" in err
    code, _, err = cli(
        "train",
        "--demos",
        str(demos),
        "--recipe",
        "bidirectional",
        "--steps",
        "0",
        "--out",
        str(tmp_path / "z.safetensors"),
    )
    assert code == 2 and "steps must be >= 1" in err
    assert list(tmp_path.glob("*.safetensors")) == []


def test_probe_loss_tracks_training_and_init_continues_a_checkpoint(demos, tmp_path):
    first = tmp_path / "first.safetensors"
    report = train(TrainConfig(recipe="block_diffusion", probe_every=10, **TINY), demos, first)
    steps = [s for s, _ in report.probes]
    assert steps == [0, 10, 20, 30, 40]
    assert report.probes[-1][1] < 0.8 * report.probes[0][1]
    assert "probe_loss" in (tmp_path / "first.loss.csv").read_text().splitlines()[0]

    # Continued training starts where the first run ended, not from scratch.
    more = train(
        TrainConfig(recipe="block_diffusion", init=str(first), probe_every=10, **{**TINY, "steps": 10}),
        demos,
        tmp_path / "more.safetensors",
    )
    assert more.probes[0][1] == pytest.approx(report.probes[-1][1], rel=1e-5)
    meta = load(tmp_path / "more.safetensors").meta
    assert meta["init_sha256"] and meta["teacher_sha256"] == ""

    with pytest.raises(ValueError, match="block_causal model; recipe 'bidirectional'"):
        train(TrainConfig(recipe="bidirectional", init=str(first), **TINY), demos, tmp_path / "x.safetensors")


def test_student_records_its_teacher_by_content(demos, tmp_path):
    import hashlib

    teacher = tmp_path / "t.safetensors"
    train(TrainConfig(recipe="bidirectional", **{**TINY, "steps": 2}), demos, teacher)
    train(
        TrainConfig(recipe="distill", teacher=str(teacher), **{**TINY, "steps": 2}),
        demos,
        tmp_path / "s.safetensors",
    )
    assert (
        load(tmp_path / "s.safetensors").meta["teacher_sha256"]
        == hashlib.sha256(teacher.read_bytes()).hexdigest()
    )


def test_distillation_continues_from_a_student_of_the_same_teacher_only(demos, tmp_path):
    teacher, other = tmp_path / "t.safetensors", tmp_path / "other.safetensors"
    train(TrainConfig(recipe="bidirectional", **{**TINY, "steps": 2}), demos, teacher)
    train(TrainConfig(recipe="bidirectional", **{**TINY, "steps": 2, "seed": 1}), demos, other)
    student = tmp_path / "s.safetensors"
    first = train(TrainConfig(recipe="distill", teacher=str(teacher), probe_every=10, **TINY), demos, student)
    more = train(
        TrainConfig(
            recipe="distill", teacher=str(teacher), init=str(student), probe_every=10, **{**TINY, "steps": 10}
        ),
        demos,
        tmp_path / "more.safetensors",
    )
    # It starts from the student's weights (the probe is the same loss on the same rows),
    # not again from the teacher's.
    assert more.probes[0][1] == pytest.approx(first.probes[-1][1], rel=1e-5)
    assert first.probes[-1][1] != pytest.approx(first.probes[0][1], rel=1e-3)

    with pytest.raises(ValueError, match="distilled from another teacher"):
        train(
            TrainConfig(recipe="distill", teacher=str(other), init=str(student), **TINY),
            demos,
            tmp_path / "x.safetensors",
        )
    with pytest.raises(ValueError, match="not a block-causal student"):
        train(
            TrainConfig(recipe="distill", teacher=str(teacher), init=str(teacher), **TINY),
            demos,
            tmp_path / "y.safetensors",
        )
    assert not (tmp_path / "x.safetensors").exists() and not (tmp_path / "y.safetensors").exists()


def _synthetic_demos(folder, episodes):
    """A demonstrations folder of (task, observations, actions) episodes."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from harness.collect import DEMO_COLUMNS

    rows: dict[str, list] = {name: [] for name in DEMO_COLUMNS.names}
    for episode, (task, observations, actions) in enumerate(episodes):
        for step, (obs, action) in enumerate(zip(observations, actions, strict=True)):
            for name, value in (
                ("episode_id", episode),
                ("task", task),
                ("instruction", f"do the {task} thing"),
                ("episode_index", episode),
                ("seed", 0),
                ("init_state_id", 0),
                ("step", step),
                ("observation", np.asarray(obs, np.float32).tolist()),
                ("action", np.asarray(action, np.float32).tolist()),
            ):
                rows[name].append(value)
    folder.mkdir()
    pq.write_table(pa.table(rows, schema=DEMO_COLUMNS), folder / "steps.parquet")
    (folder / "manifest.json").write_text(json.dumps({"steps_sha256": "x"}))
    return folder


def test_mixed_state_sizes_are_zero_padded_and_the_policy_accepts_exactly_those(tmp_path):
    """LIBERO goal/10/90 tasks differ in state size: one model reads all of them."""
    import gymnasium as gym
    import numpy as np

    from policies.base import EpisodeContext
    from policies.registry import get_policy, parse_params

    rng = np.random.default_rng(0)
    demos = _synthetic_demos(
        tmp_path / "demos",
        [
            (task, rng.normal(size=(12, dim)), rng.uniform(-1, 1, (12, 4)))
            for task, dim in [("wide", 5), ("narrow", 3)] * 2
        ],
    )
    out = tmp_path / "m.safetensors"
    train(
        TrainConfig(recipe="bidirectional", **{**TINY, "steps": 2, "batch_size": 8, "warmup": 1}), demos, out
    )
    ckpt = load(out)
    assert ckpt.model.cfg.state_dim == 5 and ckpt.meta["state_dims"] == [3, 5]

    spec = get_policy("bidirectional")
    policy = spec.build(parse_params(spec, {"checkpoint": str(out), "steps": 2}))

    def context(dim: int) -> EpisodeContext:
        return EpisodeContext(
            suite="fake/mixed",
            task="narrow",
            instruction="do the narrow thing",
            action_space=gym.spaces.Box(-1, 1, (4,)),
            observation_space=gym.spaces.Box(-np.inf, np.inf, (dim,)),
            max_steps=10,
            episode_index=0,
        )

    policy.reset([context(3)])
    chunk = policy.act([np.ones(3, dtype=np.float32)])
    assert chunk.actions.shape == (1, TINY["chunk_len"], 4)
    with pytest.raises(ValueError, match="states of size 3 or 5"):
        policy.reset([context(4)])


def test_several_demonstration_folders_train_as_one(demos, tmp_path, cli):
    import hashlib
    import shutil

    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from policies.dvla.demos import load_demos

    one = load_demos(demos, chunk_len=4)
    two = load_demos([demos, demos], chunk_len=4)
    n = len(one.actions)
    assert len(two.actions) == 2 * n and np.array_equal(two.actions[n:], one.actions)
    assert np.array_equal(two.chunk_index[n:], one.chunk_index + n)  # chunks stay inside episodes
    assert two.sha256 == hashlib.sha256(f"{one.sha256}+{one.sha256}".encode()).hexdigest() != one.sha256

    # A second folder whose first episode id is the first folder's last one: still two
    # episodes, so the first folder's last chunk must not run into the second folder.
    shifted = tmp_path / "shifted"
    shutil.copytree(demos, shifted)
    table = pq.read_table(shifted / "steps.parquet").to_pandas()
    table["episode_id"] += int(table["episode_id"].max())
    pq.write_table(pa.Table.from_pandas(table, preserve_index=False), shifted / "steps.parquet")
    joined = load_demos([demos, shifted], chunk_len=4)
    assert joined.chunk_index[:n].max() < n

    other = tmp_path / "other"
    shutil.copytree(demos, other)
    manifest = json.loads((other / "manifest.json").read_text())
    (other / "manifest.json").write_text(json.dumps({**manifest, "action_dim": 7}))
    with pytest.raises(ValueError, match="action_dim 7 differs"):
        load_demos([demos, other], chunk_len=4)

    out = tmp_path / "both.safetensors"
    args = [
        "--recipe",
        "bidirectional",
        "--steps",
        "2",
        "--batch-size",
        "8",
        "--width",
        "32",
        "--layers",
        "1",
    ]
    code, _, err = cli("train", "--demos", str(demos), str(demos), *args, "--out", str(out), "--quiet")
    assert code == 0, err
    assert load(out).meta["data_sha256"] == two.sha256


@pytest.mark.parametrize(
    "recipe, schedule",
    [
        ("bidirectional", ""),
        ("block_diffusion", "frontier"),
        ("block_diffusion", "clean_context"),
        ("autoregressive", ""),
        ("distill", "frontier"),
    ],
)
def test_rows_of_noisy_demonstrations_are_scored_on_their_first_action_only(recipe, schedule):
    """What actions 2..H of a DART row say (they answer noise its state cannot predict)
    must change nothing: not the loss, and not what the model reads (with clean_context,
    not in the clean copy either; with distill, not what the teacher reads)."""
    from policies.dvla.losses import recipe_loss
    from tests.fakes import tiny_model

    pattern = {"bidirectional": "bidirectional", "autoregressive": "causal"}.get(recipe, "block_causal")
    model = tiny_model(pattern)
    teacher = tiny_model("bidirectional") if recipe == "distill" else None
    d, n = model.cfg.action_dim, model.cfg.action_tokens
    g = torch.Generator().manual_seed(0)
    clean = torch.randint(0, model.cfg.bins, (16, n), generator=g)
    words, state = torch.randint(1, 20, (16, 5), generator=g), torch.randn(16, 6, generator=g)
    blurred = clean.clone()
    blurred[:, d:] = torch.randint(0, model.cfg.bins, (16, n - d), generator=g)
    positions = torch.arange(n)

    def loss(tokens, first_only):
        seed = torch.Generator().manual_seed(1)
        return recipe_loss(
            recipe, schedule, model, teacher, tokens, words, state, positions, seed, None, first_only
        )

    noisy = torch.ones(16, dtype=torch.bool)
    if recipe != "autoregressive":  # later tokens are its inputs, but they score nothing
        assert torch.equal(loss(clean, noisy), loss(blurred, noisy))
    assert not torch.equal(loss(clean, None), loss(blurred, None))
    half = torch.arange(16) < 8  # clean rows stay whole
    assert not torch.equal(loss(clean, half), loss(blurred, half))


def test_noisy_targets_follow_the_folders_manifest(demos, tmp_path, cli):
    import shutil

    from policies.dvla.demos import load_demos

    noisy = tmp_path / "noisy"
    shutil.copytree(demos, noisy)
    manifest = json.loads((noisy / "manifest.json").read_text())
    (noisy / "manifest.json").write_text(json.dumps({**manifest, "action_noise": 0.1}))
    both = load_demos([demos, noisy], chunk_len=4)
    n = len(both.actions) // 2
    assert not both.noisy[:n].any() and both.noisy[n:].all()

    weights = {}
    for mode in ("first_action", "chunk"):
        out = tmp_path / f"{mode}.safetensors"
        argv = ["train", "--demos", str(demos), str(noisy), "--recipe", "bidirectional"]
        argv += ["--steps", "3", "--batch-size", "8", "--width", "32", "--layers", "1"]
        assert cli(*argv, "--noisy-targets", mode, "--out", str(out), "--quiet")[0] == 0
        ckpt = load(out)
        assert ckpt.meta["train_config"]["noisy_targets"] == mode
        weights[mode] = ckpt.model.state_dict()
    assert any(not torch.equal(weights["first_action"][k], weights["chunk"][k]) for k in weights["chunk"])
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--noisy-targets", "all",
        "--out", str(tmp_path / "x.safetensors"),
    )  # fmt: skip
    assert code == 2 and "first_action" in err and not (tmp_path / "x.safetensors").exists()


def test_relative_positions_append_each_offset_from_the_end_effector():
    import numpy as np

    from policies.observations import relative_positions

    states = np.arange(2 * 10, dtype=np.float32).reshape(2, 10) ** 1.5
    out = relative_positions(states, (1, 4, 7))
    assert out.shape == (2, 16) and np.array_equal(out[:, :10], states)
    assert np.allclose(out[:, 10:13], states[:, 4:7] - states[:, 1:4])
    assert np.allclose(out[:, 13:16], states[:, 7:10] - states[:, 1:4])
    assert np.array_equal(relative_positions(states, ()), states)


def test_relative_state_features_reach_the_checkpoint_and_the_policy(demos, tmp_path, cli):
    """Meta-World's env says where its positions are; collect records it, training with
    --state-features relative appends their offsets from the hand, the policy reads raw
    states, and a continued model or a student keeps the choice."""
    import numpy as np

    from policies.dvla.demos import load_demos

    manifest = json.loads((demos / "manifest.json").read_text())
    assert manifest["state_positions"] == {"reach-v3": [0, 4, 11, 36], "drawer-close-v3": [0, 4, 11, 36]}
    teacher = tmp_path / "rel.safetensors"
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--state-features", "relative",
        "--steps", "6", "--batch-size", "16", "--width", "32", "--layers", "1", "--ffn", "64",
        "--chunk-len", "4", "--out", str(teacher), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    ckpt = load(teacher)
    assert ckpt.state_positions == (0, 4, 11, 36)
    assert ckpt.model.cfg.state_dim == 39 + 9 and ckpt.raw_state_dim == 39
    obs = load_demos(demos, chunk_len=4).observations
    feats = ckpt.features(obs)
    assert np.allclose(feats[:, 39:42], obs[:, 4:7] - obs[:, 0:3])
    assert np.allclose(feats[:, 45:48], obs[:, 36:39] - obs[:, 0:3])
    assert np.allclose(ckpt.state_mean, feats.mean(0), atol=1e-5)  # normalised as the model reads

    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--quiet",
        "--policy", f"bidirectional:checkpoint={teacher},steps=2", "--out", str(tmp_path / "r"),
    )  # fmt: skip
    assert code == 0, err
    row = RunDir(tmp_path / "r").read_episodes().iloc[0]
    assert row["chunks"] > 0 and not isinstance(row["failure_reason"], str)  # ran, raised nothing

    student = tmp_path / "s.safetensors"
    train(TrainConfig(recipe="distill", teacher=str(teacher), **{**TINY, "steps": 2}), demos, student)
    assert load(student).state_positions == (0, 4, 11, 36)
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--init", str(teacher),
        "--state-features", "raw", "--steps", "2", "--out", str(tmp_path / "c.safetensors"),
    )  # fmt: skip
    assert code == 2 and "reads relative states" in err
    assert not (tmp_path / "c.safetensors").exists()


def test_relative_state_features_need_recorded_positions(demos, tmp_path, cli):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(demos, old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["state_positions"]  # a folder collected before positions were recorded
    (old / "manifest.json").write_text(json.dumps(manifest))
    code, _, err = cli(
        "train", "--demos", str(old), "--recipe", "bidirectional", "--state-features", "relative",
        "--out", str(tmp_path / "x.safetensors"),
    )  # fmt: skip
    assert (
        code == 2
        and "do not record where positions sit in the state" in err
        and "--state-features raw" in err
    )
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--state-features", "nearby",
        "--out", str(tmp_path / "x.safetensors"),
    )  # fmt: skip
    assert code == 2 and "relative" in err
    assert list(tmp_path.glob("*.safetensors")) == []


def test_action_range_full_keeps_a_rare_action_the_percentile_bins_clip(tmp_path, cli):
    import numpy as np

    rng = np.random.default_rng(0)
    episodes = []
    for i in range(10):
        actions = rng.uniform(-0.1, 0.1, (40, 4))
        actions[:2, 2] = 1.0 if i < 2 else actions[:2, 2]  # a wrist turn in 4 of 400 steps
        episodes.append(("turn", rng.normal(size=(40, 3)), actions))
    demos = _synthetic_demos(tmp_path / "demos", episodes)
    small = ["--steps", "2", "--batch-size", "8", "--width", "32", "--layers", "1", "--ffn", "64", "--quiet"]
    code, _, err = cli("train", "--demos", str(demos), "--recipe", "bidirectional", "--out", str(tmp_path / "p.safetensors"), *small)  # fmt: skip
    assert code == 0, err
    assert "clips some training actions" in err and "dimension 2: up to 0.8" in err
    assert load(tmp_path / "p.safetensors").meta["tokenizer_worst_error"][2] > 0.8
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--action-range", "full",
        "--out", str(tmp_path / "f.safetensors"), *small,
    )  # fmt: skip
    assert code == 0, err
    assert "clips" not in err
    full = load(tmp_path / "f.safetensors")
    assert full.tokenizer.high[2] == 1.0 and max(full.meta["tokenizer_worst_error"]) < 0.01
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--init", str(tmp_path / "f.safetensors"),
        "--action-range", "full", "--out", str(tmp_path / "c.safetensors"), *small,
    )  # fmt: skip
    assert code == 2 and "comes from the --init or --teacher checkpoint" in err
    assert not (tmp_path / "c.safetensors").exists()


def test_a_continued_model_that_clips_says_its_tokenizer_is_inherited(tmp_path, cli):
    """--action-range cannot widen an --init model's bins, so the hint must not offer it."""
    import numpy as np

    rng = np.random.default_rng(0)
    small = ["--steps", "2", "--batch-size", "8", "--width", "32", "--layers", "1", "--ffn", "64", "--quiet"]
    calm = [("turn", rng.normal(size=(40, 3)), rng.uniform(-0.1, 0.1, (40, 4))) for _ in range(5)]
    base = _synthetic_demos(tmp_path / "calm", calm)
    code, _, err = cli("train", "--demos", str(base), "--recipe", "bidirectional", "--action-range", "full", "--out", str(tmp_path / "a.safetensors"), *small)  # fmt: skip
    assert code == 0 and "clips" not in err, err
    wide = []
    for _ in range(5):
        actions = rng.uniform(-0.1, 0.1, (40, 4))
        actions[:3, 2] = 1.0  # wrist turns the first model's bins never saw
        wide.append(("turn", rng.normal(size=(40, 3)), actions))
    more = _synthetic_demos(tmp_path / "wide", wide)
    code, _, err = cli("train", "--demos", str(more), "--recipe", "bidirectional", "--init", str(tmp_path / "a.safetensors"), "--out", str(tmp_path / "b.safetensors"), *small)  # fmt: skip
    assert code == 0, err
    assert "clips some training actions" in err and "dimension 2" in err
    assert "The tokenizer is --init" in err and "from scratch" in err
    assert "If they matter" not in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without a CUDA GPU")
def test_train_on_cuda_without_a_gpu_exits_2_and_writes_nothing(cli, demos, tmp_path):
    out = tmp_path / "g.safetensors"
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--device", "cuda", "--out", str(out)
    )
    assert code == 2 and "--device cuda:" in err and "--device cpu" in err
    assert list(tmp_path.iterdir()) == []
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--device", "tpu", "--out", str(out)
    )
    assert code == 2 and "invalid choice: 'tpu'" in err and list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="device 'tpu' is not one of cpu, cuda"):
        TrainConfig(recipe="bidirectional", device="tpu").validate()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("recipe", ["bidirectional", "autoregressive", "block_diffusion", "distill"])
def test_a_gpu_run_writes_a_cpu_checkpoint_that_records_its_device(tmp_path, recipe):
    """Every recipe's tensors (masks drawn on the CPU, batches, the teacher) meet the model
    on the GPU, and the checkpoint comes back device-free, naming where it was trained.
    Synthetic demonstrations: a GPU machine need not have a simulator."""
    import numpy as np

    rng = np.random.default_rng(0)
    episodes = []
    for e in range(6):
        obs = rng.normal(size=(30, 9)).cumsum(0) / 5
        episodes.append((f"task{e % 2}", obs, np.tanh(obs[:, :4])))
    demos = _synthetic_demos(tmp_path / "demos", episodes)
    teacher = tmp_path / "t.safetensors"
    train(TrainConfig(recipe="bidirectional", **{**TINY, "steps": 4}), demos, teacher)
    extra = {"teacher": str(teacher)} if recipe == "distill" else {}
    cfg = TrainConfig(recipe=recipe, device="cuda", **extra, **TINY)
    report = train(cfg, demos, tmp_path / "g.safetensors")
    assert _mean(report.losses[-5:]) < _mean(report.losses[:5])
    ckpt = load(tmp_path / "g.safetensors")
    assert ckpt.meta["train_config"]["device"] == "cuda"
    assert all(p.device.type == "cpu" for p in ckpt.model.parameters())
    # the same seed draws the same batches and masks: losses track the CPU run's closely
    cpu = train(replace(cfg, device="cpu"), demos, tmp_path / "c.safetensors")
    assert abs(report.losses[0] - cpu.losses[0]) < 1e-3 * max(1.0, cpu.losses[0])
