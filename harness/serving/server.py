"""`dvla-harness serve`: any registered policy behind openpi's WebSocket policy protocol.

On connect the server sends its metadata (one msgpack map); then every message from the
client is one call and gets one reply, as openpi's `WebsocketPolicyServer` does, so
`openpi-client`'s `WebsocketClientPolicy` (and anything compatible) can evaluate our
decoders, and our `remote` policy can evaluate openpi-served models. The messages:

    observation map          -> {"actions": (chunk, action_dim) float32, "dvla/nfe": int,
                                 "dvla/work": {...}, "dvla/policy_time_s": float,
                                 "dvla/action_tokens": int, "server_timing": {"infer_ms": float}}
    {"dvla/reset": context}  -> {"dvla/ok": True, "dvla/nfe": ..., "dvla/policy_time_s": ...}
    {"dvla/batch": {"episodes": [context, ...], "observations": [observation map, ...]}}
                             -> {"actions": (K, chunk, action_dim) float32, "dvla/nfe": int,
                                 "dvla/policy_time_s": float, "dvla/action_tokens": int,
                                 "dvla/batch_size": K}

An observation map holds the state under `state_key` (default "state"), camera images
under their names, and the instruction under "prompt" (openpi's key). Our client resets
every episode explicitly (the episode's task, instruction, index, seed); a plain openpi
client never does, so the first call on a connection, and any call whose prompt differs
from the instruction in force, starts an episode of the served task with that prompt.

Batches (`--batch-envs K` on the client): when the served policy can decode several
episodes in one call (`act_batch`, policies/base.py), the metadata says `"act_batch":
true` and a `dvla/batch` message carries K observations with each one's episode context
(the episodes are at different steps; openpi has no such message, so only our client
sends it). One `act_batch` call serves them all; its NFE is the passes of that call (the
client charges them to each of the K episodes, as the local batched loop does).
With `--max-batch B` the server batches across clients too (harness/serving/coalesce.py): calls
that arrive together, from any connections, share one act_batch call, and the replies
add the queue wait ("dvla/queue_time_s") and the decode's size ("dvla/batch_size").

Forward passes are counted with the runner's own hooks (harness/episode/nfe.py) around each
call and returned with it, with the policy's own time, so a remote row keeps honest NFE
and splits time into policy and transport. Every reply that reports passes also reports
their counted work under "dvla/work" (harness/episode/work.py: "flops", "query_tokens",
"kv_tokens", "kv_cached_tokens", integers or null for not measured); a call batched
across clients gives each request its rows' share of the work, as of the tokens. A bad message gets an error text back (the
protocol's way: openpi clients raise it) and the connection stays open; nothing is
unpickled; one policy call runs at a time (the NFE hooks count one call at a time).
"""

from __future__ import annotations

import hmac
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from http import HTTPStatus
from typing import Any

import gymnasium as gym
import numpy as np

from harness.episode.nfe import NFECounter
from harness.episode.work import WIRE_KEY, Work
from harness.serving.coalesce import Coalescer, checked_actions
from policies.base import EpisodeContext, Policy, can_batch
from policies.wire import MAX_MESSAGE_BYTES, WireError, pack, unpack

log = logging.getLogger("dvla_harness.serve")
PROTOCOL = "openpi-websocket/1"  # openpi's WebsocketPolicyServer message flow, msgpack-numpy
RESET = "dvla/reset"
BATCH = "dvla/batch"
PROMPT = "prompt"


