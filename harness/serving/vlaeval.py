"""`dvla-harness serve --protocol vla-eval`: any registered policy as a vla-eval model server.

vla-eval's own client and benchmark runner (`vla-eval run`, its `Connection` and
`Orchestrator`) drive it as they drive one of their `PredictModelServer`s
(`vla_eval/model_servers/serve.py` and `predict.py`), over the protocol of
policies/vlaeval_wire.py:

    hello            -> hello: {harness_version, protocol_version, model_server,
                        capabilities, observation_params, action_spec, observation_spec,
                        dvla: the openpi dialect's metadata}
    episode_start    -> (no reply; an `error` with its seq if the episode cannot start)
    observation      -> action: {"actions": float32 (action_dim,), "dvla/nfe": int,
                        "dvla/work": {...}, "dvla/policy_time_s": float, "dvla/action_tokens": int}
    episode_end      -> (no reply)
    anything else    -> error: {"error": "..."}; the connection stays open

The policy decodes a chunk when the episode has none left and the server hands it out
one action per observation, as `PredictModelServer` does with `chunk_size` set; the
chunk is dropped at every episode_start and episode_end. Its hello asks the benchmark
(`observation_params`, which vla-eval's orchestrator merges into the benchmark's
arguments) for everything this harness's observation holds: for LIBERO the wrist image
and the 8-D state, unfolded (`quat_no_antipodal`), so the policy reads what
`libero/<suite>:obs=upstream` gives it here. PNG images are decoded.

An episode_start's task is this harness's: for LIBERO, vla-eval's `task_id` and
`episode_idx` are the task's index in the served suite and the episode (the initial
state) within it, so the policy is reset with the episode's own context (task name,
seed, initial state), as `run` would reset it. The forward passes of each decode (and of
the reset, reported with the episode's first action) travel with the action that
started it; the other actions of its chunk carry 0.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import cache
from typing import Any

import numpy as np

from harness.episode.work import WIRE_KEY, Work
from harness.serving.server import Served, Session
from policies.vlaeval_protocol import PROTOCOL_VERSION, Mapping, choose, observation, observation_params
from policies.vlaeval_wire import Envelope, pack, unpack
from policies.wire import WireError

log = logging.getLogger("dvla_harness.serve")
PROTOCOL = "vla-eval/1"
SERVABLE = (
    "a server of vla-eval's protocol serves libero/<suite>:obs=upstream suites, whose whole observation "
    "vla-eval's LIBERO sends (its SimplerEnv and CALVIN send no state a policy here reads)"
)


def mapping_for(served: Served) -> Mapping:
    """The vla-eval observation the served suite's policy reads (ValueError if none):
    only LIBERO's carries everything a policy here reads (images and its state)."""
    return choose("libero", served.observation_space, SERVABLE)


def _spec(
    name: str, dims: int, fmt: str, low: float | None = None, high: float | None = None
) -> dict[str, Any]:
    """One DimSpec as vla-eval's `DimSpec.to_dict` writes it."""
    spec: dict[str, Any] = {"name": name, "dims": dims, "format": fmt}
    return spec | ({"range": [low, high]} if low is not None else {})


# vla-eval's LIBERO specs (its benchmark's get_action_spec / get_observation_spec), so its
# orchestrator's check between server and benchmark passes.
ACTION_SPEC = {
    "position": _spec("position", 3, "delta_xyz", -1, 1),
    "rotation": _spec("rotation", 3, "axis_angle", -3.15, 3.15),
    "gripper": _spec("gripper", 1, "binary_close_positive", -1, 1),
}
OBSERVATION_SPEC = {
    "agentview": _spec("image", 0, "rgb_hwc_uint8"),
    "wrist": _spec("image", 0, "rgb_hwc_uint8"),
    "state": _spec("state", 8, "eef_pos3_axisangle3_gripper2"),
    "language": _spec("language", 0, "language"),
}


def hello(served: Served, mapping: Mapping) -> dict[str, Any]:
    from harness import __version__

    return {
        "harness_version": f"dvla-harness {__version__}",
        "protocol_version": PROTOCOL_VERSION,
        "model_server": f"dvla-harness:{served.name}",
        "capabilities": {},
        "observation_params": observation_params(mapping),
        "action_spec": ACTION_SPEC,
        "observation_spec": OBSERVATION_SPEC,
        "dvla": served.metadata | {"protocol": PROTOCOL},
    }


@cache
def _suite(name: str) -> Any:
    from adapters.registry import load_suite

    return load_suite(name)


