"""--resume of a run folder recorded in a clone at another folder: the shipped checkpoint
the config resolves to has another absolute path there (harness/run/resume.py,
`adopt_moved_checkpoints`).

The "other checkout" is a copy of the shipped file under tmp_path/other/policies/
checkpoints/; the rows are recorded with it by the same writer a clone there would use,
then resumed with this checkout's file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from harness.backends import Execution
from harness.config import PolicyRun, ResolvedRun, policy_config_id, sha256_file
from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.resume import adopt_moved_checkpoints
from harness.run.runner import run
from policies.registry import SHIPPED_CHECKPOINTS, get_policy, params_json, parse_params
from results.store import RunDir
from tests.fakes import ChunkPolicy, fake_resolved

SHIPPED_FILE = "metaworld-mt10-bidirectional.safetensors"  # `bidirectional`'s default checkpoint


def decoder(params: dict) -> PolicyRun:
    """The `bidirectional` policy's configuration as resolve_policy makes it (its real
    parameters, checkpoint path, sha256 and config id), acting as a fake chunk policy."""
    spec = get_policy("bidirectional")
    parsed = parse_params(spec, params)
    pjson, digest = params_json(parsed), sha256_file(parsed.checkpoint)
    config_id = policy_config_id(spec.name, pjson, digest)
    return PolicyRun(spec, parsed, pjson, parsed.checkpoint, digest, config_id, ChunkPolicy(chunk=2))


def with_decoder(episodes: int, params: dict | None = None) -> ResolvedRun:
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=episodes)
    resolved.policies = [decoder(params or {})]
    return resolved


def resumed_here() -> ResolvedRun:
    """What a worker rebuilds on resume (module level: sent to a spawned process)."""
    return with_decoder(episodes=3)


def other_checkout(tmp_path: Path, content: bytes | None = None) -> Path:
    """The shipped file in a clone at another folder (other content when given)."""
    folder = tmp_path / "other" / SHIPPED_CHECKPOINTS.parent.name / SHIPPED_CHECKPOINTS.name
    folder.mkdir(parents=True)
    path = folder / SHIPPED_FILE
    if content is None:
        shutil.copyfile(SHIPPED_CHECKPOINTS / SHIPPED_FILE, path)
    else:
        path.write_bytes(content)
    return path


def recorded_there(tmp_path: Path, checkpoint: Path) -> tuple[Path, pd.DataFrame]:
    out = tmp_path / "run"
    run(with_decoder(episodes=2, params={"checkpoint": str(checkpoint)}), out)
    rows = RunDir(out).read_episodes()
    assert rows["checkpoint"].unique().tolist() == [str(checkpoint)]
    return out, rows


@pytest.mark.parametrize("workers", [1, 2])
def test_rows_of_the_same_shipped_checkpoint_at_another_path_are_continued_not_run_again(
    tmp_path, capsys, workers
):
    out, before = recorded_there(tmp_path, other_checkout(tmp_path))
    here = resumed_here()
    assert here.policies[0].config_id != before["policy_config_id"].iloc[0]  # what the bug ran again
    capsys.readouterr()
    # workers=2 rebuild the run in spawned processes, which must find episodes by the recorded id
    execution = Execution(workers=2, rebuild=resumed_here) if workers == 2 else None
    report = run(here, out, OpenMode.RESUME, execution=execution)
    assert (report.skipped, report.executed, report.failed) == (2, 1, 0)
    err = capsys.readouterr().err
    assert "its rows were recorded with the same shipped checkpoint" in err
    assert str(tmp_path / "other") in err and str(SHIPPED_CHECKPOINTS / SHIPPED_FILE) in err
    rows = RunDir(out).read_episodes().sort_values("episode_index")
    assert rows["episode_index"].tolist() == [0, 1, 2]
    assert rows["policy_config_id"].unique().tolist() == before["policy_config_id"].unique().tolist()
    assert rows["policy_params"].unique().tolist() == before["policy_params"].unique().tolist()
    assert rows["started_at"][:2].tolist() == before.sort_values("episode_index")["started_at"].tolist()
    assert rows["checkpoint"].iloc[2] == str(SHIPPED_CHECKPOINTS / SHIPPED_FILE)  # the file it loaded
    events = [json.loads(line)["event"] for line in open(out / "events.jsonl")]
    assert "checkpoint_matched_at_another_path" in events


def test_a_shipped_checkpoint_with_other_content_in_the_other_checkout_is_refused_and_nothing_written(
    tmp_path,
):
    out, _ = recorded_there(tmp_path, other_checkout(tmp_path, content=b"an older shipped file"))
    written = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and p.name != "writer.lock"}
    here = resumed_here()
    with pytest.raises(UsageError) as refused:
        run(here, out, OpenMode.RESUME)
    message = str(refused.value)
    assert message.startswith("--resume: policy 'bidirectional': its rows were recorded with checkpoint ")
    assert str(tmp_path / "other") in message and str(SHIPPED_CHECKPOINTS / SHIPPED_FILE) in message
    old = sha256_file(str(tmp_path / "other" / "policies" / "checkpoints" / SHIPPED_FILE))
    assert old[:12] in message and here.policies[0].checkpoint_sha256[:12] in message
    assert "shipped checkpoint changed" in message and "start a new --out" in message
    assert "commit that recorded them" in message
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and p.name != "writer.lock"}
    assert after == written


def _recorded(run_: PolicyRun, checkpoint: str) -> tuple[str, str]:
    """The params JSON and config id rows of `run_` recorded with `checkpoint` have."""
    pjson = params_json(parse_params(run_.spec, json.loads(run_.params_json) | {"checkpoint": checkpoint}))
    return pjson, policy_config_id(run_.spec.name, pjson, run_.checkpoint_sha256)


def _rows(*sets: tuple[str, str, str]) -> pd.DataFrame:
    return pd.DataFrame(
        [("bidirectional", p, c, d) for p, c, d in sets],
        columns=["policy", "policy_params", "policy_config_id", "checkpoint_sha256"],
    )


def test_a_policy_of_this_run_with_no_rows_yet_is_not_mistaken_for_moved_rows(tmp_path):
    """Two entries of one policy on two shipped checkpoints, only the first recorded (in
    another checkout): the first continues its rows, the second starts as itself."""
    first, second = decoder({}), decoder({"checkpoint": "chains-tray"})
    pjson, config_id = _recorded(first, str(tmp_path / "policies" / "checkpoints" / SHIPPED_FILE))
    resolved = fake_resolved(ChunkPolicy())
    resolved.policies = [first, second]
    second_id = second.config_id
    notices = adopt_moved_checkpoints({}, _rows((pjson, config_id, first.checkpoint_sha256)), resolved)
    assert len(notices) == 1 and (first.params_json, first.config_id) == (pjson, config_id)
    assert second.config_id == second_id


def test_a_user_checkpoint_of_the_same_name_and_content_elsewhere_is_continued_and_other_content_refused(
    tmp_path,
):
    """A checkpoint outside the shipped folder (a plugin's default inside its install) is
    matched the same way, by file name and sha256; rows of one differing only in
    `checkpoint` that nothing matches are refused rather than run again beside it."""
    run_ = decoder({})
    pjson, config_id = _recorded(run_, "/elsewhere/" + SHIPPED_FILE)
    resolved = fake_resolved(ChunkPolicy())
    resolved.policies = [run_]
    notices = adopt_moved_checkpoints({}, _rows((pjson, config_id, run_.checkpoint_sha256)), resolved)
    assert "the same checkpoint file" in notices[0] and run_.config_id == config_id

    for path, digest in (("/elsewhere/" + SHIPPED_FILE, "0" * 64), ("/elsewhere/renamed.safetensors", None)):
        run_ = decoder({})
        pjson, config_id = _recorded(run_, path)
        resolved.policies = [run_]
        with pytest.raises(UsageError, match="resuming would start it again as a new configuration"):
            adopt_moved_checkpoints({}, _rows((pjson, config_id, digest or run_.checkpoint_sha256)), resolved)


def test_rows_both_moved_and_predating_a_defaulted_parameter_are_continued(tmp_path):
    """A clone at another folder on an older package: the recorded set lacks `seed` (at
    its default now) as well as naming the other path."""
    run_ = decoder({})
    values = json.loads(run_.params_json) | {
        "checkpoint": str(tmp_path / "policies/checkpoints" / SHIPPED_FILE)
    }
    del values["seed"]
    pjson = json.dumps(values, sort_keys=True, separators=(",", ":"))
    resolved = fake_resolved(ChunkPolicy())
    resolved.policies = [run_]
    notices = adopt_moved_checkpoints({}, _rows((pjson, "recorded0001", run_.checkpoint_sha256)), resolved)
    assert "the same shipped checkpoint" in notices[0] and "at their defaults (seed=0)" in notices[0]
    assert (run_.params_json, run_.config_id) == (pjson, "recorded0001")
