"""The `remote` policy: a model served anywhere, over openpi's WebSocket policy protocol.

`--policy remote:url=ws://HOST:PORT` evaluates a policy behind a server: `dvla-harness
serve` (any registered policy), openpi's `serve_policy` script, or anything that speaks
the same protocol (metadata on connect, one msgpack message with numpy arrays per call,
a map with the actions back; policies/wire.py). The suite's observation goes out under
`state_key` (and each camera under its own name) with the instruction under
`prompt_key`; the reply's `actions_key` holds one action or a chunk of them.

What is counted, and by whom: forward passes happen on the server, so the harness's
hooks there count them (a dvla-harness server returns them with every reply, and the
policy's own time); the runner keeps that NFE and splits each call's time into the
server's policy time and transport (`transport_time_s`). A server that reports no NFE
(openpi's) gives NFE as null, never 0. The passes' counted work (FLOPs, positions
attended; harness/episode/work.py) comes the same way, under "dvla/work"; a reply without it
leaves the episode's work null, not measured.

Reliability: every receive has a timeout (`timeout_s`), so a server that stops answering
fails that episode instead of hanging the run. Before anything runs, `check_spaces`
connects (`retries` attempts: a wrong address is refused in a second) and compares the
server's metadata (when it describes its observation and action) with the suite's, so a
mismatch is a usage error (exit 2) with nothing written. Once the run is going, a server
that goes away (a crash, a restart that takes seconds to reload its model) fails the
episode in flight with `ConnectionLost`, and the next episode keeps trying to connect,
with back-off, for `reconnect_s` seconds before it fails with `ConnectionLost` too; that
wait is neither policy nor env time (`take_served`), and a plain `--resume` runs
`ConnectionLost` rows again (harness/run/resume.py), as it does episodes of lost workers.

Keys: a server that wants one (`serve --token-env`, openpi's `api_key`) gets it in
openpi's header, read from an environment variable (`token_env=NAME`) or a file
(`token_file=PATH`) at every connection. Where the key comes from is no part of the
configuration (`identity=False`: not in the rows, the config id or resume's match), so a
rotated key resumes the same run; an inline `token=`, a password in the url or a
credential in its query (`?api_key=`) is refused, since the manifest records the config
and the command line.

What a server reports (NFE, counted work, tokens, its own time) is checked before it
enters a row: a figure that is not a count in range fails the episode naming the value.

Batches: with `--batch-envs K`, a server whose metadata says `"act_batch": true` (a
dvla-harness server serving a decoder) gets the K observations, each with its episode's
context, in one `dvla/batch` message and decodes them in one call; its NFE is charged to
each of the K episodes and its policy time shared among them, as the local batched loop
does. Against any other server `--batch-envs K > 1` is refused before anything runs.
"""

from __future__ import annotations

import importlib.util
import math
import numbers
import os
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import gymnasium as gym
import numpy as np

from harness.episode.timed import ServedTotals
from harness.episode.work import WIRE_KEY as WORK_KEY
from harness.episode.work import Work
from harness.plugins import install_hint
from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.spec import PolicySpec, param

RESET = "dvla/reset"
BATCH = "dvla/batch"
# The most one reply may report. A chunk decoded in a million forward passes is no
# measurement, and 2**53 (FLOPs, positions, tokens) is the largest integer every JSON
# reader keeps exactly; past these a server's figure would only corrupt the run's totals.
MAX_REPORTED_PASSES = 1_000_000
MAX_REPORTED_COUNT = 2**53
# Query parameter names that carry a credential (api_key=, token=, sig=, password=...):
# the url is recorded in the manifest and every row.
_CREDENTIAL = re.compile(r"key|token|secret|pass|auth|sig|credential|session|jwt|bearer", re.IGNORECASE)


