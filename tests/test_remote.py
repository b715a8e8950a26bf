"""The `remote` policy through the real runner: against `dvla-harness serve` (the same
success, steps and NFE as the local decoder, transport time recorded), and against
small hand-written servers that speak openpi's protocol badly on purpose: one that
drops the connection mid-episode, one too slow to answer, one whose policy does not fit
the suite, one that reports no NFE."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("websockets")
pytest.importorskip("msgpack")
pytest.importorskip("metaworld")

from websockets.sync.server import serve

from policies.wire import pack, unpack

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

SUITE = "metaworld/mt1/reach-v3"
# counted work (harness/episode/work.py): the server's hooks count it and report it with each reply
WORK = ("flops_total", "query_tokens_total", "kv_tokens_total", "kv_cached_tokens_total")


@pytest.fixture
def servers():
    running = []

    def start(server) -> int:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        running.append(server)
        return server.socket.getsockname()[1]

    yield start
    for server in running:
        server.shutdown()


def openpi_like(reply: Callable[[int, int, dict], dict | None], metadata: dict | None = None):
    """A server in openpi's manner: metadata, then reply(connection_no, call_no, message)
    per message; None from `reply` closes the connection."""
    connections = [0]

    def handle(ws) -> None:
        connections[0] += 1
        ws.send(pack(metadata or {"server": "openpi-like"}))
        for call, data in enumerate(ws):
            answer = reply(connections[0], call, unpack(data))
            if answer is None:
                ws.close()
                return
            ws.send(pack(answer))

    return serve(handle, "127.0.0.1", 0, compression=None)


def run(cli, tmp_path: Path, url: str, *extra: str, policy_params: str = "") -> tuple[int, str, Path]:
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", SUITE, "--policy", f"remote:url={url}{policy_params}", *extra,
        "--episodes-per-task", "2", "--out", str(out), "--quiet",
    )  # fmt: skip
    return code, err, out


@pytest.fixture
def serve_process():
    """`dvla-harness serve` in its own process (the runner's NFE hooks and the server's
    must not share one), on a free port; yields its ws:// address."""
    procs = []

    def start(*args: str, ignore_sigint: bool = False) -> str:
        repo = Path(__file__).resolve().parent.parent
        proc = subprocess.Popen(
            [sys.executable, "-m", "harness", "serve", *args, "--port", "0"],
            cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=os.environ | {"OMP_NUM_THREADS": "1", "COLUMNS": "200"},
            # as a shell leaves a background job: SIGINT ignored from the start
            preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if ignore_sigint else None,
        )  # fmt: skip
        procs.append(proc)
        line = proc.stdout.readline()
        match = re.search(r"on (ws://[0-9.]+:[0-9]+)", line)
        assert match, line + proc.stdout.read() if proc.poll() is not None else line
        return match.group(1)

    start.procs = procs  # type: ignore[attr-defined]
    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
        proc.wait(timeout=120)  # a server holding LeRobot takes ~30 s to exit at load 17


def test_remote_equals_local_through_dvla_harness_serve(cli, tmp_path, serve_process, monkeypatch):
    monkeypatch.setenv("DVLA_TEST_KEY", "k")
    url = serve_process(
        "--policy", "fast_dvla", "--suite", "metaworld/mt10", "--task", "reach-v3", "--token-env", "DVLA_TEST_KEY"
    )  # fmt: skip
    code, err, out = run(
        cli, tmp_path, url, "--policy", "fast_dvla", policy_params=",token_env=DVLA_TEST_KEY"
    )
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet").set_index(["policy", "episode_index"])
    remote, local = rows.loc["remote"], rows.loc["fast_dvla"]
    for column in ("success", "steps", "chunks", "nfe_total", "action_tokens_total", *WORK):
        assert list(remote[column]) == list(local[column]), column
    assert (remote["transport_time_s"] >= 0).all() and local["transport_time_s"].isna().all()
    assert (remote["transport_time_s"] < remote["policy_time_s"]).all()


