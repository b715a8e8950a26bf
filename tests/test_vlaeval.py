"""The `vlaeval` policy against vla-eval's own model-server classes (the `vla-eval`
package's PredictModelServer, served by its own `serve_background`), and against small
servers that speak its protocol badly on purpose: no hello, a reply to the wrong
message, garbage, an error, an oversized frame, a server that dies mid-episode."""

from __future__ import annotations

import dataclasses
import re
import threading
import time
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("vla_eval")
pytest.importorskip("websockets")

from vla_eval.api import serve_background
from vla_eval.model_servers.predict import PredictModelServer
from websockets.sync.server import serve

from policies.base import EpisodeContext
from policies.remote import ConnectionLost
from policies.vlaeval import ServerError, VlaEvalParams, VlaEvalPolicy
from policies.vlaeval_wire import pack, unpack
from policies.wire import MAX_MESSAGE_BYTES, WireError

SUITE = "libero/spatial:obs=upstream,seeding=openpi"
PIXELS = gym.spaces.Box(0, 255, (256, 256, 3), np.uint8)
UPSTREAM = gym.spaces.Dict(
    {"state": gym.spaces.Box(-np.inf, np.inf, (8,), np.float32), "agentview": PIXELS, "wrist": PIXELS}
)
ACTIONS = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
# LIBERO's start pose: the hand's quaternion has w just below 0, so robosuite's axis-angle
# (this harness's state) has an angle just over pi, which vla-eval folds by default
START_ROTATION = np.array([np.pi + 0.0004, 0.0, 0.0])


def _context(index: int = 0, task: str = "elsewhere", instruction: str = "put the bowl on the plate"):
    return EpisodeContext(SUITE, task, instruction, ACTIONS, UPSTREAM, 220, index, 7, index)