@dataclass(frozen=True)
class ConnectionParams:
    """How to reach a policy server, shared by the remote policies of every protocol."""

    url: str = param("ws://127.0.0.1:8000", "the server's address (ws:// or wss://)")
    token: str = param("", "refused: a key typed here would be recorded; use token_env or token_file")
    token_env: str = param(
        "", "environment variable holding the API key (never recorded; openpi's header)", identity=False
    )
    token_file: str = param("", "file holding the API key (never recorded)", identity=False)
    timeout_s: float = param(30.0, "seconds to wait for the server's reply before the episode fails", low=0.1)
    connect_timeout_s: float = param(10.0, "seconds to wait for a connection", low=0.1)
    retries: int = param(
        3, "connection attempts before the run starts, with doubling back-off", low=1, high=20
    )
    reconnect_s: float = param(
        60.0,
        "seconds an episode keeps trying to reconnect, with back-off, to a server that went away "
        "(a restart) before it fails",
        low=0.0,
        high=86400.0,
        identity=False,  # how long to wait is no part of what is evaluated
    )

    def validate(self) -> None:
        """A key, or a password in the address, given inline would be written into the
        manifest (its config and command line) and, for the address, every row."""
        if self.token:
            raise ValueError(
                "an inline token= would be recorded in the run's manifest; put the key in an "
                "environment variable (token_env=NAME) or a file (token_file=PATH)"
            )
        if self.token_env and self.token_file:
            raise ValueError("token_env and token_file are both given; pick one")
        parts = urlsplit(self.url)
        if parts.password is not None:
            raise ValueError(
                "the url carries a password (user:password@), which every row would record; "
                "pass the key with token_env or token_file"
            )
        named = [
            name for name, _ in parse_qsl(parts.query, keep_blank_values=True) if _CREDENTIAL.search(name)
        ]
        if named:
            raise ValueError(
                f"the url carries a credential in its query ({named[0]}=...), which the manifest and "
                "every row would record; pass the key with token_env or token_file"
            )


@dataclass(frozen=True)
class RemoteParams(ConnectionParams):
    state_key: str = param("state", "observation key of the state vector on the wire")
    prompt_key: str = param("prompt", "observation key of the instruction on the wire")
    actions_key: str = param("actions", "reply key of the action (or action chunk)")


def read_api_key(env: str, path: str, *, env_flag: str = "token_env", file_flag: str = "token_file") -> str:
    """The API key from an environment variable or a file ('' when neither is named).

    Read where it is used, never stored in the parameters: so it is in no results file,
    and a rotated key is picked up at the next connection. Messages name the variable
    or file, never the key."""
    if env:
        if env not in os.environ:
            raise ValueError(f"{env_flag}: the environment variable {env} is not set")
        key, source = os.environ[env].strip(), f"{env_flag}: the environment variable {env}"
    elif path:
        try:
            key, source = Path(path).read_text().strip(), f"{file_flag} {path!r}"
        except OSError as exc:
            raise ValueError(f"{file_flag} {path!r} cannot be read: {exc.strerror or exc}") from None
        except UnicodeDecodeError:
            raise ValueError(f"{file_flag} {path!r} is not text") from None
    else:
        return ""
    if not key:
        raise ValueError(f"{source} is empty")
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in key):
        raise ValueError(f"{source} holds more than one line or control characters; a key is one line")
    return key


class ConnectionLost(ConnectionError):
    """The connection to the server was lost, or could not be made again within
    `reconnect_s`: the server's trouble, not the policy's (a plain --resume runs the
    episode again)."""


BACK_OFF_MAX_S = 5.0  # the longest pause between two connection attempts


