"""--resume checks the manifest against the rows the folder already holds: a manifest.json
edited by hand (or damaged) is refused naming the field, before anything is written,
instead of adding rows of another configuration beside the recorded ones."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from harness.cli import main

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

RUN = ["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random:seed=3", "--episodes-per-task", "2"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A finished run of 2 episodes, copied by each test before it edits the copy."""
    out = tmp_path_factory.mktemp("recorded") / "run"
    assert main([*RUN, "--out", str(out), "--quiet"]) == 0
    return out


def _edit(policy: dict) -> None:
    policy["params"]["seed"] = "4"


EDITS: dict[str, tuple[Callable[[dict], None], str]] = {
    "replan_every": (
        lambda m: m["config"].update(replan_every=2),
        "replan_every: the manifest's config says 2, and 2 of its 2 rows were recorded with 0",
    ),
    "a policy parameter": (
        lambda m: _edit(m["config"]["policies"][0]),
        "policy 'random' parameter seed: the manifest's config gives 4, its rows were recorded with 3, "
        "so 2 of its 2 rows are no episode of it",
    ),
    "the out-of-space rule": (
        lambda m: m["config"].update(out_of_space="clip"),
        'out_of_space: the manifest\'s config says "clip", and 2 of its 2 rows were recorded with "fail"',
    ),
    "the split": (
        lambda m: m["config"].update(split="train"),
        "seed: episode 0 of task 'reach-v3' was recorded with",
    ),
    "the fingerprint": (
        lambda m: m.update(config_fingerprint="0123456789abcdef"),
        "config_fingerprint: the manifest records 0123456789abcdef, and the config beside it gives",
    ),
}


@pytest.mark.parametrize("edited", list(EDITS))
def test_a_hand_edited_manifest_is_refused_naming_the_field_and_nothing_is_written(
    cli, tmp_path, recorded, edited
):
    edit, message = EDITS[edited]
    out = tmp_path / "run"
    shutil.copytree(recorded, out)
    manifest = json.loads((out / "manifest.json").read_text())
    edit(manifest)
    (out / "manifest.json").write_text(json.dumps(manifest))
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != "writer.lock"}
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "3", "--quiet")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "its manifest.json disagrees with the rows it holds" in err and message in err
    after = {p.name: p.read_bytes() for p in out.iterdir() if p.name != "writer.lock"}
    assert after == before


def test_an_untouched_manifest_resumes_and_extends(cli, tmp_path, recorded):
    out = tmp_path / "run"
    shutil.copytree(recorded, out)
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "3", "--quiet")
    assert code == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["episodes_per_task"] == 3
    # the extended run's fingerprint is its recorded config's, so it resumes again
    code, _, err = cli("run", "--out", str(out), "--resume", "--quiet")
    assert code == 0 and "3 episode(s) already recorded, 0 to run" in err, err