@dataclass
class Served:
    """The policy a server serves, and what an episode of it looks like."""

    policy: Policy
    name: str
    params: str  # the validated params, JSON
    suite: str
    task: str
    instruction: str
    max_steps: int
    observation_space: gym.spaces.Space
    action_space: gym.spaces.Box
    state_key: str = "state"
    token: str | None = field(default=None, repr=False)  # never printed
    max_batch: int = 1  # > 1: coalesce concurrent clients' calls (harness/serving/coalesce.py)
    batch_wait_s: float = 0.005
    counter: NFECounter = field(init=False)
    lock: threading.Lock = field(default_factory=threading.Lock)
    coalescer: Coalescer | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.counter = NFECounter(self.policy)
        if self.max_batch > 1:
            if not can_batch(self.policy):
                raise ValueError(
                    f"{self.name} cannot decode a batch (no act_batch): serve it with --max-batch 1"
                )
            act_batch = self.policy.act_batch  # type: ignore[attr-defined]
            self.coalescer = Coalescer(self.call, act_batch, self.max_batch, self.batch_wait_s)

    @cached_property
    def metadata(self) -> dict[str, Any]:
        """What the policy takes and returns, sent on connect and checked on every call:
        built once."""
        images = {}
        if isinstance(self.observation_space, gym.spaces.Dict):
            images = {k: list(s.shape) for k, s in self.observation_space.spaces.items() if k != "state"}
        state = self.observation_space["state"] if images else self.observation_space
        return {
            "server": "dvla-harness",
            "protocol": PROTOCOL,
            "policy": self.name,
            "params": json.loads(self.params),
            "suite": self.suite,
            "task": self.task,
            "observation": {"state_key": self.state_key, "state_shape": list(state.shape), "images": images},
            "action": {
                "dim": int(self.action_space.shape[0]),
                "low": np.asarray(self.action_space.low, np.float32),
                "high": np.asarray(self.action_space.high, np.float32),
            },
            "reports_nfe": True,
            "act_batch": can_batch(self.policy),
            "max_batch": self.max_batch,
        }

    def context(self, values: dict[str, Any]) -> EpisodeContext:
        def number(key: str, default: int | None) -> int | None:
            value = values.get(key, default)
            if value is not None and not isinstance(value, int | np.integer):
                raise WireError(f"{RESET}: {key} must be an integer, got {value!r}")
            return None if value is None else int(value)

        instruction = values.get("instruction", self.instruction)
        if not isinstance(instruction, str):
            raise WireError(f"{RESET}: instruction must be text, got {type(instruction).__name__}")
        return EpisodeContext(
            suite=self.suite,
            task=str(values.get("task", self.task)),
            instruction=instruction,
            action_space=self.action_space,
            observation_space=self.observation_space,
            max_steps=number("max_steps", self.max_steps) or self.max_steps,
            episode_index=number("episode_index", 0) or 0,
            seed=number("seed", None),
            init_state_id=number("init_state_id", None),
            subtask_index=number("subtask_index", 0) or 0,
        )

    def observation(self, message: dict[str, Any]) -> Any:
        """The policy's observation from a message: the state array (and images)."""
        state = message.get(self.state_key)
        if not isinstance(state, np.ndarray):
            raise WireError(
                f"no {self.state_key!r} array in the observation (keys: {sorted(map(str, message))})"
            )
        expected = self.metadata["observation"]
        if list(state.shape) != expected["state_shape"]:
            raise WireError(
                f"{self.state_key!r} has shape {list(state.shape)}, the policy takes {expected['state_shape']}"
            )
        if not np.issubdtype(state.dtype, np.number) or not np.isfinite(state).all():
            raise WireError(f"{self.state_key!r} must be finite numbers")
        if not expected["images"]:
            return state.astype(np.float32)
        out: dict[str, Any] = {"state": state.astype(np.float32)}
        for key, shape in expected["images"].items():
            image = message.get(key)
            if not isinstance(image, np.ndarray) or list(image.shape) != shape:
                raise WireError(f"image {key!r} must be an array of shape {shape}")
            out[key] = image.astype(np.uint8)
        return out

    def call(self, fn: Callable[[], Any]) -> tuple[Any, int, float, Work]:
        """Run one policy call under the NFE hooks: (result, passes, seconds, work)."""
        with self.lock:
            start = time.perf_counter()
            self.counter.take_work()
            with self.counter.counting():
                result = fn()
            seconds = time.perf_counter() - start
            return result, self.counter.take(), seconds, self.counter.take_work()