class RemotePolicy:
    def __init__(self, params: RemoteParams | ConnectionParams):
        if not params.url.startswith(("ws://", "wss://")):
            raise ValueError(f"url must start with ws:// or wss://, got {params.url!r}")
        if importlib.util.find_spec("msgpack") is None:
            raise ValueError(f"it needs msgpack: {install_hint('remote')}")
        self.params = params
        self._headers()  # a missing or empty key is refused before anything runs
        self._ws: Any = None
        self.metadata: dict[str, Any] = {}
        self._contexts: Sequence[EpisodeContext] = ()
        self._totals = ServedTotals()

    # --- connection ----------------------------------------------------------------

    def _connect(self, window: float | None = None) -> None:
        """Connect: `retries` attempts (before the run starts), or with `window` seconds,
        as many attempts as fit in it (at least `retries`), back-off doubling from 0.25 s
        up to BACK_OFF_MAX_S; ConnectionLost when none succeeds."""
        from policies.wire import MAX_MESSAGE_BYTES, WireError
        from policies.wsclient import HandshakeRefused, WebSocket

        headers = self._headers()
        delay, last, attempt = 0.25, None, 0
        start = time.monotonic()
        end = start + (window or 0.0)
        while True:
            attempt += 1
            try:
                self._ws = WebSocket(
                    self.params.url,
                    headers=headers,
                    open_timeout=self.params.connect_timeout_s,
                    max_size=MAX_MESSAGE_BYTES,
                )
                self.metadata = self._handshake()
                return
            except HandshakeRefused as exc:  # e.g. 401 (a wrong token): no point retrying
                self.close()
                raise ConnectionError(f"{self.params.url}: {exc}") from None
            except (OSError, WireError) as exc:
                last = exc
                self.close()
            left = end - time.monotonic()
            if attempt >= self.params.retries and left <= 0:
                break
            time.sleep(delay if attempt < self.params.retries else max(0.0, min(delay, left)))
            delay = min(delay * 2, BACK_OFF_MAX_S)
        within = f" in {time.monotonic() - start:.0f} s (reconnect_s={window:g})" if window else ""
        raise ConnectionLost(f"{self.params.url}: no connection after {attempt} attempts{within} ({last})")

    def _reconnect(self) -> None:
        """Connect again within an episode, the wait set aside from its policy time."""
        start = time.perf_counter()
        try:
            self._connect(self.params.reconnect_s)
        finally:
            self._totals.connect_wait_s += time.perf_counter() - start

    def _headers(self) -> dict[str, str] | None:
        """openpi's header (`Authorization: Api-Key KEY`), the key read now."""
        key = read_api_key(self.params.token_env, self.params.token_file)
        return {"Authorization": f"Api-Key {key}"} if key else None

    def _handshake(self) -> dict[str, Any]:
        """What a new connection starts with: openpi's server sends its metadata."""
        from policies.wire import WireError

        metadata = self._receive()
        if not isinstance(metadata, dict):
            raise WireError("the server's metadata is not a map")
        return metadata

    def _encode(self, message: dict[str, Any]) -> bytes:
        from policies.wire import pack

        return pack(message)

    def _decode(self, data: bytes | str) -> Any:
        from policies.wire import unpack

        return unpack(data)

    def _receive(self) -> Any:
        try:
            data = self._ws.recv(timeout=self.params.timeout_s)
        except TimeoutError:
            raise TimeoutError(f"{self.params.url}: no reply within {self.params.timeout_s} s") from None
        return self._decode(data)

    def _call(self, message: dict[str, Any]) -> dict[str, Any]:
        from policies.wire import WireError
        from policies.wsclient import ConnectionClosed, ProtocolError

        if self._ws is None:
            self._reconnect()
        try:
            self._ws.send(self._encode(message))
            reply = self._receive()
        except (TimeoutError, WireError):
            self.close()  # a late reply must not be read as the next call's
            raise
        except ProtocolError as exc:  # the server broke the protocol: its fault, not the network's
            self.close()
            raise ConnectionError(f"{self.params.url}: {exc}") from None
        except (ConnectionClosed, ConnectionError) as exc:  # closed, reset, a broken pipe
            self.close()  # the next episode connects again
            raise ConnectionLost(f"{self.params.url}: the server closed the connection ({exc})") from None
        if not isinstance(reply, dict):
            raise WireError(f"the server replied with {type(reply).__name__}, not a map")
        nfe = reported_count(reply, "dvla/nfe", MAX_REPORTED_PASSES)
        work = reported_work(reply)
        # a batching server's queue wait is the server's time too: transport stays transport
        seconds = reported_seconds(reply, "dvla/policy_time_s") + reported_seconds(reply, "dvla/queue_time_s")
        self._totals.nfe = None if nfe is None or self._totals.nfe is None else self._totals.nfe + nfe
        self._totals.work += work
        self._totals.server_time_s += seconds
        return reply

    def close(self) -> None:
        if self._ws is not None:
            self._ws.close()  # never raises, even when the connection is already gone
        self._ws = None

    # --- the policy contract -------------------------------------------------------

    def check_spaces(self, observation_space: gym.Space, action_space: gym.Space) -> None:
        """Refuse a server whose metadata describes another observation or action."""
        try:
            if self._ws is None:
                self._connect()
        except ConnectionError as exc:
            raise ValueError(str(exc)) from None
        described_obs = self.metadata.get("observation") or {}
        described_act = self.metadata.get("action") or {}
        state = (
            observation_space["state"]
            if isinstance(observation_space, gym.spaces.Dict)
            else observation_space
        )
        if "state_shape" in described_obs and list(described_obs["state_shape"]) != list(state.shape):
            raise ValueError(
                f"the server's policy takes a state of shape {list(described_obs['state_shape'])}, "
                f"this suite gives {list(state.shape)}"
            )
        if "state_key" in described_obs and described_obs["state_key"] != self.params.state_key:
            raise ValueError(
                f"the server reads the state under {described_obs['state_key']!r}; pass state_key="
                f"{described_obs['state_key']} (now {self.params.state_key!r})"
            )
        if "dim" in described_act and int(described_act["dim"]) != int(np.prod(action_space.shape)):
            raise ValueError(
                f"the server's policy returns {described_act['dim']}-D actions, this suite takes "
                f"{int(np.prod(action_space.shape))}-D"
            )

    @property
    def act_batch(self) -> Any:
        """`act_batch` when the server decodes batches, else None (so `can_batch` says no):
        asks the server (connects) the first time."""
        if self._ws is None and not self.metadata:
            self._connect()
        return self._act_batch if self.metadata.get("act_batch") is True else None

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        if len(episodes) != 1:
            raise ValueError("the remote policy starts one episode per reset call")
        self._contexts = episodes
        if self._ws is None:
            self._reconnect()
        if self.metadata.get("server") == "dvla-harness":  # openpi servers have no reset
            self._call({RESET: _context_map(episodes[0])})

    def _observation(self, obs: Observation) -> dict[str, Any]:
        if isinstance(obs, dict):
            message = {self.params.state_key: np.asarray(obs["state"], np.float32)}
            return message | {k: np.asarray(v) for k, v in obs.items() if k != "state"}
        return {self.params.state_key: np.asarray(obs, np.float32)}

    def _actions(self, reply: dict[str, Any], rows: int | None) -> np.ndarray:
        """The reply's actions as (rows, chunk, action_dim); rows None: one episode, whose
        reply may hold one action or one chunk."""
        from policies.wire import WireError

        if self.params.actions_key not in reply:
            raise WireError(f"the reply has no {self.params.actions_key!r} (keys: {sorted(map(str, reply))})")
        actions = np.asarray(reply[self.params.actions_key], dtype=np.float64)
        if rows is None:
            actions = actions[None] if actions.ndim == 1 else actions
            if actions.ndim != 2:
                raise WireError(f"actions of shape {actions.shape}; expected (chunk, action_dim)")
            actions = actions[None]
        elif actions.ndim != 3 or actions.shape[0] != rows:
            raise WireError(
                f"a batch of {rows} got actions of shape {actions.shape}; expected ({rows}, chunk, action_dim)"
            )
        bad = np.argwhere(~np.isfinite(actions))
        if len(bad):  # the shape was right: say so, and where the first bad value is
            first = tuple(int(i) for i in bad[0])
            at = list(first if rows else first[1:])
            raise WireError(
                f"actions of shape {actions.shape if rows else actions.shape[1:]} hold {len(bad)} "
                f"value(s) that are not finite ({actions[first]} at {at} first)"
            )
        return actions

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        message = {self.params.prompt_key: self._contexts[0].instruction} | self._observation(observations[0])
        reply = self._call(message)
        return ChunkBatch(actions=self._actions(reply, None), action_tokens=_tokens(reply))

    def _act_batch(
        self, episodes: Sequence[EpisodeContext], observations: Sequence[Observation]
    ) -> ChunkBatch:
        batch = {
            "episodes": [_context_map(ep) for ep in episodes],
            "observations": [
                {self.params.prompt_key: ep.instruction} | self._observation(obs)
                for ep, obs in zip(episodes, observations, strict=True)
            ],
        }
        reply = self._call({BATCH: batch})
        return ChunkBatch(actions=self._actions(reply, len(episodes)), action_tokens=_tokens(reply))

    @property
    def served_by(self) -> str:
        """Where its model runs, in words (for messages)."""
        return f"the server at {self.params.url}"

    def take_served(self) -> ServedTotals:
        """What the server reported since the last take: its passes, work and own time,
        and this client's waits to connect again (harness/episode/timed.py reads it after
        every call)."""
        totals, self._totals = self._totals, ServedTotals()
        return totals


