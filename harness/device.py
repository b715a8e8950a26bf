"""Where model policies decode: `run --device cpu|cuda|auto`, recorded in the manifest.

The default is the CPU: the shipped models are small (~0.9M parameters, batch 1), every
committed baseline and README figure was measured on one, and a speed figure from a GPU
is not comparable with them. `auto` takes a CUDA GPU when torch sees one; `cuda` without
one is refused before anything is loaded or written. Policies that hold a model say so
by having `to_device(device)` (policies/dvla.py); the others (scripted experts, random)
have nothing to move and run as they are.
"""

from __future__ import annotations

from typing import Any

from harness.errors import UsageError

DEVICES = ("cpu", "cuda", "auto")
DEFAULT_DEVICE = "cpu"

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


def apply_device(policies: list[Any], requested: str) -> dict[str, Any]:
    """Move every model policy of `policies` (PolicyRun) to the resolved device and
    return what the manifest records: what was asked for, what was used, the GPU's name,
    and which policies hold a model that runs there."""
    global _record
    used = resolve_device(requested)
    moved = []
    for p in policies:
        move = getattr(p.policy, "to_device", None)
        if callable(move):
            move(used)
            moved.append(p.spec.name)
    gpu = None
    if used == "cuda":
        import torch

        gpu = torch.cuda.get_device_name(0)
    _record = {"requested": requested, "used": used, "gpu": gpu, "model_policies": moved}
    return _record


def device_record() -> dict[str, Any]:
    """The last apply_device's record; a run started without it (the library's
    runner.run called directly) decodes where its policies were built: the CPU."""
    return _record or {"requested": None, "used": DEFAULT_DEVICE, "gpu": None, "model_policies": None}