def _observation(step: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(step)
    state = np.concatenate([[0.1, 0.2, 1.0 + step], START_ROTATION, [0.04, -0.04]]).astype(np.float32)
    return {
        "state": state,
        "agentview": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
        "wrist": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
    }


class Chunks(PredictModelServer):
    """A vla-eval model server whose chunk of 3 says which call made it: the server
    buffers it and hands out one action per observation."""

    def __init__(self, observation_params: dict[str, Any]):
        super().__init__(chunk_size=3)
        self.params, self.seen, self.starts, self.ends = observation_params, [], [], []

    def get_observation_params(self) -> dict[str, Any]:
        return self.params

    def predict(self, obs: dict[str, Any], ctx: Any) -> dict[str, Any]:
        self.seen.append(obs)
        chunk = np.tile(np.linspace(-0.3, 0.3, 7, dtype=np.float32), (3, 1)) + 0.01 * len(self.seen)
        chunk[:, 6] = [0.2, -0.2, 0.0]  # the gripper: LIBERO executes its sign, 0 as close
        return {"actions": chunk}

    async def on_episode_start(self, config: dict[str, Any], ctx: Any) -> None:
        self.starts.append(config)
        await super().on_episode_start(config, ctx)

    async def on_episode_end(self, result: dict[str, Any], ctx: Any) -> None:
        self.ends.append(result)
        await super().on_episode_end(result, ctx)


def _eventually(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "the server never got there"
        time.sleep(0.01)


@pytest.fixture
def vla_eval_server():
    handles = []

    def start(**observation_params: Any) -> tuple[Chunks, str]:
        model = Chunks(observation_params)
        handles.append(serve_background(model))
        return model, handles[-1].url

    yield start
    for handle in handles:
        handle.close()


@pytest.mark.libero  # the episode's task index comes from LIBERO's task list
@pytest.mark.parametrize("unfolded", [False, True])
def test_a_vla_eval_model_server_is_evaluated_one_action_per_observation(vla_eval_server, unfolded):
    from adapters.registry import load_suite

    params = {"send_state": True, "send_wrist_image": True} | (
        {"quat_no_antipodal": True} if unfolded else {}
    )
    model, url = vla_eval_server(**params)
    policy = VlaEvalPolicy(VlaEvalParams(url=url))
    policy.check_spaces(UPSTREAM, ACTIONS)
    task = load_suite(SUITE).tasks[3]
    policy.reset([_context(4, task.name, task.instruction)])
    executed = [policy.act([_observation(step)]).actions[0, 0] for step in range(4)]
    served = policy.take_served()
    assert served.nfe is None and served.work.flops is None  # a vla-eval server reports no passes
    policy.reset([_context(5, task.name, task.instruction)])
    policy.close()  # ends the second episode too
    _eventually(lambda: len(model.ends) == 2)  # messages without a reply are handled in the background

    assert model.starts[0] == {
        "task": {"name": task.instruction, "suite": "libero_spatial", "task_id": 3, "episode_idx": 4}
    }
    assert (
        model.ends == [{"steps": 4}, {"steps": 0}] and len(model.starts) == 2
    )  # each episode ended when the next began, or the run ended
    assert len(model.seen) == 2  # 4 steps from chunks of 3: two predictions
    for step, obs in zip((0, 3), model.seen, strict=True):
        sent = _observation(step)
        np.testing.assert_array_equal(obs["images"]["agentview"], sent["agentview"])  # PNG: lossless
        np.testing.assert_array_equal(obs["images"]["wrist"], sent["wrist"])
        assert obs["task_description"] == task.instruction
        rotation = obs["states"][3:6]
        if unfolded:
            np.testing.assert_array_equal(obs["states"], sent["state"].astype(np.float64))
        else:  # the same rotation, the angle 2 pi - angle about the opposite axis
            np.testing.assert_allclose(rotation, [-(np.pi - 0.0004), 0, 0], atol=1e-6)
    first = np.linspace(-0.3, 0.3, 7) + 0.01
    np.testing.assert_allclose(executed[0][:6], first[:6], atol=1e-6)
    np.testing.assert_allclose(executed[3][:6], first[:6] + 0.01, atol=1e-6)
    assert [a[6] for a in executed] == [1.0, -1.0, 1.0, 1.0]  # binarised by sign, 0 -> +1


@pytest.mark.libero
def test_a_worker_processs_policy_sends_what_the_server_asks_without_a_check(vla_eval_server):
    model, url = vla_eval_server(send_state=True, quat_no_antipodal=True)
    policy = VlaEvalPolicy(VlaEvalParams(url=url))  # `run --workers N` checks the parent's policy only
    policy.reset([_context()])
    policy.act([_observation(0)])
    policy.close()
    np.testing.assert_array_equal(model.seen[-1]["states"], _observation(0)["state"].astype(np.float64))
    assert set(model.seen[-1]["images"]) == {"agentview"}  # no send_wrist_image


def test_simpler_and_calvin_observations_carry_their_benchmarks_keys(vla_eval_server):
    model, url = vla_eval_server(send_wrist_image=True)
    simpler_space = gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (30,)), "base_camera": PIXELS})
    simpler = VlaEvalPolicy(VlaEvalParams(url=url))  # auto: a base_camera makes it SimplerEnv's
    simpler.check_spaces(simpler_space, ACTIONS)
    context = EpisodeContext(
        "simpler/push_cube:obs=images", "push_cube", "push the cube", ACTIONS, simpler_space, 50, 3, 11
    )
    simpler.reset([context])
    camera = _observation(0)["agentview"]
    simpler.act([{"state": np.zeros(30, np.float32), "base_camera": camera}])
    simpler.close()
    assert model.starts[-1] == {"task": {"name": "push_cube", "task_name": "push_cube", "episode_idx": 3}}
    assert set(model.seen[-1]) == {"images", "task_description", "task_name"}
    np.testing.assert_array_equal(model.seen[-1]["images"]["primary"], camera)

    calvin = VlaEvalPolicy(VlaEvalParams(url=url, benchmark="calvin"))
    calvin.check_spaces(UPSTREAM, ACTIONS)
    chain = EpisodeContext(
        "chains/kitchen:obs=upstream", "kitchen", "open the drawer", ACTIONS, UPSTREAM, 600, 2
    )
    calvin.reset([chain])
    for step in range(4):  # the second subtask starts at step 3: the same episode, restarted there
        if step == 3:
            calvin.reset([dataclasses.replace(chain, instruction="close the drawer", subtask_index=1)])
        calvin.act([_observation(step)])
    calvin.close()
    _eventually(lambda: len(model.ends) == 2)
    assert model.starts[-1] == {"task": {"name": "kitchen", "seq_idx": 2, "episode_idx": 2}}
    assert len(model.starts) == 2 and model.ends[-1] == {"steps": 4}  # one episode for the whole chain
    first, restarted = model.seen[-2], model.seen[-1]  # a chunk of 3: predictions at steps 0 and 3
    assert set(first["images"]) == {"rgb_static", "rgb_gripper"} and "episode_restart" not in first
    assert restarted["episode_restart"] is True and restarted["task_description"] == "close the drawer"


