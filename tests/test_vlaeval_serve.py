"""`dvla-harness serve --protocol vla-eval` driven by vla-eval itself: its `vla-eval run
--no-docker` (client, orchestrator and LIBERO benchmark, the real package) evaluates a
policy of this harness, executing the policy's own actions one per step from its
chunks; and traffic that breaks the protocol gets an error message while the server
goes on serving."""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import threading
import urllib.request

import msgpack
import numpy as np
import pytest

pytest.importorskip("vla_eval")
pytest.importorskip("websockets")

from harness.commands.serve import build_served
from harness.serving import vlaeval as dialect
from harness.serving.server import make_server
from policies.vlaeval_wire import pack, unpack

pytestmark = pytest.mark.libero

SUITE = "libero/spatial:obs=upstream,seeding=openpi"  # vla-eval's LIBERO: env.seed(7), 256 px
POLICY = "random:seed=5,chunk_length=4"


@pytest.fixture(scope="module")
def served():
    pytest.importorskip("libero")
    args = argparse.Namespace(policy=POLICY, suite=SUITE, task=None, state_key="state")
    served = build_served(args)
    server = make_server(served, "127.0.0.1", 0, dialect.handler, ping_interval=None)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield served, server.socket.getsockname()[1]
    server.shutdown()


def test_vla_evals_own_runner_executes_the_served_policys_actions(served, tmp_path):
    from adapters.libero_sim import configure_libero
    from policies.registry import get_policy, parse_params

    served_policy, port = served
    configure_libero()  # LIBERO_CONFIG_PATH, inherited by vla-eval's process
    config = {
        "server": {"url": f"ws://127.0.0.1:{port}"},
        "output_dir": str(tmp_path / "results"),
        "benchmarks": [
            {
                "benchmark": "vla_eval.benchmarks.libero.benchmark:LIBEROBenchmark",
                "params": {"suite": "libero_spatial", "seed": 7},
                "episodes_per_task": 2,
                "max_tasks": 1,
                "max_steps": 6,
            }
        ],
    }
    (tmp_path / "eval.yaml").write_text(json.dumps(config))  # YAML reads JSON
    done = subprocess.run(
        [sys.executable, "-m", "vla_eval.cli.main", "run", "--no-docker", "-c", str(tmp_path / "eval.yaml")],
        capture_output=True,
        text=True,
        timeout=600,
        env=os.environ,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    log = done.stdout + done.stderr
    # the hello's observation_params reached the benchmark, and its specs matched ours
    assert "Auto-configured from model server: send_state=True" in log
    assert "quat_no_antipodal=True" in log and "Spec validation passed" in log

    (db,) = (tmp_path / "results").glob("recording-*.sqlite")
    with sqlite3.connect(db) as con:
        episodes = con.execute(
            "SELECT eid, episode_id, steps FROM episode_results ORDER BY episode_id"
        ).fetchall()
        assert [(e, s) for _, e, s in episodes] == [(0, 6), (1, 6)]
        for eid, episode, _ in episodes:
            rows = con.execute(
                "SELECT fields FROM step_rows WHERE eid = ? ORDER BY step_id", (eid,)
            ).fetchall()
            executed = np.array([json.loads(f)["action"] for (f,) in rows], np.float32)
            # the same policy here, reset as `run` resets episode `episode` of task 0
            local = get_policy("random").build(
                parse_params(get_policy("random"), {"seed": 5, "chunk_length": 4})
            )
            values = dialect.episode_values(
                served_policy, {"suite": "libero_spatial", "task_id": 0, "episode_idx": episode}
            )
            local.reset([served_policy.context(values)])
            chunks = np.concatenate([local.act([None]).actions[0] for _ in range(2)])[:6].astype(np.float32)
            np.testing.assert_array_equal(executed[:, :6], chunks[:, :6])
            np.testing.assert_array_equal(
                executed[:, 6], np.where(chunks[:, 6] < 0, -1.0, 1.0)
            )  # its binarising


def _client(port: int):
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None)


def _observation(state_dim: int = 8) -> dict:
    image = np.zeros((256, 256, 3), np.uint8)
    return {
        "images": {"agentview": image, "wrist": image},
        "task_description": "x",
        "states": np.zeros(state_dim),
    }


