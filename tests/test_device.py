"""`run --device cpu|cuda|auto`: model policies decode where asked, the manifest
says where, and a GPU that is not there is refused before anything is written."""

from __future__ import annotations

import json

import pytest
import torch

from harness import device
from harness.config import PolicyRun
from harness.device import resolve_device
from harness.errors import UsageError
from policies.registry import NoParams, PolicySpec
from tests.fakes import ChunkPolicy, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

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


# --backend ray: --device is tied to the GPUs Ray reserves per worker (--ray-num-gpus).
# No GPU here: what torch sees and what Ray reserved are monkeypatched, no Ray is started.


@pytest.mark.parametrize("gpus", [[], ["--ray-num-gpus", "0"]])
def test_cuda_on_ray_workers_without_a_reserved_gpu_exits_2_naming_ray_num_gpus(cli, tmp_path, gpus):
    out = tmp_path / "r"
    code, _, err = cli(
        "run", "--policy", "fast_dvla", "--backend", "ray", "--device", "cuda", *gpus, "--out", str(out)
    )
    assert code == 2 and not out.exists()
    (line,) = err.strip().splitlines()
    assert "--device cuda with --backend ray needs --ray-num-gpus G" in line and "--device auto" in line


def test_under_ray_this_process_leaves_the_device_to_the_workers(monkeypatch):
    """A CPU head node may drive GPU workers: this process neither refuses cuda for want
    of a GPU of its own nor moves its policies; the manifest says 'per worker'."""
    from argparse import Namespace

    from harness.commands.run import prepare_compute

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(device, "_record", None)
    monkeypatch.setattr("harness.threads.apply_threads", lambda *_a: {})  # this process's threads
    ray_args = Namespace(threads=1, device="cuda", backend="ray", ray_num_gpus=0.5)
    prepare_compute(ray_args)  # no refusal: the workers have the GPUs
    with pytest.raises(UsageError, match="--device cuda:"):
        prepare_compute(Namespace(threads=1, device="cuda", backend="local", ray_num_gpus=0.0))
    model, scripted = _Placed(), object()
    policies = [_run("fast_dvla", model), _run("scripted", scripted)]
    record = device.apply_device(policies, "cuda", per_worker=True)
    assert record == {"requested": "cuda", "used": "per worker", "gpu": None, "model_policies": ["fast_dvla"]}
    assert model.moved == [] and device.policy_device(model) == "per worker"
    assert device.policy_device(scripted) is None


def test_a_ray_worker_decodes_on_the_gpu_ray_reserved_for_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert device.worker_device("auto", []) == "cpu"  # none reserved: the CPU, even on a GPU node
    assert device.worker_device("auto", ["0"]) == "cuda"
    assert device.worker_device("cuda", ["1"]) == "cuda" and device.worker_device("cpu", ["0"]) == "cpu"
    assert device.worker_device("auto") == "cuda"  # a local worker: what this machine has
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert device.worker_device("auto", ["0"]) == "cpu"  # a reserved GPU a CPU-only torch cannot use


@pytest.mark.parametrize(("reserved", "used"), [(["0"], "cuda"), ([], "cpu")])
def test_a_ray_actor_records_where_its_policies_decode(monkeypatch, reserved, used):
    from harness.backends import ray as ray_backend
    from harness.backends.local import WorkerSpec

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda _index=0: "Fake GPU")
    monkeypatch.setattr(ray_backend, "reserved_gpu_ids", lambda: reserved)
    monkeypatch.setattr(device, "_record", None)
    monkeypatch.setattr("harness.threads.apply_threads", lambda *_a: {})  # this process's threads
    policy = _Placed()
    spec = WorkerSpec(lambda: fake_resolved(policy), threads=1, workers=1, traces=False, device="auto")
    actor = ray_backend.EpisodeActor("ray-0", spec)
    try:
        *warming, (kind, record) = actor.ready()  # a stream: each policy's warm-up, then ready
        assert [k for k, _ in warming] == ["warming"]
        assert kind == "ready" and policy.moved == [used]
        gpu = "Fake GPU" if used == "cuda" else None
        assert record["device"] == {"requested": "auto", "used": used, "gpu": gpu, "ray_gpu_ids": reserved}
    finally:
        actor.close()


@pytest.mark.parametrize(
    ("asked", "gpus", "local", "expected"),
    [
        (("cuda", 1.0), 0.0, True, "UsageError"),  # this machine's Ray: no worker could start
        (("cuda", 1.0), 0.0, False, "the workers wait until a node with enough GPUs joins"),
        (("cuda", 0.25), 1.0, True, None),
        (("auto", 0.0), 2.0, False, "every worker decodes on the CPU; add --ray-num-gpus G"),
        (("auto", 0.0), 0.0, True, None),
        (("cpu", 1.0), 1.0, True, "add --device cuda or auto, or drop --ray-num-gpus"),
        (("cpu", 0.0), 4.0, True, None),
    ],
    ids=[
        "local-too-few",
        "cluster-too-few",
        "shared",
        "auto-unreserved",
        "auto-no-gpus",
        "cpu-reserved",
        "cpu",
    ],
)
def test_the_gpus_ray_has_are_checked_against_what_the_workers_reserve(asked, gpus, local, expected):
    from harness.backends.ray import check_cluster_gpus

    if expected == "UsageError":
        with pytest.raises(
            UsageError, match=r"has 0 GPU\(s\), fewer than one worker reserves \(--ray-num-gpus 1\)"
        ):
            check_cluster_gpus(*asked, gpus, local=local)
        return
    warning = check_cluster_gpus(*asked, gpus, local=local)
    assert warning == expected if expected is None else expected in warning


class _Placed(ChunkPolicy):
    """A policy with a model to place: records where it was moved."""

    def __init__(self) -> None:
        super().__init__(chunk=2)
        self.moved: list[str] = []

    def to_device(self, where: str) -> None:
        self.moved.append(where)


def _run(name: str, policy: object) -> PolicyRun:
    spec = PolicySpec(name, "test policy", NoParams, lambda _p: policy)
    return PolicyRun(spec, NoParams(), "{}", "", "", f"{name}-id", policy)  # type: ignore[arg-type]
