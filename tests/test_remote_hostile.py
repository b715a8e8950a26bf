"""A hostile or broken remote server, and keys where they would be recorded: what the
server reports is checked before it enters a row, and a failure says what was wrong."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

pytest.importorskip("websockets")
pytest.importorskip("msgpack")

from policies.base import EpisodeContext
from policies.registry import PolicyParamError, get_policy, parse_params
from policies.remote import MAX_REPORTED_PASSES, RemotePolicy
from policies.wire import WireError
from tests.test_remote import openpi_like, servers  # noqa: F401  (a fixture)

CHUNK = np.zeros((4, 4), np.float32)


def _policy(port: int) -> RemotePolicy:
    params = parse_params(get_policy("remote"), {"url": f"ws://127.0.0.1:{port}", "timeout_s": 5})
    policy = RemotePolicy(params)
    space = gym.spaces.Box(-1, 1, (4,))
    context = EpisodeContext("s", "t", "reach", space, gym.spaces.Box(-1, 1, (39,)), 10, 0)
    policy.reset([context])
    return policy


def _act(port: int) -> None:
    policy = _policy(port)
    try:
        policy.act([np.zeros(39, np.float32)])
        policy.take_served()
    finally:
        policy.close()


@pytest.mark.parametrize(
    ("extra", "shown"),
    [
        ({"dvla/nfe": -5}, "dvla/nfe = -5"),
        ({"dvla/nfe": 2.5}, "dvla/nfe = 2.5"),
        ({"dvla/nfe": math.nan}, "dvla/nfe = nan"),
        ({"dvla/nfe": True}, "dvla/nfe = True"),
        ({"dvla/nfe": MAX_REPORTED_PASSES + 1}, f"dvla/nfe = {MAX_REPORTED_PASSES + 1}"),
        ({"dvla/nfe": "7"}, "dvla/nfe = '7'"),
        ({"dvla/work": {"flops": -1}}, "flops = -1"),
        ({"dvla/work": {"flops": 1.0e300}}, "flops = 1e+300"),
        ({"dvla/work": "a lot"}, "dvla/work = 'a lot'"),
        ({"dvla/action_tokens": -3}, "dvla/action_tokens = -3"),
        ({"dvla/policy_time_s": math.inf}, "dvla/policy_time_s = inf"),
        ({"dvla/queue_time_s": -1.0}, "dvla/queue_time_s = -1.0"),
    ],
)
def test_a_servers_figure_that_is_not_a_count_fails_the_call_naming_the_value(servers, extra, shown):  # noqa: F811
    port = servers(openpi_like(lambda c, n, m: {"actions": CHUNK, "dvla/nfe": 1} | extra))
    with pytest.raises(WireError, match=r"the server reported .*expected") as refused:
        _act(port)
    assert shown in str(refused.value)


def test_counts_a_server_reports_within_bounds_are_taken(servers):  # noqa: F811
    reply = {"actions": CHUNK, "dvla/nfe": np.int64(3), "dvla/work": {"flops": 10, "query_tokens": None}}
    port = servers(openpi_like(lambda c, n, m: reply | {"dvla/policy_time_s": 0.01}))
    policy = _policy(port)
    try:
        policy.take_served()
        policy.act([np.zeros(39, np.float32)])
        served = policy.take_served()
    finally:
        policy.close()
    assert served.nfe == 3 and served.work.flops == 10 and served.work.query_tokens is None
    assert served.server_time_s == pytest.approx(0.01)


def test_non_finite_actions_of_the_right_shape_say_not_finite_not_shape(servers):  # noqa: F811
    chunk = CHUNK.copy()
    chunk[1, 2] = np.nan
    port = servers(openpi_like(lambda c, n, m: {"actions": chunk}))
    with pytest.raises(WireError) as refused:
        _act(port)
    message = str(refused.value)
    assert "actions of shape (4, 4) hold 1 value(s) that are not finite (nan at [1, 2] first)" in message
    assert "expected" not in message
    port = servers(openpi_like(lambda c, n, m: {"actions": np.zeros((1, 4, 4, 1), np.float32)}))
    with pytest.raises(WireError) as refused:
        _act(port)
    assert "shape (1, 4, 4, 1); expected (chunk, action_dim)" in str(refused.value)
    assert "finite" not in str(refused.value)


@pytest.mark.metaworld
def test_a_negative_nfe_from_the_server_is_a_failure_row_naming_it_not_a_negative_total(
    cli,
    tmp_path,
    servers,  # noqa: F811
):
    port = servers(openpi_like(lambda c, n, m: {"actions": CHUNK, "dvla/nfe": -5}))
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", f"remote:url=ws://127.0.0.1:{port}",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 1, err
    row = pd.read_parquet(out / "episodes.parquet").iloc[0]
    assert "the server reported dvla/nfe = -5" in row["failure_reason"]
    assert not row["nfe_total"] < 0 and not row["nfe_per_chunk"] < 0


@pytest.mark.parametrize(
    "url",
    [
        "ws://127.0.0.1:8000/?api_key=s3cr3t",
        "ws://127.0.0.1:8000/policy?model=a&token=s3cr3t",
        "wss://host.example/?X-Amz-Signature=s3cr3t",
        "ws://127.0.0.1:8000/?access%5Ftoken=s3cr3t",
    ],
)
def test_a_key_in_the_urls_query_is_refused_without_repeating_it(url):
    with pytest.raises(PolicyParamError, match="credential in its query") as refused:
        parse_params(get_policy("remote"), {"url": url})
    assert "s3cr3t" not in str(refused.value)


def test_a_query_without_a_credential_is_an_address_like_any_other():
    params = parse_params(get_policy("remote"), {"url": "ws://127.0.0.1:8000/policy?model=pi0&v=2"})
    assert params.url.endswith("?model=pi0&v=2")


def test_the_cli_refuses_a_key_in_the_url_before_anything_is_written(cli, tmp_path: Path):
    out = tmp_path / "run"
    code, outs, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "remote:url=ws://127.0.0.1:9/?api_key=s3cr3t",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 2 and "credential in its query (api_key=...)" in err and len(err.strip().splitlines()) == 1
    assert "s3cr3t" not in err + outs and not out.exists()
