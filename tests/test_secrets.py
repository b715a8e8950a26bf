"""A server's API key stays out of everything the harness writes: a real `serve` and a
remote run with a key, then every byte of the run folder, the HTML report, the
leaderboard, `show` and both processes' output searched for it; a rotated key (or one
moved to a file) resumes the same configuration; a key given inline is refused without
being echoed."""

from __future__ import annotations

import argparse
import logging
import os
import re
import socket
import subprocess
import sys
import uuid
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

pytest.importorskip("websockets")
pytest.importorskip("msgpack")
pytest.importorskip("metaworld")

SUITE = "metaworld/mt1/reach-v3"
REPO = Path(__file__).resolve().parent.parent


def _key() -> str:
    return f"sk-{uuid.uuid4().hex}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """`dvla-harness serve --policy random` in its own process, its key in an environment
    variable; `output()` is everything it printed (read once it has stopped)."""

    def __init__(self, key: str, port: int):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "harness", "serve", "--policy", "random", "--suite", SUITE,
             "--token-env", "DVLA_SERVE_KEY", "--port", str(port)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=os.environ | {"DVLA_SERVE_KEY": key, "OMP_NUM_THREADS": "1", "COLUMNS": "200"},
        )  # fmt: skip
        self.first_line = self.proc.stdout.readline()
        match = re.search(r"on (ws://[0-9.]+:[0-9]+)", self.first_line)
        assert match, self.first_line + (self.proc.stdout.read() if self.proc.poll() is not None else "")
        self.url = match.group(1)

    def stop(self) -> str:
        if self.proc.poll() is None:
            self.proc.terminate()
        rest = self.proc.communicate(timeout=30)[0]
        return self.first_line + rest


@pytest.fixture
def servers():
    started: list[Server] = []

    def start(key: str, port: int) -> Server:
        started.append(Server(key, port))
        return started[-1]

    yield start
    for server in started:
        server.stop()


def _files_holding(folder: Path, secret: str) -> list[str]:
    """Every file under `folder` (recursively, binary included) whose bytes hold `secret`."""
    needle = secret.encode()
    return [str(p) for p in sorted(folder.rglob("*")) if p.is_file() and needle in p.read_bytes()]


def test_the_key_is_in_no_file_report_listing_or_log(cli, tmp_path, servers, monkeypatch, caplog):
    caplog.set_level(logging.DEBUG)
    key = _key()
    server = servers(key, _free_port())
    monkeypatch.setenv("DVLA_REMOTE_KEY", key)
    out, report = tmp_path / "run", tmp_path / "report"
    said = []
    for argv in (
        ["run", "--suite", SUITE, "--policy", f"remote:url={server.url},token_env=DVLA_REMOTE_KEY",
         "--episodes-per-task", "2", "--out", str(out)],
        ["show", str(out)],
        ["leaderboard", str(out)],
        ["leaderboard", str(out), "--format", "csv"],
        ["report", "html", str(out), "--out", str(report)],
    ):  # fmt: skip
        code, text, err = cli(*argv)
        assert code == 0, (argv, err)
        said += [text, err]
    rows = pd.read_parquet(out / "episodes.parquet")
    assert len(rows) == 2 and rows["failure_reason"].isna().all()  # it did connect with the key
    assert "token_env" not in rows["policy_params"][0]  # where the key is read from: not identity
    assert _files_holding(out, key) == [] and _files_holding(report, key) == []
    assert len(list(report.rglob("*"))) > 0
    assert not any(key in s for s in said)
    assert not any(key in r.getMessage() for r in caplog.records)
    served = server.stop()
    assert "token required" in served and key not in served


def test_a_wrong_key_fails_with_one_line_that_does_not_echo_either_key(cli, tmp_path, servers, monkeypatch):
    right, wrong = _key(), _key()
    server = servers(right, _free_port())
    monkeypatch.setenv("DVLA_REMOTE_KEY", wrong)
    out = tmp_path / "run"
    code, text, err = cli(
        "run", "--suite", SUITE, "--policy", f"remote:url={server.url},token_env=DVLA_REMOTE_KEY",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 2 and "401" in err, err
    assert right not in text + err and wrong not in text + err
    assert not out.exists()


def test_a_rotated_or_moved_key_resumes_the_same_configuration(cli, tmp_path, servers, monkeypatch):
    port, first, second = _free_port(), _key(), _key()
    server = servers(first, port)
    monkeypatch.setenv("DVLA_REMOTE_KEY", first)
    out = tmp_path / "run"
    policy = f"remote:url={server.url},token_env=DVLA_REMOTE_KEY"
    base = ["run", "--suite", SUITE, "--out", str(out), "--quiet"]
    code, _, err = cli(*base, "--policy", policy, "--episodes-per-task", "1")
    assert code == 0, err
    before = pd.read_parquet(out / "episodes.parquet")
    server.stop()
    server = servers(second, port)  # the key rotated: same server, new key
    monkeypatch.setenv("DVLA_REMOTE_KEY", second)
    code, _, err = cli(*base, "--resume", "--episodes-per-task", "2")  # the recorded config
    assert code == 0, err
    key_file = tmp_path / "key"
    key_file.write_text(second + "\n")
    monkeypatch.delenv("DVLA_REMOTE_KEY")
    moved = f"remote:url={server.url},token_file={key_file}"  # the key moved to a file
    code, _, err = cli(*base, "--resume", "--policy", moved, "--episodes-per-task", "3")
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet").sort_values("episode_index")
    assert list(rows["episode_index"]) == [0, 1, 2] and rows["failure_reason"].isna().all()
    assert rows["policy_config_id"].nunique() == 1
    assert rows["policy_config_id"].iloc[0] == before["policy_config_id"].iloc[0]
    assert rows["started_at"].iloc[0] == before["started_at"].iloc[0]  # not run again
    for secret in (first, second):
        assert _files_holding(out, secret) == []


def test_an_inline_key_is_refused_without_echoing_it(cli, tmp_path):
    key = _key()
    out = tmp_path / "run"
    for argv in (
        ["run", "--suite", SUITE, "--policy", f"remote:url=ws://127.0.0.1:9,token={key}", "--out", str(out)],
        ["run", "--suite", SUITE, "--policy", f"remote:url=ws://user:{key}@127.0.0.1:9", "--out", str(out)],
        ["serve", "--policy", "random", "--suite", SUITE, "--token", key],
    ):
        code, text, err = cli(*argv)
        assert code == 2 and "token-env" in err.replace("_", "-"), err
        assert key not in text + err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("params", "env", "needle"),
    [
        (",token_env=DVLA_NO_SUCH_KEY", {}, "the environment variable DVLA_NO_SUCH_KEY is not set"),
        (",token_env=DVLA_REMOTE_KEY", {"DVLA_REMOTE_KEY": "  "}, "DVLA_REMOTE_KEY is empty"),
        (",token_env=DVLA_REMOTE_KEY", {"DVLA_REMOTE_KEY": "a\nb"}, "more than one line"),
        (",token_file=/nonexistent/key", {}, "token_file '/nonexistent/key' cannot be read"),
        (",token_env=A,token_file=/k", {}, "token_env and token_file are both given"),
    ],
)
def test_a_key_that_cannot_be_read_is_exit_2_before_anything_runs(
    cli, tmp_path, monkeypatch, params, env, needle
):
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", SUITE, "--policy", f"remote:url=ws://127.0.0.1:9{params}", "--out", str(out)
    )
    assert code == 2 and needle in err and err.count("\n") == 1, err
    assert not out.exists()


def test_serve_reads_its_key_from_a_file_and_refuses_an_unreadable_one(cli, tmp_path):
    from harness.commands.serve import server_key

    key_file = tmp_path / "key"
    key_file.write_text("  from-a-file\n")
    assert (
        server_key(argparse.Namespace(token=None, token_env=None, token_file=str(key_file))) == "from-a-file"
    )
    assert server_key(argparse.Namespace(token=None, token_env=None, token_file=None)) is None
    code, _, err = cli(
        "serve", "--policy", "random", "--suite", SUITE, "--token-file", str(tmp_path / "none")
    )
    assert code == 2 and "--token-file" in err and "cannot be read" in err


def test_a_folder_recorded_with_an_inline_key_does_not_repeat_it_in_errors(cli, tmp_path):
    """Folders written before inline keys were refused hold one in their config; a refused
    resume names the difference without it."""
    import json

    key, out = _key(), tmp_path / "run"
    base = ["run", "--suite", SUITE, "--episodes-per-task", "1", "--out", str(out), "--quiet"]
    assert cli(*base, "--policy", "random")[0] == 0
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["config"]["policies"] = [{"name": "remote", "params": {"url": "ws://127.0.0.1:9", "token": key}}]
    (out / "manifest.json").write_text(json.dumps(manifest))
    code, text, err = cli(*base, "--policy", "random", "--resume")
    assert code == 2 and "belongs to a different config" in err and '"token": "<set>"' in err
    assert key not in text + err
