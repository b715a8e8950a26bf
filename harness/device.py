"""Where model policies decode: `run --device cpu|cuda|auto`, recorded in the manifest.

The default is the CPU: the shipped models are small (~0.9M parameters, the chain set
2.9M; batch 1), every committed baseline and README figure was measured on one, and a
speed figure from a GPU is not comparable with them. `auto` takes a CUDA GPU when torch
sees one; `cuda` without one is refused before anything is loaded or written. Policies
that hold a model say so by having `to_device(device)` (policies/dvla/policy.py); the
others (scripted experts, random) have nothing to move and run as they are.

With `--backend ray` the device is each worker's business, not this process's: the
workers may run on other nodes (a CPU head node driving GPU nodes), so this process
neither resolves nor applies it (its own policies, warmed up only, stay on the CPU; the
manifest's `device.used` says "per worker"), and each worker resolves it where Ray put
it (`worker_device`). Every worker's record in the manifest's execution entry says what
it asked for and used, so a run over mixed nodes says which worker decoded where.
"""

from __future__ import annotations

from typing import Any

from harness.errors import UsageError

DEVICES = ("cpu", "cuda", "auto")
DEFAULT_DEVICE = "cpu"
PER_WORKER = "per worker"  # manifest device.used under --backend ray: see the workers' records

_record: dict[str, Any] | None = None


def _no_cuda_reason(torch: Any) -> str:
    if torch.version.cuda is None:
        return f"the installed torch {torch.__version__} is a CPU-only build"
    return f"torch {torch.__version__} (built for CUDA {torch.version.cuda}) sees no CUDA GPU"


def resolve_device(requested: str) -> str:
    """'cpu' or 'cuda' for `requested` (one of DEVICES); UsageError (exit 2) for cuda
    without a GPU. torch is imported only when a GPU is asked about."""
    if requested not in DEVICES:
        raise UsageError(f"--device {requested!r}: valid choices are {', '.join(DEVICES)}")
    if requested == "cpu":
        return "cpu"
    import torch

    if torch.cuda.is_available():
        return "cuda"
    if requested == "auto":
        return "cpu"
    raise UsageError(
        f"--device cuda: {_no_cuda_reason(torch)}; use --device cpu, or --device auto "
        "(cuda when a GPU is visible, else cpu)"
    )


def apply_device(
    policies: list[Any], requested: str, used: str | None = None, per_worker: bool = False
) -> dict[str, Any]:
    """Move every model policy of `policies` (PolicyRun) to the resolved device and
    return what the manifest records: what was asked for, what was used, the GPU's name,
    and which policies hold a model that runs there.

    used: the device already decided (a Ray worker's `worker_device`), else resolved here.
    per_worker (--backend ray): the workers decide, each on its node; this process may
      have no GPU at all (a CPU head node), so nothing is resolved or moved here.
    """
    global _record
    moved = [p.spec.name for p in policies if callable(getattr(p.policy, "to_device", None))]
    if per_worker:
        _record = {"requested": requested, "used": PER_WORKER, "gpu": None, "model_policies": moved}
        return _record
    used = used or resolve_device(requested)
    for p in policies:
        move = getattr(p.policy, "to_device", None)
        if callable(move):
            move(used)
    gpu = None
    if used == "cuda":
        import torch

        gpu = torch.cuda.get_device_name(0)
    _record = {"requested": requested, "used": used, "gpu": gpu, "model_policies": moved}
    return _record


def worker_device(requested: str, ray_gpu_ids: list[Any] | None = None) -> str:
    """The device a worker's policies take: 'cpu' or 'cuda'.

    ray_gpu_ids (a Ray worker: the GPUs Ray reserved for it, maybe none): `auto` means
    the GPU Ray gave this worker. With none reserved it is the CPU even on a GPU node:
    Ray does not count a GPU an actor uses unasked, so it would place any number of
    workers on it (or, with Ray's older default, hide it from them anyway). `cuda` with
    none reserved is refused before the run (harness/backends/ray.py `check_ray_device`).
    """
    if requested == "auto" and ray_gpu_ids is not None and not ray_gpu_ids:
        return "cpu"
    return resolve_device(requested)


def policy_device(policy: Any) -> str | None:
    """The manifest's per-policy device: where its model decodes, "per worker" under
    --backend ray, None for a policy without a model."""
    per_worker = _record is not None and _record["used"] == PER_WORKER
    if per_worker and callable(getattr(policy, "to_device", None)):
        return PER_WORKER
    return getattr(policy, "device", None)


def device_record() -> dict[str, Any]:
    """The last apply_device's record; a run started without it (the library's
    runner.run called directly) decodes where its policies were built: the CPU."""
    return _record or {"requested": None, "used": DEFAULT_DEVICE, "gpu": None, "model_policies": None}


def worker_device_record(ray_gpu_ids: list[Any] | None = None) -> dict[str, Any]:
    """A worker's entry in the manifest (execution[].worker_threads[].device): what it
    was asked for, what it used, its GPU's name, and under Ray the GPU ids Ray gave it."""
    record = {k: v for k, v in device_record().items() if k != "model_policies"}
    if ray_gpu_ids is not None:
        record["ray_gpu_ids"] = [str(i) for i in ray_gpu_ids]
    return record
