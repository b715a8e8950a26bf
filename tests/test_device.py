"""`run --device cpu|cuda|auto` (issue 22): model policies decode where asked, the manifest
says where, and a GPU that is not there is refused before anything is written."""

from __future__ import annotations

import json

import pytest
import torch

from harness.device import resolve_device
from harness.errors import UsageError

NO_GPU = not torch.cuda.is_available()


@pytest.mark.skipif(not NO_GPU, reason="needs a machine without a CUDA GPU")
def test_cuda_without_a_gpu_exits_2_naming_the_problem_and_writes_nothing(cli, tmp_path):
    out = tmp_path / "r"
    code, _, err = cli("run", "--policy", "fast_dvla", "--device", "cuda", "--out", str(out))
    assert code == 2
    (line,) = err.strip().splitlines()
    assert "--device cuda:" in line and ("CPU-only build" in line or "sees no CUDA GPU" in line)
    assert "--device cpu" in line and "--device auto" in line
    assert not out.exists()
    code, _, err = cli("run", "--policy", "fast_dvla", "--device", "tpu", "--out", str(out))
    assert code == 2 and "invalid choice: 'tpu'" in err and not out.exists()


def test_auto_takes_a_gpu_only_when_torch_sees_one(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(UsageError, match="--device cuda"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == "cuda" and resolve_device("cuda") == "cuda"


@pytest.mark.parametrize("device", ["cpu", "auto"])
def test_model_policies_decode_on_the_device_the_manifest_names(cli, tmp_path, device):
    out = tmp_path / device
    code, _, err = cli(
        "run",
        "--suite",
        "metaworld/mt1/reach-v3",
        "--policy",
        "fast_dvla",
        "--policy",
        "scripted",
        "--episodes-per-task",
        "1",
        "--device",
        device,
        "--quiet",
        "--out",
        str(out),
    )
    assert code == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    used = "cuda" if device == "auto" and not NO_GPU else "cpu"
    assert manifest["device"] == {
        "requested": device,
        "used": used,
        "gpu": None if used == "cpu" else torch.cuda.get_device_name(0),
        "model_policies": ["fast_dvla"],
    }
    assert [p["device"] for p in manifest["policies"]] == [used, None]  # scripted holds no model