def reported_count(reply: dict[str, Any], key: str, limit: int = MAX_REPORTED_COUNT) -> int | None:
    """A count the server reported under `key` (passes, tokens), None when it reports
    none; anything but an integer in [0, limit] fails the episode naming the value, which
    would otherwise enter the run's totals (a negative NFE, a NaN time)."""
    from policies.wire import WireError

    value = reply.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= value <= limit:
        raise WireError(f"the server reported {key} = {value!r}; expected an integer in [0, {limit}]")
    return int(value)


def reported_seconds(reply: dict[str, Any], key: str) -> float:
    """A time the server reported under `key` (0 when it reports none): finite, >= 0."""
    from policies.wire import WireError

    value = reply.get(key, 0.0)
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0:
        raise WireError(f"the server reported {key} = {value!r}; expected a number of seconds >= 0")
    return float(value)


def reported_work(reply: dict[str, Any]) -> Work:
    """The passes' counted work the server reported (harness/episode/work.py): absent, or
    a field null, is not measured; any other field must be a count."""
    from policies.wire import WireError

    value = reply.get(WORK_KEY)
    if value is None:
        return Work.from_wire(None)
    if not isinstance(value, dict):
        raise WireError(f"the server reported {WORK_KEY} = {value!r}; expected a map of counts")
    for f in fields(Work):
        reported_count(value, f.name)  # a bad field names its value (a WireError)
    return Work.from_wire(value)


def _tokens(reply: dict[str, Any]) -> int:
    return reported_count(reply, "dvla/action_tokens") or 0


def _context_map(ep: EpisodeContext) -> dict[str, Any]:
    """What a dvla-harness server needs of an episode's context (its reset message)."""
    return {
        "task": ep.task,
        "instruction": ep.instruction,
        "episode_index": ep.episode_index,
        "seed": ep.seed,
        "init_state_id": ep.init_state_id,
        "max_steps": ep.max_steps,
        "subtask_index": ep.subtask_index,
    }


REMOTE = PolicySpec(
    name="remote",
    summary="a policy served over openpi's WebSocket protocol (dvla-harness serve, openpi serve_policy)",
    params=RemoteParams,
    build=RemotePolicy,
    extra="remote",
)
