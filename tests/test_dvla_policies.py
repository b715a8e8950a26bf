"""The decoders as registered policies: checkpoints, validation, NFE per chunk in rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from policies.dvla.checkpoint import Checkpoint, CheckpointError, load, save
from policies.dvla.model import ActionTokenModel, ModelConfig
from policies.dvla.tokenizer import ActionTokenizer
from results.store import RunDir

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--quiet"]


def make_checkpoint(path, pattern: str, block_size: int = 0):
    torch.manual_seed(0)
    cfg = ModelConfig(
        action_dim=4,
        chunk_len=4,
        state_dim=39,
        bins=64,
        vocab_words=16,
        max_words=6,
        width=32,
        layers=2,
        heads=4,
        ffn=64,
        pattern=pattern,
        block_size=block_size,
    )
    actions = np.random.default_rng(0).uniform(-1, 1, (500, 4))
    ckpt = Checkpoint(
        ActionTokenModel(cfg),
        ActionTokenizer.fit(actions, bins=64),
        {"reach": 2, "the": 3, "goal": 4, "position": 5},
        np.zeros(39, np.float32),
        np.ones(39, np.float32),
        {"recipe": "untrained"},
    )
    return save(ckpt, path)


@pytest.mark.parametrize(
    ("policy", "pattern", "block", "params", "nfe"),
    [
        ("bidirectional", "bidirectional", 0, "steps=5", 5.0),
        ("fast_dllm", "bidirectional", 0, "threshold=0,steps_per_block=3", 3.0),  # 1 block x 3
        ("fast_dllm", "bidirectional", 0, "threshold=0,steps_per_block=3,blocks=4", 12.0),  # 4 x 3
        ("fast_dllm", "bidirectional", 0, "threshold=0,steps_per_block=3,block_size=8", 6.0),  # 2 x 3
        ("autoregressive", "causal", 0, "", 16.0),
        ("block_diffusion", "block_causal", 8, "steps_per_block=3", 6.0),
    ],
)
def test_nfe_per_chunk_in_rows_is_the_decoders_identity(cli, tmp_path, policy, pattern, block, params, nfe):
    ckpt = make_checkpoint(tmp_path / "m.safetensors", pattern, block)
    spec = f"{policy}:checkpoint={ckpt}" + (f",{params}" if params else "")
    code, _, err = cli(*MT1, "--policy", spec, "--out", str(tmp_path / "run"))
    assert code == 0, err
    row = RunDir(tmp_path / "run").read_episodes().iloc[0]
    assert row["nfe_per_chunk"] == nfe
    assert row["action_tokens_total"] == row["chunks"] * 16
    assert row["tokens_per_s"] > 0 and row["checkpoint_sha256"] and pd.isna(row["failure_reason"])


def test_fast_dvla_runs_and_its_nfe_is_bounded(cli, tmp_path):
    ckpt = make_checkpoint(tmp_path / "m.safetensors", "block_causal", 4)
    code, _, _ = cli(*MT1, "--policy", f"fast_dvla:checkpoint={ckpt}", "--out", str(tmp_path / "run"))
    assert code == 0
    row = RunDir(tmp_path / "run").read_episodes().iloc[0]
    assert 1 <= row["nfe_per_chunk"] <= 16


def test_fast_dllm_blocks_that_do_not_divide_the_chunk_are_refused(cli, tmp_path):
    ckpt = make_checkpoint(tmp_path / "m.safetensors", "bidirectional")
    code, _, err = cli(
        *MT1, "--policy", f"fast_dllm:checkpoint={ckpt},blocks=3", "--out", str(tmp_path / "run")
    )
    assert code == 2 and "blocks=3 does not divide the chunk's 16 action tokens; valid: 1, 2, 4, 8, 16" in err
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_of_the_wrong_pattern_is_refused(cli, tmp_path):
    ckpt = make_checkpoint(tmp_path / "m.safetensors", "bidirectional")
    code, _, err = cli(*MT1, "--policy", f"fast_dvla:checkpoint={ckpt}", "--out", str(tmp_path / "run"))
    assert code == 2 and "a bidirectional model; this decoder needs a block_causal model" in err
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_trained_on_another_suite_is_refused_before_anything_is_written(cli, tmp_path):
    # LIBERO object's student acts in 7-D; Meta-World takes 4-D actions. Refused once, up
    # front, not as one failed row per episode.
    code, _, err = cli(
        *MT1,
        "--policy",
        "scripted",
        "--policy",
        "fast_dvla:checkpoint=libero-object",
        "--out",
        str(tmp_path / "run"),
    )
    assert code == 2 and "policy fast_dvla cannot act in metaworld/mt1/reach-v3" in err
    assert "libero-object-fast_dvla.safetensors: acts in 7-D, the suite's actions are (4,)" in err
    assert not (tmp_path / "run").exists()


def test_bad_decoder_parameters_are_refused(cli, tmp_path):
    ckpt = make_checkpoint(tmp_path / "m.safetensors", "block_causal", 4)
    code, _, err = cli(
        *MT1,
        "--policy",
        f"fast_dvla:checkpoint={ckpt},tau_add=0.9,tau_act=0.5",
        "--out",
        str(tmp_path / "run"),
    )
    assert code == 2 and "tau_add (0.9) must be <= tau_act (0.5)" in err
    code, _, err = cli(*MT1, "--policy", "bidirectional:steps=0", "--out", str(tmp_path / "run"))
    assert code == 2 and "steps=0 is out of range; valid range [1, 1024]" in err
    code, _, err = cli(
        *MT1, "--policy", "bidirectional:checkpoint=nope.safetensors", "--out", str(tmp_path / "r")
    )
    assert code == 2 and "checkpoint 'nope.safetensors' does not exist" in err
    code, _, err = cli(*MT1, "--policy", "fast_dvla:checkpoint=libero-nowhere", "--out", str(tmp_path / "r"))
    assert code == 2 and "'libero-nowhere' does not exist" in err and "metaworld-mt10" in err


def test_a_shipped_set_name_resolves_to_that_sets_file_for_the_decoders_recipe():
    from policies.dvla.policy import shipped
    from policies.registry import get_policy, parse_params

    for policy, recipe in [("fast_dllm", "bidirectional"), ("fast_dvla", "fast_dvla")]:
        params = parse_params(get_policy(policy), {"checkpoint": "metaworld-mt10"})
        assert params.checkpoint == shipped(recipe) and Path(params.checkpoint).is_file()


def test_corrupt_and_foreign_checkpoints_get_clear_errors(tmp_path):
    good = make_checkpoint(tmp_path / "m.safetensors", "causal")
    assert load(good).model.cfg.pattern == "causal"
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(good.read_bytes()[:100])
    with pytest.raises(CheckpointError, match=r"corrupt\.safetensors: not a readable safetensors file"):
        load(corrupt)
    from safetensors.torch import save_file

    save_file({"x": torch.zeros(2)}, str(tmp_path / "foreign.safetensors"))
    with pytest.raises(CheckpointError, match="without a dvla-harness header"):
        load(tmp_path / "foreign.safetensors")


def test_state_positions_that_do_not_fit_the_state_are_refused(tmp_path):
    good = load(make_checkpoint(tmp_path / "m.safetensors", "causal"))
    assert good.state_positions == () and good.raw_state_dim == 39
    # 39 model inputs = a 36-D raw state + one offset: a position at 34 runs past its end.
    good.state_positions = (0, 34)
    with pytest.raises(CheckpointError, match=r"state_positions \[0, 34\] do not fit a 36-D state"):
        load(save(good, tmp_path / "bad.safetensors"))
    good.state_positions = (0, 33)
    assert load(save(good, tmp_path / "ok.safetensors")).raw_state_dim == 36


def test_a_state_prefix_that_does_not_fit_the_model_is_refused(tmp_path):
    good = load(make_checkpoint(tmp_path / "m.safetensors", "causal"))
    good.state_prefix = 39  # all 39 inputs are the head of the state: a proprio model
    good.meta = {**good.meta, "state_dims": [45]}
    ok = load(save(good, tmp_path / "ok.safetensors"))
    assert ok.state_prefix == 39 and ok.raw_state_dim == 45 and ok.state_features == "proprio"
    for prefix, needle in ((16, "a prefix is all the model reads"), (-1, "non-negative integer")):
        good.state_prefix = prefix
        with pytest.raises(CheckpointError, match=needle):
            load(save(good, tmp_path / "bad.safetensors"))