def episode_values(served: Served, task: Any) -> dict[str, Any]:
    """The episode context (server.Session.reset's values) of vla-eval's LIBERO task map."""
    if not isinstance(task, dict):
        raise WireError(f"episode_start needs a task map, got {type(task).__name__}")
    suite = _suite(served.suite)
    key = served.suite.partition(":")[0].removeprefix("libero/")
    if task.get("suite", f"libero_{key}") != f"libero_{key}":
        raise WireError(f"this server serves {served.suite}; the benchmark runs {task.get('suite')!r}")
    index = task.get("task_id")
    if index is None:
        named = [t.index for t in suite.tasks if t.instruction == task.get("name")]
        index = named[0] if named else None
    if not isinstance(index, int) or not 0 <= index < len(suite.tasks):
        raise WireError(f"task_id {index!r} names no task of {served.suite} (0..{len(suite.tasks) - 1})")
    spec_task = suite.tasks[index]
    episode = task.get("episode_idx", 0)
    if not isinstance(episode, int) or not 0 <= episode < len(spec_task.episodes):
        raise WireError(
            f"episode_idx {episode!r} is not an episode of task {index} (0..{len(spec_task.episodes) - 1})"
        )
    spec = spec_task.episodes[episode]
    return {
        "task": spec_task.name,
        "instruction": spec_task.instruction,
        "episode_index": spec.index,
        "seed": spec.seed,
        "init_state_id": spec.init_state_id,
        "max_steps": spec_task.max_steps,
    }


class VlaEvalSession:
    """One connection: its episode, the rest of its chunk, and the counts not yet reported."""

    def __init__(self, served: Served, mapping: Mapping):
        self.served, self.mapping = served, mapping
        self.base = Session(served)
        self.chunk: list[np.ndarray] = []
        self.unreported = {"dvla/nfe": 0, WIRE_KEY: Work(), "dvla/policy_time_s": 0.0}

    def handle(self, message: Envelope) -> dict[str, Any] | None:
        """The reply's payload, or None for a message that gets none."""
        if message.type == "hello":
            return hello(self.served, self.mapping)
        if message.type == "episode_start":
            self.chunk = []
            self.base.context = None
            reply = self.base.reset(episode_values(self.served, message.payload.get("task")))
            self._unreported(reply)
            return None
        if message.type == "episode_end":
            self.chunk, self.base.context = [], None
            return None
        if message.type == "observation":
            return self.act(message.payload)
        if message.type == "error":
            log.warning("the client reported an error: %s", message.payload.get("error"))
            return None
        raise WireError(f"a client does not send {message.type!r} messages")

    def _unreported(self, reply: dict[str, Any]) -> None:
        self.unreported["dvla/nfe"] += int(reply.get("dvla/nfe", 0))
        self.unreported[WIRE_KEY] += Work.from_wire(reply.get(WIRE_KEY))
        self.unreported["dvla/policy_time_s"] += float(reply.get("dvla/policy_time_s", 0.0))

    def act(self, message: dict[str, Any]) -> dict[str, Any]:
        if self.base.context is None:
            raise WireError("an observation before episode_start")
        try:
            flat = observation(self.mapping, message)
        except ValueError as exc:
            raise WireError(str(exc)) from None
        if "state" in flat:
            flat[self.served.state_key] = flat.pop("state")
        obs = self.served.observation(flat)
        extra: dict[str, Any] = {}
        if not self.chunk:
            reply = self.base.decode([self.base.context], [obs], single=True)
            self.chunk = list(np.asarray(reply["actions"], dtype=np.float32))
            self._unreported(reply)
            extra = {"dvla/action_tokens": int(reply.get("dvla/action_tokens", 0))}
            if "dvla/queue_time_s" in reply:
                extra["dvla/queue_time_s"] = reply["dvla/queue_time_s"]
        counts = self.unreported | {WIRE_KEY: self.unreported[WIRE_KEY].to_wire()}
        self.unreported = {"dvla/nfe": 0, WIRE_KEY: Work(), "dvla/policy_time_s": 0.0}
        return {"actions": self.chunk.pop(0), **counts, **extra}


def handler(served: Served, live: set[Any]) -> Callable[[Any], None]:
    """The per-connection loop (server.make_server's `dialect`)."""
    mapping = mapping_for(served)

    def handle(connection: Any) -> None:
        from websockets.exceptions import ConnectionClosed

        session = VlaEvalSession(served, mapping)
        address = connection.remote_address
        live.add(connection)
        try:
            for data in connection:
                _answer(connection, session, data)
        except ConnectionClosed:
            log.info("%s went away without closing", address)
        finally:
            live.discard(connection)
            if served.coalescer is not None:
                served.coalescer.gone(id(session.base))

    return handle


def _answer(connection: Any, session: VlaEvalSession, data: bytes | str) -> None:
    """One message's reply: its payload, or an error message naming what went wrong."""
    seq = 0
    try:
        message = unpack(data)
        seq = message.seq
        payload = session.handle(message)
    except WireError as exc:
        log.warning("rejected a message from %s: %s", connection.remote_address, exc)
        connection.send(pack("error", {"error": f"bad request: {exc}"}, seq, "raw"))
        return
    except Exception as exc:  # the policy failed: say so, keep serving
        log.exception("policy call failed")
        connection.send(pack("error", {"error": f"policy error: {type(exc).__name__}: {exc}"}, seq, "raw"))
        return
    if payload is not None:
        kind = "hello" if message.type == "hello" else "action"
        connection.send(pack(kind, payload, seq, "raw"))