def test_what_the_server_asks_for_is_checked_before_anything_runs(vla_eval_server):
    _, url = vla_eval_server(absolute_action=True)
    with pytest.raises(ValueError, match="absolute_action=True; this harness's LIBERO protocol fixes"):
        VlaEvalPolicy(VlaEvalParams(url=url)).check_spaces(UPSTREAM, ACTIONS)
    _, url = vla_eval_server(send_state=True)
    simpler = gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (30,)), "base_camera": PIXELS})
    with pytest.raises(ValueError, match="asks for vla-eval's simpler state"):
        VlaEvalPolicy(VlaEvalParams(url=url)).check_spaces(simpler, ACTIONS)
    policy = VlaEvalPolicy(VlaEvalParams(url=url, benchmark="calvin"))
    with pytest.raises(ValueError, match="asks for vla-eval's calvin state"):
        policy.check_spaces(UPSTREAM, ACTIONS)


@pytest.mark.parametrize(
    ("space", "needle"),
    [
        (
            gym.spaces.Box(-1, 1, (39,)),
            "suites with a vla-eval observation: libero: libero/<suite>:obs=upstream",
        ),
        (
            gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (44,)), "agentview": PIXELS, "wrist": PIXELS}),
            "this suite's is [44]-D (privileged state); suites with a vla-eval observation: libero",
        ),
        (
            gym.spaces.Dict(
                {
                    "state": UPSTREAM["state"],
                    "agentview": gym.spaces.Box(0, 255, (128, 128, 3)),
                    "wrist": PIXELS,
                }
            ),
            "renders 256 px images; this suite's agentview is 128 x 128; suites with",
        ),
    ],
)
def test_a_suite_without_a_vla_eval_observation_is_refused(space, needle):
    policy = VlaEvalPolicy(VlaEvalParams(url="ws://127.0.0.1:9"))  # refused before it connects
    with pytest.raises(ValueError, match=re.escape(needle)):
        policy.check_spaces(space, ACTIONS)


