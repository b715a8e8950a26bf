"""The `vlaeval` policy: a vla-eval model server, evaluated by this harness.

`--policy vlaeval:url=ws://HOST:PORT` evaluates any model server written for
allenai/vla-evaluation-harness (`vla-eval` 0.8.0: its `PredictModelServer` and
`ModelServer` subclasses, OpenVLA, pi0, GR00T, X-VLA, ...), speaking its protocol
(policies/vlaeval_wire.py) as its own client (`vla_eval/connection.py`) and benchmark
runner (`runners/sync_runner.py`) do: a `hello` first, answered with the server's own
`hello` (its `observation_params`, `action_spec`); per episode an `episode_start` with
the task, then one `observation` per step answered by one `action` (the server keeps a
chunk and hands it out an action at a time), then `episode_end`. Observations carry the
keys vla-eval's benchmark of the same family sends (policies/vlaeval_protocol.py), with
camera images PNG-encoded as its client sends them.

What differs from vla-eval's own runner, and why:
- A reply must echo its observation's `seq` and be an `action`: vla-eval only logs a
  mismatch, which lets a late reply be executed as the next step's; here it fails the
  episode and the connection is dropped (the next episode connects again).
- `episode_end` is sent when the next episode starts (or the run ends) with the steps
  taken, without the success vla-eval's runner adds: a policy here does not learn its
  episode's outcome. Model servers use it to drop their chunk buffer, as they do on
  `episode_start` anyway.
- LIBERO's gripper is binarised by sign (< 0: -1, else +1) as vla-eval's LIBERO
  benchmark does, unless `binarize_gripper=false`; SimplerEnv's and CALVIN's actions
  are executed as they come.

Forward passes happen on the server; a vla-eval server reports none, so NFE and counted
work are null ("not measured"), never 0. A `dvla-harness serve --protocol vla-eval`
server adds its counts to each action (`dvla/nfe`, `dvla/work`, `dvla/policy_time_s`),
which are kept as for the openpi dialect. Timeouts, reconnects with back-off and keys
are the `remote` policy's (policies/remote.py), whose connection this one reuses.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.remote import ConnectionLost, ConnectionParams, RemotePolicy
from policies.spec import PolicySpec, param
from policies.vlaeval_protocol import (
    BENCHMARKS,
    IMAGE_FORMATS,
    PROTOCOL_VERSION,
    Mapping,
    Sending,
    choose,
    payload,
    sending,
    task_info,
)


@dataclass(frozen=True)
class VlaEvalParams(ConnectionParams):
    benchmark: str = param(
        "auto",
        "whose observation to send: auto (LIBERO's, or SimplerEnv's for simpler/*), libero, simpler, "
        "calvin (chains/*)",
        choices=BENCHMARKS,
    )
    image_format: str = param(
        "png", "how camera images travel (vla-eval's client sends png)", choices=IMAGE_FORMATS
    )
    binarize_gripper: bool = param(
        True, "LIBERO: execute the gripper's sign (+-1), as vla-eval's LIBERO does"
    )


class ServerError(RuntimeError):
    """The model server answered with an `error` message (its text inside): the
    policy's failure; the connection stays in step and is kept."""


