"""`train --ema`: the checkpoint holds the moving average of the weights, not the last step's."""

from __future__ import annotations

import pytest
import torch

from policies.dvla.checkpoint import load
from policies.dvla.recipes import TrainConfig
from policies.dvla.training import train
from tests.fakes import TINY_TRAIN

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def _weights(path) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in load(path).model.state_dict().items()}


def test_the_saved_weights_are_the_moving_average_of_every_step(demos, tmp_path, cli):
    start = tmp_path / "start.safetensors"
    train(TrainConfig(recipe="bidirectional", **{**TINY_TRAIN, "steps": 5}), demos, start)
    two = {**TINY_TRAIN, "steps": 2, "init": str(start), "warmup_steps": 1}
    for name, ema in (("last", 0.0), ("ema", 0.9)):
        train(TrainConfig(recipe="bidirectional", ema=ema, **two), demos, tmp_path / f"{name}.safetensors")
    w0, last, ema = (_weights(tmp_path / f"{n}.safetensors") for n in ("start", "last", "ema"))
    # After two steps the average is 0.9^2 w0 + 0.9 * 0.1 w1 + 0.1 w2; w1 is what a one-step
    # run from the same seed ends at (step 0 draws the same batch at the same warm-up lr).
    train(TrainConfig(recipe="bidirectional", **{**two, "steps": 1}), demos, tmp_path / "one.safetensors")
    one = _weights(tmp_path / "one.safetensors")
    moved = [k for k in w0 if not torch.equal(w0[k], last[k])]
    assert moved, "training moved nothing"
    for k in moved:
        expected = 0.81 * w0[k] + 0.09 * one[k] + 0.1 * last[k]
        torch.testing.assert_close(ema[k], expected, atol=1e-6, rtol=1e-5)
    assert load(tmp_path / "ema.safetensors").meta["train_config"]["ema"] == 0.9

    out = tmp_path / "x.safetensors"
    code, _, err = cli(
        "train", "--demos", str(demos), "--recipe", "bidirectional", "--ema", "1", "--out", str(out)
    )
    assert code == 2 and "ema must be in [0, 1)" in err and not out.exists()
