"""`--backend ray`: the run's episodes on Ray actors, on this machine or a cluster.

Each worker is a Ray actor (`EpisodeActor`) that rebuilds the run's policies and suite
from the config, as a pool worker does, and runs one episode per call, or with
--batch-envs K a task's episodes of one policy K at a time per call, as a Ray streaming
generator (each episode's start and outcome reach the scheduler as they happen, so a
row is written while the rest of its batch runs). Ray moves the calls and results, places the actors (`num_cpus` = the worker's torch threads,
`num_gpus` = --ray-num-gpus, so a policy that decodes on a GPU lands on a GPU node), and
reports a lost actor as `RayActorError`; the scheduler (harness/backends/scheduler.py)
then resubmits the episodes it held to a fresh actor, as it does for a lost process. The actors
are made with `max_restarts=0`: a restarted actor would run the lost call again by
itself, without the per-episode retry count the failure rows need.

`--device` under Ray is decided per worker (harness/device.py `worker_device`): `cuda`
needs `--ray-num-gpus` (Ray hides or does not share out a GPU an actor did not reserve),
and `auto` takes the GPU Ray reserved for the worker, if any; `check_ray_device` and
`check_cluster_gpus` say so before anything is written.

`--ray-address auto|HOST:PORT` joins a running cluster (every node needs dvla-harness
and the suite's extra installed); without it a local Ray is started with this machine's
cores and stopped at the end.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import re
import socket
import sys
import time
import warnings
from typing import TYPE_CHECKING, Any

from harness.backends.scheduler import Event, JobId
from harness.errors import UsageError
from harness.plugins import install_hint

if TYPE_CHECKING:
    from collections.abc import Iterator

    from harness.backends import Execution
    from harness.backends.local import WorkerSpec

RAY_FIX = install_hint("ray")
CONNECT_TIMEOUT_S = 5.0


def check_ray_installed() -> None:
    if importlib.util.find_spec("ray") is None:
        raise UsageError(f"--backend ray needs the ray package, which is not installed: {RAY_FIX}")


def _probe(address: str) -> None:
    """Refuse a HOST:PORT nothing answers on, in seconds (ray.init would retry for minutes)."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise UsageError(f"--ray-address {address!r}: expected auto or HOST:PORT (e.g. 10.0.0.5:6379)")
    try:
        with socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise UsageError(
            f"--ray-address {address}: cannot reach a Ray cluster there ({exc}); start one with "
            f"`ray start --head --port {port}` on that machine, or leave --ray-address out for a local Ray"
        ) from None


def check_ray_device(device: str | None, ray_num_gpus: float) -> None:
    """Refuse (exit 2) `--device cuda` on workers that reserve no GPU: Ray gives an actor
    only the GPUs it reserved (older Rays hide the others with CUDA_VISIBLE_DEVICES="",
    newer ones leave them visible but unshared), so such a worker either cannot see a
    GPU or lands, unaccounted, on a node that may have none. Flags only: no Ray needed."""
    if device == "cuda" and not ray_num_gpus > 0:
        raise UsageError(
            "--device cuda with --backend ray needs --ray-num-gpus G (the GPUs Ray reserves for "
            "each worker, e.g. 1, or 0.25 to share one GPU among 4): a Ray worker that reserves "
            "none gets no GPU; or use --device auto (a worker's reserved GPU, else the CPU)"
        )


def check_cluster_gpus(
    device: str | None, ray_num_gpus: float, cluster_gpus: float, local: bool
) -> str | None:
    """What the GPUs Ray has (`cluster_gpus`) mean for this run: a UsageError (exit 2)
    when no worker could ever be placed on this machine's own Ray (`local`), else a
    warning to print (None when all is as asked). A cluster joined with --ray-address
    may still grow (an autoscaler adds GPU nodes), so there it is only a warning."""
    if ray_num_gpus > cluster_gpus:
        where = "this machine's Ray" if local else "the Ray cluster"
        have = f"{where} has {cluster_gpus:g} GPU(s), fewer than one worker reserves (--ray-num-gpus {ray_num_gpus:g})"
        if local:
            raise UsageError(
                f"{have}, so no worker could start; lower --ray-num-gpus, drop it with --device cpu, "
                "or join a cluster with GPU nodes (--ray-address)"
            )
        return f"{have}: the workers wait until a node with enough GPUs joins"
    if device == "auto" and ray_num_gpus == 0 and cluster_gpus > 0:
        return (
            f"--device auto with --ray-num-gpus 0: the workers reserve none of the cluster's "
            f"{cluster_gpus:g} GPU(s), so every worker decodes on the CPU; add --ray-num-gpus G to use them"
        )
    if device == "cpu" and ray_num_gpus > 0:
        return (
            f"--ray-num-gpus {ray_num_gpus:g} with --device cpu: each worker reserves GPUs its model "
            "policies do not decode on; add --device cuda or auto, or drop --ray-num-gpus"
        )
    return None