class VlaEvalPolicy(RemotePolicy):
    def __init__(self, params: VlaEvalParams):
        super().__init__(params)
        self.params: VlaEvalParams = params  # type: ignore[assignment]
        self._seq = 0
        self._expect: tuple[str, int] = ("hello", 0)
        self._mapping: Mapping | None = None
        self._send = Sending()
        self._open: EpisodeContext | None = None  # the episode the server was told of
        self._steps = 0
        self._restart = False

    # --- the envelope --------------------------------------------------------------

    def _envelope(self, kind: str, payload_map: dict[str, Any]) -> bytes:
        from policies.vlaeval_wire import pack

        self._seq += 1
        return pack(kind, payload_map, self._seq, self.params.image_format)

    def _encode(self, message: dict[str, Any]) -> bytes:
        """A request that expects a reply: the reply must echo its seq."""
        data = self._envelope(message["type"], message["payload"])
        self._expect = ("action" if message["type"] == "observation" else message["type"], self._seq)
        return data

    def _decode(self, data: bytes | str) -> dict[str, Any]:
        from policies.vlaeval_wire import unpack
        from policies.wire import WireError

        envelope = unpack(data)
        kind, seq = self._expect
        if envelope.seq != seq:
            detail = f": {envelope.payload.get('error')}" if envelope.type == "error" else ""
            raise WireError(
                f"the server answered message {envelope.seq} ({envelope.type}{detail}) while message "
                f"{seq} waited for its reply"
            )
        if envelope.type == "error":
            raise ServerError(f"the model server failed: {envelope.payload.get('error', envelope.payload)}")
        if envelope.type != kind:
            raise WireError(f"the server answered message {seq} with {envelope.type!r}, not {kind!r}")
        return envelope.payload

    def _handshake(self) -> dict[str, Any]:
        """vla-eval's: the client says hello, the server answers with its own."""
        from policies.wire import WireError

        self._seq = 0
        self._open = None
        self._ws.send(self._encode({"type": "hello", "payload": _hello()}))
        try:
            return self._receive()
        except ServerError as exc:
            raise WireError(str(exc)) from None

    def _post(self, kind: str, payload_map: dict[str, Any]) -> None:
        """A message with no reply (episode_start, episode_end)."""
        from policies.wsclient import ConnectionClosed

        try:
            self._ws.send(self._envelope(kind, payload_map))
        except (ConnectionClosed, ConnectionError) as exc:
            self.close()
            raise ConnectionLost(f"{self.params.url}: the server closed the connection ({exc})") from None

    # --- the policy contract -------------------------------------------------------

    def check_spaces(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        """Refuse a suite vla-eval has no observation for, a server whose asks this harness
        cannot meet, or one that declares actions of another size."""
        self._mapping = choose(self.params.benchmark, observation_space)
        try:
            if self._ws is None:
                self._connect()
        except ConnectionError as exc:
            raise ValueError(str(exc)) from None
        self._send = sending(self._mapping, self.metadata.get("observation_params") or {})
        spec = self.metadata.get("action_spec")
        if isinstance(spec, dict) and spec:
            dims = [c.get("dims") if isinstance(c, dict) else None for c in spec.values()]
            if all(isinstance(d, int) and d > 0 for d in dims) and sum(dims) != int(
                np.prod(action_space.shape)
            ):
                raise ValueError(
                    f"the server declares {sum(dims)}-D actions ({', '.join(map(str, spec))}); this suite "
                    f"takes {int(np.prod(action_space.shape))}-D"
                )

    @property
    def act_batch(self) -> Any:
        return None  # one observation per message: a server batches across connections itself

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        if len(episodes) != 1:
            raise ValueError("the vlaeval policy starts one episode per reset call")
        context = episodes[0]
        if self._ws is None:
            self._reconnect()
        # here too, not only in check_spaces: a worker process's policy is never checked,
        # and a server restarted with other settings asks anew
        self._mapping = self._mapping or choose(self.params.benchmark, context.observation_space)
        self._send = sending(self._mapping, self.metadata.get("observation_params") or {})
        self._contexts = episodes
        if context.subtask_index > 0 and self._open is not None:
            self._restart = True  # CALVIN's way: the same episode, a new subtask
            return
        if self._open is not None:
            self._post("episode_end", {"steps": self._steps})
        self._post("episode_start", {"task": task_info(self._mapping, context)})
        self._open, self._steps, self._restart = context, 0, False

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        from policies.wire import WireError

        assert self._mapping is not None
        message = payload(self._mapping, self._send, observations[0], self._contexts[0], self._restart)
        if self._open is None:  # the connection was lost and made again: the server has no episode
            raise ConnectionLost(f"{self.params.url}: the connection was made again within the episode")
        reply = self._call({"type": "observation", "payload": message})
        self._restart = False
        self._steps += 1
        raw = reply.get("actions", reply.get("action"))  # vla-eval's LIBERO reads either
        if raw is None:
            raise WireError(f"the server's action has no 'actions' (keys: {sorted(map(str, reply))})")
        action = np.asarray(raw, dtype=np.float64)
        if action.ndim == 2 and action.shape[0] == 1:
            action = action[0]
        if action.ndim != 1 or not np.isfinite(action).all():
            raise WireError(
                f"the server returned actions of shape {action.shape} (or not finite); vla-eval's "
                "benchmarks execute one action per observation (a chunking server keeps the rest)"
            )
        if self._mapping.benchmark == "libero" and self.params.binarize_gripper:
            action[-1] = -1.0 if action[-1] < 0 else 1.0
        return ChunkBatch(actions=action[None, None], action_tokens=int(reply.get("dvla/action_tokens", 0)))

    def close(self) -> None:
        if self._ws is not None and self._open is not None:
            try:
                self._ws.send(self._envelope("episode_end", {"steps": self._steps}))
            except ConnectionError:
                pass  # already gone: the server ends the episode itself
        self._open = None
        super().close()

    @property
    def served_by(self) -> str:
        return f"the vla-eval model server at {self.params.url}"


def _hello() -> dict[str, Any]:
    from harness import __version__

    return {"harness_version": f"dvla-harness {__version__}", "protocol_version": PROTOCOL_VERSION}


VLAEVAL = PolicySpec(
    name="vlaeval",
    summary="a vla-eval model server (allenai/vla-evaluation-harness's protocol)",
    params=VlaEvalParams,
    build=VlaEvalPolicy,
    extra="remote",
)