def test_batched_remote_equals_batched_local_and_charges_each_episode_the_servers_passes(
    cli, tmp_path, serve_process
):
    """--batch-envs 2: one dvla/batch message per lockstep call, the server's passes charged
    to each episode of the call, as the local batched loop charges its own."""
    url = serve_process("--policy", "fast_dvla", "--suite", "metaworld/mt10", "--task", "reach-v3")
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", SUITE, "--policy", f"remote:url={url}", "--policy", "fast_dvla",
        "--batch-envs", "2", "--episodes-per-task", "3", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet").set_index(["policy", "episode_index"])
    remote, local = rows.loc["remote"], rows.loc["fast_dvla"]
    assert (remote["batch_envs"] == 2).all() and (local["batch_envs"] == 2).all()
    for column in ("success", "steps", "chunks", "nfe_total", "action_tokens_total", *WORK):
        assert list(remote[column]) == list(local[column]), column
    assert (remote["nfe_total"] > 0).all()
    assert (remote["transport_time_s"] >= 0).all() and local["transport_time_s"].isna().all()


def test_a_shared_server_batches_two_workers_calls_and_their_rows_equal_local_ones(
    cli, tmp_path, serve_process
):
    """serve --max-batch: two env workers' calls decoded together (mean batch > 1), each
    episode's outcome and NFE those of the same decoder run locally and alone.

    --batch-wait-ms 2000 holds each call until the other worker has asked (a call closes
    as soon as every active client is in it): with the default 5 ms the two workers fall
    into turns on a loaded machine, each stepping its env while the other's call decodes,
    and no call is ever shared. A worker's gap between calls is milliseconds; the longest
    wait is once, for a worker that finished (it counts as active for 2 s)."""
    url = serve_process(
        "--policy", "bidirectional", "--suite", "metaworld/mt10", "--max-batch", "4", "--batch-wait-ms", "2000"
    )  # fmt: skip
    tasks = ("--tasks", "reach-v3,push-v3", "--episodes-per-task", "3", "--quiet")
    remote_out, local_out = tmp_path / "remote", tmp_path / "local"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt10", "--policy", f"remote:url={url}", "--workers", "2",
        *tasks, "--out", str(remote_out),
    )  # fmt: skip
    assert code == 0, err
    code, _, err = cli(
        "run", "--suite", "metaworld/mt10", "--policy", "bidirectional", *tasks, "--out", str(local_out)
    )
    assert code == 0, err
    key = ["task", "episode_index"]
    remote = pd.read_parquet(remote_out / "episodes.parquet").set_index(key).sort_index()
    local = pd.read_parquet(local_out / "episodes.parquet").set_index(key).sort_index()
    assert remote["worker_id"].nunique() == 2
    for column in ("success", "steps", "chunks", "nfe_total", "action_tokens_total", *WORK):
        assert list(remote[column]) == list(local[column]), column
    assert (remote["transport_time_s"] >= 0).all()
    server = serve_process.procs[0]
    server.send_signal(signal.SIGTERM)  # stops with clients still attached: it closes them
    text = server.communicate(timeout=60)[0]
    mean = float(re.search(r"mean batch ([0-9.]+)", text).group(1))
    assert mean > 1.0, text  # the two workers' calls did share decodes