def connect(execution: Execution) -> None:
    """Join the cluster or start a local Ray, refusing (exit 2) what cannot be had; called
    before anything is written."""
    check_ray_installed()
    check_ray_device(execution.device, execution.ray_num_gpus)
    import ray

    if ray.is_initialized():
        return
    address = execution.ray_address
    if address not in (None, "auto"):
        _probe(address)
    options: dict[str, Any] = {"logging_level": logging.ERROR, "log_to_driver": False}
    if address is None:
        # workers import the project and the test plugins the way this process does
        path = os.pathsep.join(p for p in [os.getcwd(), *sys.path] if p and os.path.isdir(p))
        options |= {
            "num_cpus": os.cpu_count() or 1,
            "include_dashboard": False,
            "runtime_env": {"env_vars": {"PYTHONPATH": path}},
        }
    try:
        ray.init(address=address, **options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"at {address}" if address else "locally"
        hint = "start one with `ray start --head`, or leave --ray-address out for a local Ray"
        raise UsageError(f"--backend ray: cannot start or join Ray {where} ({exc}); {hint}") from None
    gpus = float(ray.cluster_resources().get("GPU", 0))
    try:
        warning = check_cluster_gpus(execution.device, execution.ray_num_gpus, gpus, local=address is None)
    except UsageError:
        if address is None:
            ray.shutdown()  # the Ray this call started
        raise
    if warning:
        warnings.warn(warning, UserWarning, stacklevel=2)


def reserved_gpu_ids() -> list[Any]:
    """The GPUs Ray reserved for the calling actor (none with --ray-num-gpus 0)."""
    import ray

    try:
        return list(ray.get_runtime_context().get_accelerator_ids().get("GPU", []))
    except AttributeError:  # an older Ray
        return list(ray.get_gpu_ids())


# `actor_death_reason`: Ray's words for a dead actor, and ours
_EXIT_CODE = re.compile(r"Worker exits with an exit code (-?\d+)")
_VANISHED = (
    "its process vanished (Ray saw its connection close): crashed (e.g. SIGSEGV), exited, "
    "or killed by SIGKILL (the out-of-memory killer, or a kill); Ray does not say which"
)
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
REASON_CHARS = 300


def actor_death_reason(message: str) -> str:
    """Why a Ray actor is gone, in one line of at most REASON_CHARS characters, from
    the text of its `RayActorError` (`str(exc)`, which is its `error_msg`).

    Ray keeps the cause only as text: `ActorDiedError` joins a generic first line
    ("The actor died unexpectedly before finishing this task."), the actor's id, pid
    and node, and the GCS's "The actor is dead because ..." line with the worker's exit
    type and detail; the exception has no exit code or signal field. So the cause is
    read from that text and said in the words of harness/backends/pool.py `lost_reason`
    ("killed by SIGTERM", "exited with status 3") where Ray knows it. Ray 2.60 does not
    know it for a segfault, an `os._exit` or a SIGKILL (measured): the raylet sees only
    the worker's connection close ("connection error code 2. End of file") and says the
    same for all three, so the reason names the three. Text Ray words otherwise falls
    back to its last "The actor is dead ..." or "The actor died ..." line, else its first.
    """
    text = _ANSI.sub("", message).strip()
    if not text:
        return "Ray gave no message"
    if "raised in its creation task" in text:  # its __init__ raised: the exception's own last line
        return _one_line(f"its __init__ raised {text.splitlines()[-1].strip()}")
    if "NODE_OUT_OF_MEMORY" in text:
        return "killed by Ray's memory monitor (its node ran low on memory)"
    if "receives a SIGTERM" in text:
        return "killed by SIGTERM"
    if code := _EXIT_CODE.search(text):
        return f"exited with status {code.group(1)}"
    if "connection error code" in text and "End of file" in text:
        return _VANISHED
    if "killed by `ray.kill`" in text:
        return "killed by ray.kill"
    if "its node has died" in text:
        return "its node died (preempted)" if "preempted" in text else "its node died"
    if "its owner has died" in text:
        return "its owner died"
    because = [line for line in text.splitlines() if line.startswith(("The actor is dead", "The actor died"))]
    return _one_line(because[-1] if because else text.splitlines()[0])


def _one_line(text: str) -> str:
    line = " ".join(text.split())
    return line if len(line) <= REASON_CHARS else line[: REASON_CHARS - 3] + "..."


class EpisodeActor:
    """A Ray worker: the run rebuilt once, then one episode per `run` call, or a batch of
    a task's episodes per `run_batch` call; both stream their events back as they happen."""

    def __init__(self, worker_id: str, spec: WorkerSpec):
        from harness.backends.local import start_worker

        self.error = ""
        try:
            self.worker, self.record = start_worker(spec, worker_id, reserved_gpu_ids())
        except Exception as exc:  # said by ready(), not as a dead actor retried in vain
            self.error = f"{type(exc).__name__}: {exc}"

    def ready(self) -> Iterator[tuple[str, Any]]:
        """A Ray streaming generator: ("warming", policy_config_id) before each policy's
        warm-up calls (each held to --episode-timeout by the scheduler), then "ready"
        with this worker's record, or "error" saying why it could not start."""
        if self.error:
            yield "error", self.error
            return
        yield from self.worker.warming()
        yield "ready", self.record | {"warm_up": self.worker.warm_up}

    def run(self, jid: JobId) -> Iterator[tuple[str, Any]]:
        """A Ray streaming generator, as run_batch: how far the episode has got (every
        PROGRESS_S, for its row should the actor die), then its end."""
        yield from self.worker.run([jid], alone=True)

    def run_batch(self, group: list[JobId]) -> Iterator[tuple[str, Any]]:
        """A Ray streaming generator: each event reaches the scheduler as it is yielded."""
        yield from self.worker.run(group, alone=False)

    def close(self) -> None:
        if not self.error:
            self.worker.close()


class RayWorkers:
    """The `Workers` of harness/backends/scheduler.py as Ray actors; each resolves
    --device on its own node."""

    def __init__(self, spec: WorkerSpec, execution: Execution):
        import ray

        from harness.threads import default_threads

        connect(execution)
        self.ray = ray
        self.owns_ray = execution.ray_address is None
        self.spec = spec
        self.actor_class = ray.remote(EpisodeActor).options(
            num_cpus=spec.threads or default_threads(spec.workers),
            num_gpus=execution.ray_num_gpus,
            max_restarts=0,
            max_task_retries=0,
        )
        self.actors: dict[int, Any] = {}
        # object ref or a batch's ObjectRefGenerator -> (slot, the actor it came from)
        self.refs: dict[Any, tuple[int, Any]] = {}
        self.started = 0
        # a batch's events stream back as yielded; each yield waits until this process has
        # taken the one before (backpressure 1): an actor that dies drops the events not
        # yet taken, and the scheduler must hear which episodes it had started
        self.stream: dict[str, Any] = {"num_returns": "streaming", "_generator_backpressure_num_objects": 1}

    def start(self, slot: int) -> str:
        worker_id = f"ray-{self.started}"
        self.started += 1
        actor = self.actor_class.remote(worker_id, self.spec)
        self.actors[slot] = actor
        self.refs[self._stream(actor.ready)] = (slot, actor)
        return worker_id

    def _stream(self, method: Any, *args: Any) -> Any:
        """Call an actor's generator method, its events streamed back as yielded."""
        try:
            return method.options(**self.stream).remote(*args)
        except (TypeError, ValueError):  # a Ray without the (private) backpressure option
            self.stream = {"num_returns": "streaming"}
            return method.options(**self.stream).remote(*args)

    def submit(self, slot: int, group: list[JobId], alone: bool) -> None:
        actor = self.actors[slot]
        if alone:
            for jid in group:
                self.refs[self._stream(actor.run, jid)] = (slot, actor)
        else:
            self.refs[self._stream(actor.run_batch, group)] = (slot, actor)

    def wait(self, timeout: float) -> list[Event]:
        if not self.refs:
            time.sleep(timeout)
            return []
        ready, _ = self.ray.wait(list(self.refs), num_returns=1, timeout=timeout)
        if ready:  # and whatever else is ready now
            ready, _ = self.ray.wait(list(self.refs), num_returns=len(self.refs), timeout=0)
        events = []
        for waitable in ready:
            if waitable not in self.refs:
                continue  # its actor was lost at an earlier event of this wait
            slot, actor = self.refs[waitable]
            if self.actors.get(slot) is not actor:
                del self.refs[waitable]
                continue  # from an actor already replaced
            if isinstance(waitable, self.ray.ObjectRef):
                ref = waitable
                del self.refs[waitable]
            else:  # a batch's generator: its next event (kept until the batch ends)
                try:
                    ref = next(waitable)
                except StopIteration:
                    del self.refs[waitable]
                    continue
            try:
                kind, payload = self.ray.get(ref)
            except self.ray.exceptions.RayActorError as exc:
                self.kill(slot)
                events.append(Event(slot, "lost", f"Ray actor died ({actor_death_reason(str(exc))})"))
                continue
            except self.ray.exceptions.RayError as exc:
                events.append(Event(slot, "error", f"{type(exc).__name__}: {exc}"))
                continue
            events.append(Event(slot, kind, payload))
        return events

    def kill(self, slot: int) -> None:
        actor = self.actors.pop(slot, None)
        if actor is not None:
            self.refs = {r: v for r, v in self.refs.items() if v[1] is not actor}
            self.ray.kill(actor, no_restart=True)

    def shutdown(self) -> None:
        for slot in list(self.actors):
            actor = self.actors[slot]
            try:
                self.ray.get(actor.close.remote(), timeout=10)
            except Exception:
                pass  # closing envs is a courtesy; the actor is killed either way
            self.kill(slot)
        if self.owns_ray:
            self.ray.shutdown()