class Session:
    """One client connection: the episode in force on it."""

    def __init__(self, served: Served):
        self.served = served
        self.context: EpisodeContext | None = None

    def reset(self, values: dict[str, Any]) -> dict[str, Any]:
        context = self.served.context(values)
        _, nfe, seconds, work = self.served.call(lambda: self.served.policy.reset([context]))
        self.context = context
        return {"dvla/ok": True, "dvla/nfe": nfe, WIRE_KEY: work.to_wire(), "dvla/policy_time_s": seconds}

    def decode(self, contexts: list[EpisodeContext], observations: list[Any], single: bool) -> dict[str, Any]:
        """Chunks for the rows: through the coalescer when the server batches clients
        together, else in one call of this connection's own."""
        served = self.served
        extra: dict[str, Any] = {}
        if served.coalescer is not None:
            request = served.coalescer.submit(contexts, observations, client=id(self))
            actions, nfe, seconds, tokens, work = (
                request.actions,
                request.nfe,
                request.policy_time_s,
                request.action_tokens,
                request.work,
            )
            extra = {"dvla/queue_time_s": request.queue_time_s, "dvla/batch_size": request.call_rows}
        else:
            if single:
                batch, nfe, seconds, work = served.call(lambda: served.policy.act(observations))
            else:
                act_batch = served.policy.act_batch  # type: ignore[attr-defined]
                batch, nfe, seconds, work = served.call(lambda: act_batch(contexts, observations))
                extra = {"dvla/batch_size": len(observations)}
            actions, tokens = checked_actions(batch.actions, len(observations)), int(batch.action_tokens)
        return {
            "actions": actions[0] if single else actions,
            "dvla/nfe": nfe,
            WIRE_KEY: work.to_wire(),
            "dvla/policy_time_s": seconds,
            "dvla/action_tokens": tokens,
            "server_timing": {"infer_ms": 1000 * seconds},
            **extra,
        }

    def batch(self, values: Any) -> dict[str, Any]:
        """K episodes' observations in one act_batch call (the client's --batch-envs)."""
        if not self.served.metadata["act_batch"]:
            raise WireError(f"{self.served.name} cannot decode a batch (no act_batch); send one observation")
        if not isinstance(values, dict):
            raise WireError(f"{BATCH} must be a map with 'episodes' and 'observations'")
        episodes, observations = values.get("episodes"), values.get("observations")
        if not isinstance(episodes, list) or not isinstance(observations, list):
            raise WireError(f"{BATCH} needs lists 'episodes' and 'observations'")
        if not observations or len(episodes) != len(observations):
            raise WireError(
                f"{BATCH}: {len(episodes)} episodes and {len(observations)} observations (one each, at least one)"
            )
        for value in episodes + observations:
            if not isinstance(value, dict):
                raise WireError(f"{BATCH}: every episode and observation must be a map")
        contexts = [self.served.context(e) for e in episodes]
        return self.decode(contexts, [self.served.observation(o) for o in observations], single=False)

    def handle(self, message: Any) -> dict[str, Any]:
        if not isinstance(message, dict):
            raise WireError(f"a message must be a map, got {type(message).__name__}")
        if BATCH in message:
            return self.batch(message[BATCH])
        if RESET in message:
            if not isinstance(message[RESET], dict):
                raise WireError(f"{RESET} must be a map of the episode's context")
            return self.reset(message[RESET])
        prompt = message.get(PROMPT)
        if prompt is not None and not isinstance(prompt, str):
            raise WireError(f"{PROMPT!r} must be text")
        started: dict[str, Any] = {}
        if self.context is None or (prompt is not None and prompt != self.context.instruction):
            # a client without resets (openpi's): a new prompt is a new episode
            started = self.reset({"instruction": prompt} if prompt is not None else {})
        observation = self.served.observation(message)
        assert self.context is not None
        reply = self.decode([self.context], [observation], single=True)
        if not started:
            return reply
        return reply | {"dvla/reset_nfe": started["dvla/nfe"], "dvla/reset_work": started[WIRE_KEY]}