@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_stops_the_server_with_a_client_still_connected(serve_process, stop):
    """SIGTERM (a service manager, CI) or Ctrl-C, even when started in the background
    with SIGINT ignored: the server closes its clients and exits, printing why."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    url = serve_process("--policy", "random", "--suite", SUITE, ignore_sigint=stop == signal.SIGINT)
    with connect(url, compression=None) as ws:
        unpack(ws.recv())  # connected, idle: its thread must not keep the server alive
        server = serve_process.procs[0]
        server.send_signal(stop)
        assert "stopped" in server.communicate(timeout=60)[0] and server.returncode == 0
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=10)  # the server closed it on the way out


def test_batching_against_a_server_that_cannot_batch_exits_2_before_anything_runs(cli, tmp_path, servers):
    port = servers(openpi_like(lambda c, n, m: {"actions": np.zeros((4, 4), np.float32)}))
    code, err, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}", "--batch-envs", "2")
    assert code == 2 and "cannot decode batches" in err and "--batch-envs 1" in err
    assert not out.exists()


def test_a_server_that_drops_mid_episode_fails_that_episode_and_the_next_reconnects(cli, tmp_path, servers):
    def reply(connection: int, call: int, message: dict) -> dict | None:
        if connection == 1 and call == 3:
            return None  # gone mid-episode
        return {"actions": np.zeros((4, 4), np.float32), "dvla/nfe": 1}

    port = servers(openpi_like(reply))
    code, _, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}")
    assert code == 1  # a run with a failed episode exits 1, and goes on
    rows = pd.read_parquet(out / "episodes.parquet").sort_values("episode_index")
    assert "closed the connection" in rows["failure_reason"].iloc[0]
    assert (
        pd.isna(rows["failure_reason"].iloc[1]) and rows["steps"].iloc[1] == 500
    )  # reconnected, ran to the budget


def test_a_server_too_slow_to_answer_is_a_timeout_failure_not_a_hang(cli, tmp_path, servers):
    def reply(connection: int, call: int, message: dict) -> dict | None:
        if connection == 1 and call == 1:
            time.sleep(2.0)
        return {"actions": np.zeros((4, 4), np.float32)}

    port = servers(openpi_like(reply))
    start = time.perf_counter()
    code, _, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}", policy_params=",timeout_s=0.5")
    rows = pd.read_parquet(out / "episodes.parquet").sort_values("episode_index")
    assert code == 1 and "no reply within 0.5 s" in rows["failure_reason"].iloc[0]
    assert pd.isna(rows["failure_reason"].iloc[1]) and time.perf_counter() - start < 60


def test_a_server_that_reports_no_nfe_leaves_it_null_and_the_leaderboard_says_so(cli, tmp_path, servers):
    port = servers(openpi_like(lambda c, n, m: {"actions": np.zeros((4, 4), np.float32)}))
    code, err, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}")
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet")
    assert rows["nfe_total"].isna().all() and rows["nfe_per_chunk"].isna().all()
    assert rows[["flops_total", "flops_per_chunk", *WORK]].isna().all().all()  # not measured, never 0
    code, text, _ = cli("leaderboard", str(out), "--format", "md")
    assert code == 0 and "not measured" in text


@pytest.mark.parametrize(
    ("metadata", "needle"),
    [
        ({"server": "x", "action": {"dim": 7}}, "returns 7-D actions, this suite takes 4-D"),
        ({"server": "x", "observation": {"state_shape": [9]}}, "takes a state of shape [9]"),
        (
            {"server": "x", "observation": {"state_key": "observation/state"}},
            "pass state_key=observation/state",
        ),
    ],
)
def test_a_server_that_does_not_fit_the_suite_exits_2_before_anything_runs(
    cli, tmp_path, servers, metadata, needle
):
    port = servers(openpi_like(lambda c, n, m: {"actions": np.zeros((4, 4), np.float32)}, metadata))
    code, err, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}")
    assert code == 2 and needle in err and not (out / "episodes.parquet").exists()


def test_no_server_and_bad_urls_are_clear(cli, tmp_path):
    code, err, out = run(cli, tmp_path, "ws://127.0.0.1:9", policy_params=",retries=1,connect_timeout_s=1")
    assert code == 2 and "no connection after 1 attempts" in err and not out.exists()
    code, err, _ = run(cli, tmp_path, "http://example")
    assert code == 2 and "url must start with ws:// or wss://" in err


def test_the_manifest_and_params_record_the_remote_configuration(cli, tmp_path, servers):
    port = servers(openpi_like(lambda c, n, m: {"actions": np.zeros((4, 4), np.float32), "dvla/nfe": 2}))
    code, err, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}")
    assert code == 0, err
    params = json.loads(pd.read_parquet(out / "episodes.parquet")["policy_params"].iloc[0])
    assert params["url"] == f"ws://127.0.0.1:{port}" and params["timeout_s"] == 30.0


def test_the_docs_server_snippet_serves_a_model_to_the_remote_policy(cli, tmp_path, servers):
    """docs/remote-policies.md's 'Serving a model from another repository', as written."""
    doc = (Path(__file__).resolve().parent.parent / "docs" / "remote-policies.md").read_text()
    section = doc.split("## Serving a model from another repository", 1)[1]
    code_text = re.search(r"```python\n(.+?)\n```", section, re.S).group(1)
    namespace: dict = {}
    exec(compile(code_text, "docs/remote-policies.md", "exec"), namespace)

    class Model:
        action_dim = 4

        def act(self, state, prompt):
            assert state.shape == (39,) and "reach" in prompt
            return np.tile(np.float32([0.1, 0.0, 0.0, 0.0]), (4, 1))

    port = servers(namespace["serve"](lambda ws: namespace["handler"](ws, Model()), "127.0.0.1", 0))
    code, err, out = run(cli, tmp_path, f"ws://127.0.0.1:{port}")
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet")
    assert (rows["steps"] == 500).all() and rows["nfe_total"].isna().all()  # ran; NFE not measured
