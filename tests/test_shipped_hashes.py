"""Shipped checkpoints have known bytes (policies/checkpoints/checkpoints.sha256): the list
matches the files, and a shipped name whose bytes differ is said, naming the file."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import pytest

import policies.registry as registry
from harness.config import PolicyChoice, resolve_policy, sha256_file
from policies.registry import SHIPPED_CHECKPOINTS, SHIPPED_SUMS, shipped_digests

NAME = "metaworld-mt10-bidirectional.safetensors"


def test_the_known_hashes_are_those_of_every_shipped_checkpoint():
    known = shipped_digests(SHIPPED_CHECKPOINTS)
    files = sorted(p.name for p in SHIPPED_CHECKPOINTS.glob("*.safetensors"))
    assert sorted(known) == files and len(files) > 20
    assert {name: sha256_file(str(SHIPPED_CHECKPOINTS / name)) for name in files} == known


@pytest.fixture
def shipped_copy(tmp_path, monkeypatch) -> Path:
    """A shipped folder of one checkpoint and the committed hash list, read as the real one."""
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    shutil.copy(SHIPPED_CHECKPOINTS / SHIPPED_SUMS, folder / SHIPPED_SUMS)
    shutil.copy(SHIPPED_CHECKPOINTS / NAME, folder / NAME)
    monkeypatch.setattr(registry, "SHIPPED_CHECKPOINTS", folder)
    return folder / NAME


def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01  # inside the last tensor: the file still loads, as another model
    path.write_bytes(bytes(data))


def _warnings_resolving(path: Path) -> list[str]:
    from adapters.registry import load_suite

    suite = load_suite("metaworld/mt1/reach-v3")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        resolve_policy(PolicyChoice("bidirectional", {"checkpoint": str(path)}), suite)
    return [str(w.message) for w in caught if "shipped checkpoint" in str(w.message)]


@pytest.mark.metaworld
def test_a_shipped_checkpoint_with_one_byte_changed_is_said_naming_the_file(shipped_copy):
    assert _warnings_resolving(shipped_copy) == []  # the shipped bytes: nothing to say
    _flip_last_byte(shipped_copy)
    (said,) = _warnings_resolving(shipped_copy)
    known = shipped_digests(SHIPPED_CHECKPOINTS)[NAME]
    assert f"shipped checkpoint {NAME} does not hold the bytes it was shipped with" in said
    assert sha256_file(str(shipped_copy))[:12] in said and known[:12] in said


@pytest.mark.metaworld
def test_the_cli_warns_in_one_line_and_still_runs(cli, tmp_path, shipped_copy):
    _flip_last_byte(shipped_copy)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", f"bidirectional:checkpoint={shipped_copy}",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    lines = [line for line in err.splitlines() if "shipped checkpoint" in line]
    assert code == 0 and len(lines) == 1
    assert lines[0].startswith(f"dvla-harness run: warning: shipped checkpoint {NAME} does not hold")
