"""`dvla-harness serve` against openpi's own client (the real `openpi-client` package):
metadata, actions equal to the local policy's, NFE counted through the wire, tokens,
and bad input that is refused without stopping the server."""

from __future__ import annotations

import argparse
import threading

import numpy as np
import pytest

pytest.importorskip("websockets")
pytest.importorskip("msgpack")

from harness.commands.serve import build_served
from harness.serving.server import make_server
from policies.wire import WireError, pack, unpack

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

SUITE, TASK = "metaworld/mt10", "reach-v3"


def _served(policy: str = "fast_dvla", token: str | None = None):
    pytest.importorskip("metaworld")
    args = argparse.Namespace(policy=policy, suite=SUITE, task=TASK, state_key="state")
    return build_served(args, token)


@pytest.fixture
def server():
    """A real server on a free loopback port, in a thread; yields (served, port)."""
    started = []

    def start(policy: str = "fast_dvla", token: str | None = None):
        served = _served(policy, token)
        srv = make_server(served, "127.0.0.1", 0)
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        started.append(srv)
        return served, srv.socket.getsockname()[1]

    yield start
    for srv in started:
        srv.shutdown()


def _observation(seed: int = 0) -> np.ndarray:
    from adapters.registry import load_suite

    suite = load_suite(SUITE)
    task = suite.task(TASK)
    env = suite.make_env(task)
    try:
        obs, _ = env.reset(options={"episode": task.episodes[seed]})
    finally:
        env.close()
    return obs


def test_openpi_client_gets_metadata_and_the_local_policys_actions(server):
    from openpi_client.websocket_client_policy import WebsocketClientPolicy

    served, port = server("fast_dvla", token="s3cret")
    client = WebsocketClientPolicy(host="127.0.0.1", port=port, api_key="s3cret")
    meta = client.get_server_metadata()
    assert meta["server"] == "dvla-harness" and meta["policy"] == "fast_dvla" and meta["task"] == TASK
    assert meta["observation"]["state_shape"] == [39] and meta["action"]["dim"] == 4
    assert meta["action"]["low"].dtype == np.float32  # arrays arrive as numpy through openpi's codec
    obs = _observation()
    reply = client.infer({"state": obs, "prompt": served.instruction})
    actions = reply["actions"]
    assert actions.dtype == np.float32 and actions.ndim == 2 and actions.shape[1] == 4
    assert reply["dvla/nfe"] > 0 and reply["dvla/policy_time_s"] > 0 and reply["dvla/action_tokens"] > 0
    # the same decoder built locally, reset with the same default episode, acts the same
    local = _served("fast_dvla").policy
    local.reset([served.context({"instruction": served.instruction})])
    np.testing.assert_array_equal(local.act([obs]).actions[0].astype(np.float32), actions)
    again = client.infer({"state": obs, "prompt": served.instruction})  # same episode: no reset
    assert "dvla/reset_nfe" not in again and "dvla/reset_nfe" in reply


def test_a_wrong_token_is_refused_and_the_server_keeps_serving(server):
    from openpi_client.websocket_client_policy import WebsocketClientPolicy
    from websockets.exceptions import InvalidStatus

    _, port = server("random", token="right")
    with pytest.raises(InvalidStatus, match="401"):
        WebsocketClientPolicy(host="127.0.0.1", port=port, api_key="wrong")
    with pytest.raises(InvalidStatus, match="401"):
        WebsocketClientPolicy(host="127.0.0.1", port=port)
    assert WebsocketClientPolicy(host="127.0.0.1", port=port, api_key="right").get_server_metadata()