def _authorised(served: Served, request: Any) -> bool:
    if not served.token:
        return True
    header = request.headers.get("Authorization", "")
    return hmac.compare_digest(header.encode(), f"Api-Key {served.token}".encode())


def handler(served: Served, open_connections: set[Any] | None = None) -> Callable[[Any], None]:
    """The per-connection loop; `open_connections` (if given) holds the live ones, so that
    stopping the server can close them (their threads would keep the process alive)."""
    live: set[Any] = set() if open_connections is None else open_connections

    def handle(connection: Any) -> None:
        from websockets.exceptions import ConnectionClosed

        session = Session(served)
        address = connection.remote_address  # read now: a dropped socket has none
        live.add(connection)
        try:
            serve_connection(connection, session)
        except ConnectionClosed:  # a client process that exited without closing: not an error
            log.info("%s went away without closing", address)
        finally:
            live.discard(connection)
            if served.coalescer is not None:
                served.coalescer.gone(id(session))

    def serve_connection(connection: Any, session: Session) -> None:
        connection.send(pack(served.metadata))
        for data in connection:
            try:
                reply = pack(session.handle(unpack(data)))
            except WireError as exc:
                log.warning("rejected a message from %s: %s", connection.remote_address, exc)
                connection.send(f"bad request: {exc}")
                continue
            except Exception as exc:  # the policy failed: say so, keep serving
                log.exception("policy call failed")
                connection.send(f"policy error: {type(exc).__name__}: {exc}")
                continue
            connection.send(reply)

    return handle


Dialect = Callable[[Served, set[Any]], Callable[[Any], None]]


def make_server(
    served: Served,
    host: str = "127.0.0.1",
    port: int = 8000,
    dialect: Dialect | None = None,
    ping_interval: float | None = 20.0,
) -> Any:
    """A websockets server (call `serve_forever()`, `shutdown()`); port 0 picks a free one.
    `dialect` makes each connection's loop (harness/serving/vlaeval.py's for vla-eval's
    protocol); openpi's by default. `ping_interval` None sends no keepalive pings (a
    vla-eval client answers them only between simulator calls, which can take minutes).
    `GET /health` answers 200 once the policy is loaded (vla-eval's readiness probe),
    without a key."""
    from websockets.sync.server import serve

    def process_request(connection: Any, request: Any) -> Any:
        if request.path == "/health":
            response = connection.respond(HTTPStatus.OK, '{"status": "ok"}\n')
            del response.headers["Content-Type"]  # Headers keep every value set: replace, not add
            response.headers["Content-Type"] = "application/json"
            return response
        if not _authorised(served, request):
            log.warning("refused a connection from %s: wrong or missing token", connection.remote_address)
            return connection.respond(HTTPStatus.UNAUTHORIZED, "wrong or missing token\n")
        return None

    live: set[Any] = set()
    server = serve(
        (dialect or handler)(served, live),
        host,
        port,
        process_request=process_request,
        max_size=MAX_MESSAGE_BYTES,
        compression=None,
        ping_interval=ping_interval,
    )
    server.open_connections = live  # stop_server closes them
    return server


def stop_server(server: Any) -> None:
    """Stop accepting, then close every client's connection (each client sees a close and
    connects again for its next episode), so the process can exit with clients attached:
    some websockets versions close them in `shutdown` itself, not all."""
    server.shutdown()
    for connection in list(getattr(server, "open_connections", ())):
        try:
            connection.close()
        except Exception:
            pass  # already gone