BAD = [
    (b"\xc1 not msgpack", 0, "not a msgpack message"),
    (msgpack.packb({"type": "launch", "payload": {}, "seq": 3, "timestamp": 0.0}), 0, "unknown message type"),
    (pack("observation", _observation(), 4), 4, "an observation before episode_start"),
    (pack("episode_start", {"task": {"task_id": 10, "episode_idx": 0}}, 5), 5, "task_id 10 names no task"),
    (
        pack("episode_start", {"task": {"task_id": 0, "episode_idx": 50}}, 6),
        6,
        "episode_idx 50 is not an episode",
    ),
    (
        pack("episode_start", {"task": {"suite": "libero_object", "task_id": 0}}, 7),
        7,
        "the benchmark runs 'libero_object'",
    ),
    (pack("action", {}, 8), 8, "a client does not send 'action'"),
]


@pytest.mark.parametrize(("message", "seq", "needle"), BAD, ids=[b[2] for b in BAD])
def test_bad_messages_get_an_error_and_the_connection_stays_open(served, message, seq, needle):
    _, port = served
    with _client(port) as ws:
        ws.send(message)
        reply = unpack(ws.recv(timeout=30))
        assert (reply.type, reply.seq) == ("error", seq) and needle in reply.payload["error"]
        ws.send(pack("hello", {"protocol_version": 1}, 9))
        assert unpack(ws.recv(timeout=30)).type == "hello"  # still serving this connection


def test_an_episode_is_served_one_action_per_observation_and_bad_observations_are_refused(served):
    served_policy, port = served
    with _client(port) as ws:
        ws.send(pack("hello", {"protocol_version": 1}, 1))
        hello = unpack(ws.recv(timeout=30)).payload
        assert hello["observation_params"] == {
            "send_wrist_image": True,
            "send_state": True,
            "quat_no_antipodal": True,
        }
        assert (
            hello["model_server"] == "dvla-harness:random" and hello["dvla"]["suite"] == served_policy.suite
        )
        ws.send(
            pack("episode_start", {"task": {"suite": "libero_spatial", "task_id": 2, "episode_idx": 3}}, 2)
        )
        ws.send(pack("observation", _observation(state_dim=5), 3))
        bad = unpack(ws.recv(timeout=30))
        assert (bad.type, bad.seq) == ("error", 3)
        assert "has shape [5], the policy takes [8]" in bad.payload["error"]
        ws.send(pack("observation", {"task_description": "x"}, 3))
        bad = unpack(ws.recv(timeout=30)).payload["error"]
        assert bad.startswith("bad request: a vla-eval observation needs an images map")
        replies = []
        for seq in range(4, 10):
            ws.send(pack("observation", _observation(), seq))
            replies.append(unpack(ws.recv(timeout=30)))
        assert [r.seq for r in replies] == list(range(4, 10)) and {r.type for r in replies} == {"action"}
        assert all(r.payload["actions"].shape == (7,) for r in replies)
        # a chunk of 4: the decodes at steps 0 and 4 report their passes, the rest 0
        assert [r.payload["dvla/nfe"] for r in replies] == [0] * 6  # the random policy makes none
        assert (
            replies[1].payload["dvla/policy_time_s"] == 0.0 and replies[4].payload["dvla/policy_time_s"] > 0
        )


def test_an_oversized_frame_drops_that_connection_only_and_health_answers(served):
    from websockets.exceptions import ConnectionClosed

    from policies.wire import MAX_MESSAGE_BYTES

    _, port = served
    with _client(port) as ws:
        ws.send(b"\x00" * (MAX_MESSAGE_BYTES + 1))
        with pytest.raises(ConnectionClosed, match="1009"):
            ws.recv(timeout=30)
    with _client(port) as ws:
        ws.send(pack("hello", {}, 1))
        assert unpack(ws.recv(timeout=30)).type == "hello"
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=30) as response:
        assert response.status == 200 and json.loads(response.read()) == {"status": "ok"}
        assert response.headers["Content-Type"] == "application/json"


def test_serve_refuses_a_suite_vla_eval_cannot_feed(cli, tmp_path):
    code, _, err = cli(
        "serve", "--protocol", "vla-eval", "--policy", "random", "--suite", "libero/spatial", "--port", "0"
    )
    assert code == 2 and "--protocol vla-eval: vla-eval's libero observation needs" in err
    assert "serves libero/<suite>:obs=upstream suites" in err