@pytest.mark.parametrize(
    ("message", "needle"),
    [
        (b"\xc1 not msgpack", "not a msgpack message"),
        (pack([1, 2, 3]), "a message must be a map"),
        (pack({"prompt": "x"}), "no 'state' array"),
        (pack({"state": np.zeros(5, np.float32)}), "has shape [5], the policy takes [39]"),
        (pack({"state": np.full(39, np.nan, np.float32)}), "must be finite"),
        (pack({"dvla/reset": {"episode_index": "three"}}), "episode_index must be an integer"),
    ],
)
def test_bad_messages_get_an_error_text_and_the_connection_stays_open(server, message, needle):
    from websockets.sync.client import connect

    _, port = server("random")
    with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
        unpack(ws.recv())  # metadata
        ws.send(message)
        reply = ws.recv()
        assert isinstance(reply, str) and needle in reply
        ws.send(pack({"state": np.zeros(39, np.float32)}))
        assert unpack(ws.recv())["actions"].shape[-1] == 4  # still serving


def test_a_batch_message_decodes_each_episode_as_alone_in_one_call(server):
    from websockets.sync.client import connect

    served, port = server("fast_dvla")
    assert served.metadata["act_batch"] is True
    observations = [_observation(0), _observation(1)]
    episodes = [{"instruction": served.instruction, "episode_index": i} for i in range(2)]
    with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
        unpack(ws.recv())
        batch = {"episodes": episodes, "observations": [{"state": o} for o in observations]}
        ws.send(pack({"dvla/batch": batch}))
        reply = unpack(ws.recv())
    assert reply["actions"].shape[0] == 2 and reply["dvla/batch_size"] == 2
    alone = _served("fast_dvla").policy  # each row equals that observation decoded alone
    for i, obs in enumerate(observations):
        context = served.context(episodes[i])
        alone.reset([context])
        np.testing.assert_allclose(alone.act([obs]).actions[0], reply["actions"][i], atol=1e-6)
    assert 0 < reply["dvla/nfe"] <= 2 * 12  # one pass per step serves both rows


@pytest.mark.parametrize(
    ("policy", "batch", "needle"),
    [
        (
            "random",
            {"episodes": [{}], "observations": [{"state": np.zeros(39, np.float32)}]},
            "cannot decode a batch",
        ),
        (
            "fast_dvla",
            {"episodes": [{}, {}], "observations": [{"state": np.zeros(39, np.float32)}]},
            "2 episodes and 1 observations",
        ),
        ("fast_dvla", {"episodes": [], "observations": []}, "at least one"),
        ("fast_dvla", [1, 2], "must be a map"),
        (
            "fast_dvla",
            {"episodes": [{}], "observations": [{"state": np.zeros(5, np.float32)}]},
            "has shape [5]",
        ),
    ],
)
def test_bad_batches_get_an_error_text_and_the_server_keeps_serving(server, policy, batch, needle):
    from websockets.sync.client import connect

    _, port = server(policy)
    with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
        unpack(ws.recv())
        ws.send(pack({"dvla/batch": batch}))
        reply = ws.recv()
        assert isinstance(reply, str) and needle in reply
        ws.send(pack({"state": np.zeros(39, np.float32)}))
        assert unpack(ws.recv())["actions"].shape[-1] == 4


def test_the_codec_is_openpis_and_refuses_what_pickle_would_need():
    from openpi_client import msgpack_numpy

    arrays = {"a": np.arange(6, dtype=np.int16).reshape(2, 3), "b": np.float32(1.5), "s": "text"}
    theirs = msgpack_numpy.unpackb(pack(arrays))
    np.testing.assert_array_equal(theirs["a"], arrays["a"])
    assert theirs["b"] == np.float32(1.5) and theirs["s"] == "text"
    ours = unpack(msgpack_numpy.packb(arrays))
    np.testing.assert_array_equal(ours["a"], arrays["a"])
    with pytest.raises(WireError, match="refused"):
        pack({"o": np.array([object()], dtype=object)})
    bad = pack({"a": np.zeros(4, np.float32)}).replace(b"<f4", b"|O8")
    with pytest.raises(WireError, match="refused"):
        unpack(bad)
    short = msgpack_numpy.packb({"a": np.zeros(4, np.float32)}).replace(
        b"\xc4\x10" + bytes(16), b"\xc4\x04" + bytes(4)
    )
    with pytest.raises(WireError, match="bytes of data"):
        unpack(short)