@pytest.mark.metaworld  # the suite is built to read its spaces
def test_run_refuses_a_suite_without_one_before_it_writes(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "vlaeval:url=ws://127.0.0.1:9",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 2 and "suites with a vla-eval observation" in err
    assert not out.exists()


# --- servers that get the protocol wrong ---------------------------------------------------


def _speaking(answer) -> tuple[Any, str]:
    """A server of vla-eval's protocol whose replies come from answer(connection, message):
    bytes to send, None to send nothing, or "close" to drop the connection."""
    connections = [0]

    def handle(ws) -> None:
        connections[0] += 1
        for data in ws:
            message = unpack(data)
            reply = answer(connections[0], message)
            if reply == "close":
                ws.close()
                return
            if reply is not None:
                ws.send(reply)

    server = serve(handle, "127.0.0.1", 0, compression=None, max_size=None)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"ws://127.0.0.1:{server.socket.getsockname()[1]}"


def _well(connection: int, message) -> bytes | None:
    if message.type == "hello":
        return pack("hello", {"protocol_version": 1, "observation_params": {"send_state": True}}, message.seq)
    if message.type == "observation":
        return pack("action", {"actions": np.zeros(7, np.float32)}, message.seq)
    return None


def _started(url: str, **params: Any) -> VlaEvalPolicy:
    policy = VlaEvalPolicy(VlaEvalParams(url=url, timeout_s=2.0, retries=1, reconnect_s=3.0, **params))
    policy.check_spaces(UPSTREAM, ACTIONS)
    policy.reset([_context()])
    return policy


@pytest.fixture
def speaking():
    servers = []

    def start(answer):
        server, url = _speaking(answer)
        servers.append(server)
        return url

    yield start
    for server in servers:
        server.shutdown()


def test_a_server_that_never_says_hello_is_refused_before_the_run(speaking):
    url = speaking(lambda connection, message: None)
    policy = VlaEvalPolicy(VlaEvalParams(url=url, timeout_s=0.5, retries=2))
    with pytest.raises(ValueError, match=r"no connection after 2 attempts.*no reply within 0.5 s"):
        policy.check_spaces(UPSTREAM, ACTIONS)
    url = speaking(lambda connection, message: pack("action", {}, message.seq))
    with pytest.raises(ValueError, match="answered message 1 with 'action', not 'hello'"):
        VlaEvalPolicy(VlaEvalParams(url=url, retries=1)).check_spaces(UPSTREAM, ACTIONS)


BAD_REPLIES = [  # (reply to the first observation, error, message, whether the connection is dropped)
    (
        lambda m: pack("action", {"actions": np.zeros(7)}, m.seq - 1),
        WireError,
        "answered message 2 .* 3 waited",
        True,
    ),
    (lambda m: pack("action", {"actions": np.zeros(7)}, m.seq + 5), WireError, "answered message 8", True),
    (lambda m: b"\xc1 garbage", WireError, "not a msgpack message", True),
    (lambda m: pack("hello", {}, m.seq), WireError, "with 'hello', not 'action'", True),
    (lambda m: b"\x00" * (MAX_MESSAGE_BYTES + 1), ConnectionError, "over the 67108864-byte limit", True),
    # in step with the server, but no action to execute: the connection is kept
    (
        lambda m: pack("action", {"actions": np.zeros((5, 7))}, m.seq),
        WireError,
        "one action per observation",
        False,
    ),
    (lambda m: pack("action", {"actions": np.full(7, np.nan)}, m.seq), WireError, "not finite", False),
    (lambda m: pack("action", {"other": 1}, m.seq), WireError, "has no 'actions'", False),
]


@pytest.mark.libero
@pytest.mark.parametrize(
    ("reply", "error", "needle", "dropped"), BAD_REPLIES, ids=[b[2] for b in BAD_REPLIES]
)
def test_a_bad_reply_fails_the_episode_and_the_next_one_runs(speaking, reply, error, needle, dropped):
    observations: list[int] = []

    def answer(connection: int, message):
        if message.type == "observation":
            observations.append(connection)
            if len(observations) == 1:
                return reply(message)
        return _well(connection, message)

    policy = _started(speaking(answer))
    with pytest.raises(error, match=needle):
        policy.act([_observation(0)])
    # a reply out of step is never read as a later step's: that connection is dropped
    policy.reset([_context(1)])
    assert policy.act([_observation(1)]).actions.shape == (1, 1, 7)
    assert observations == [1, 2 if dropped else 1]


@pytest.mark.libero
def test_an_error_reply_fails_the_step_and_keeps_the_connection(speaking):
    def answer(connection: int, message):
        if message.type == "observation" and message.payload["states"][2] == 1.0:
            return pack("error", {"error": "observation_failed: RuntimeError: out of memory"}, message.seq)
        return _well(connection, message)

    policy = _started(speaking(answer))
    with pytest.raises(
        ServerError, match="the model server failed: observation_failed: RuntimeError: out of memory"
    ):
        policy.act([_observation(0)])
    assert policy._ws is not None and policy.act([_observation(1)]).actions.shape == (1, 1, 7)


@pytest.mark.libero
def test_a_server_that_dies_mid_episode_fails_it_and_the_next_episode_reconnects(speaking):
    seen: list[tuple[int, str]] = []

    def answer(connection: int, message):
        seen.append((connection, message.type))
        if (
            connection == 1
            and message.type == "observation"
            and sum(t == "observation" for _, t in seen) == 3
        ):
            return "close"
        return _well(connection, message)

    policy = _started(speaking(answer))
    policy.act([_observation(0)])
    policy.act([_observation(1)])
    with pytest.raises(ConnectionLost, match="closed the connection"):
        policy.act([_observation(2)])
    policy.reset([_context(1)])  # reconnects: hello again, then the new episode
    policy.act([_observation(0)])
    assert [t for c, t in seen if c == 2] == ["hello", "episode_start", "observation"]
