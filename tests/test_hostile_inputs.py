"""Hostile or corrupt checkpoints and parameter values: refused with one line (exit 2),
before anything is allocated or written."""

from __future__ import annotations

import json
import warnings

import pytest
from safetensors.torch import load_file, save_file

from policies.dvla.checkpoint import CheckpointError, load
from policies.registry import PolicyParamError, get_policy, params_json, parse_params
from tests.test_dvla_policies import make_checkpoint

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def _rewrite(src, dst, edit=None, raw=None, tensors=None):
    """A copy of checkpoint `src` with its header edited (or replaced by `raw` text)."""
    from safetensors import safe_open

    with safe_open(str(src), framework="pt") as fh:
        header = json.loads(fh.metadata()["dvla_harness"])
    if edit:
        edit(header)
    text = raw if raw is not None else json.dumps(header)
    save_file(tensors or load_file(str(src)), str(dst), metadata={"dvla_harness": text})
    return dst


def _set(path, value):
    def edit(header):
        node = header
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return edit


@pytest.mark.parametrize(
    ("edit", "raw", "message"),
    [
        (_set(["model", "width"], -32), None, "model width=-32, valid range"),
        (_set(["model", "width"], 10**9), None, "model width=1000000000, valid range"),
        (_set(["model", "layers"], 3), None, "the weights do not fit the model it describes"),
        (_set(["meta"], "a string"), None, "'meta' must be a JSON object"),
        (_set(["vocab"], ["reach", "goal"]), None, "'vocab' must be a JSON object"),
        (None, "[" * 100_000 + "]" * 100_000, "nested too deeply"),
        (None, "[1, 2]", "not an object"),
        (_set(["state_mean", 0], float("nan")), None, "not finite"),
        (_set(["state_std", 3], 0.0), None, "std <= 0"),
        (_set(["tokenizer", "high", 0], float("inf")), None, "range is not finite"),
    ],
)
def test_a_hostile_header_is_refused_naming_the_problem(tmp_path, edit, raw, message):
    good = make_checkpoint(tmp_path / "good.safetensors", "bidirectional")
    bad = _rewrite(good, tmp_path / "bad.safetensors", edit, raw)
    with pytest.raises(CheckpointError, match=message.replace("(", r"\(")):
        load(bad)


def test_the_cli_refuses_a_hostile_checkpoint_with_one_line_and_nothing_written(cli, tmp_path):
    good = make_checkpoint(tmp_path / "good.safetensors", "bidirectional")
    bad = _rewrite(good, tmp_path / "bad.safetensors", _set(["model", "heads"], -1))
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", f"bidirectional:checkpoint={bad}",
        "--out", str(tmp_path / "run"), "--quiet",
    )  # fmt: skip
    assert code == 2 and "heads=-1" in err and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_a_dtype_conversion_on_load_is_stated(tmp_path):
    good = make_checkpoint(tmp_path / "good.safetensors", "bidirectional")
    half = {k: v.half() if v.is_floating_point() else v for k, v in load_file(str(good)).items()}
    path = _rewrite(good, tmp_path / "half.safetensors", tensors=half)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load(path)
    assert any("torch.float16, converted to float32" in str(w.message) for w in caught)


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"tau_conf": "nan"}, "must be a finite number"),
        ({"tau_conf": float("inf")}, "must be a finite number"),
        ({"seed": str(10**23)}, "out of range"),
    ],
)
def test_parameter_values_a_decoder_cannot_use_are_refused_at_parse_time(params, message):
    with pytest.raises(PolicyParamError, match=message):
        parse_params(get_policy("fast_dvla"), params)


def test_an_unbounded_integer_parameter_stays_a_machine_integer():
    with pytest.raises(PolicyParamError, match="out of range"):
        parse_params(get_policy("random"), {"seed": str(2**64)})
    assert json.loads(params_json(parse_params(get_policy("random"), {"seed": "7"})))["seed"] == 7


def test_a_parameter_given_twice_in_one_policy_string_is_an_error(cli, tmp_path):
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random:seed=1,seed=2",
        "--out", str(tmp_path / "run"), "--quiet",
    )  # fmt: skip
    assert code == 2 and "'seed' is given twice" in err
    assert not (tmp_path / "run").exists()


# --- malformed configs and manifests: one line, exit 2, nothing written ----------------

MT1 = [
    "run",
    "--suite",
    "metaworld/mt1/reach-v3",
    "--policy",
    "random",
    "--episodes-per-task",
    "1",
    "--quiet",
]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b'suite = "metaworld/mt1/reach-v3"\n# caf\xe9 in Latin-1\n', "is not UTF-8 text (byte 38)"),
        (
            b'suite = "metaworld/mt1/reach-v3"\ntasks = 5\n',
            "tasks must be a list of task names or indices, got 5",
        ),
        (b'suite = "metaworld/mt1/reach-v3"\ntasks = [true]\n', "tasks must be a list"),
        (b'suite = "metaworld/mt1/reach-v3"\npolicy = 5\n', "policy must be a list of [[policy]] tables"),
        (b'suite = "metaworld/mt1/reach-v3"\npolicy = {name = "random"}\n', "policy must be a list"),
    ],
)
def test_a_malformed_config_file_is_one_line_and_exit_2(cli, tmp_path, content, message):
    config = tmp_path / "bad.toml"
    config.write_bytes(content)
    code, _, err = cli("run", "--config", str(config), "--out", str(tmp_path / "run"), "--quiet")
    assert code == 2 and message in err and "Traceback" not in err
    assert err.count("\n") == 1 and not (tmp_path / "run").exists()


def test_an_output_folder_that_cannot_be_created_is_exit_2(cli, tmp_path):
    code, _, err = cli(*MT1, "--out", "/proc/dvla-harness-test/run")
    assert code == 2 and "cannot create output folder '/proc/dvla-harness-test/run'" in err
    assert err.count("\n") == 1


def test_overwrite_through_a_symlinked_run_folder_is_exit_2_and_deletes_nothing(cli, tmp_path):
    out, link = tmp_path / "run", tmp_path / "link"
    assert cli(*MT1, "--out", str(out))[0] == 0
    link.symlink_to(out)
    before = sorted(p.name for p in out.iterdir())
    code, _, err = cli(*MT1, "--out", str(link), "--overwrite")
    assert code == 2 and "is a symbolic link" in err and err.count("\n") == 1
    assert sorted(p.name for p in out.iterdir()) == before


def _edit_manifest(edit):
    def apply(path):
        manifest = json.loads(path.read_text())
        path.write_text(json.dumps(edit(manifest)))

    return apply


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        (lambda p: p.write_text("[1, 2]"), "not a run manifest (a JSON object), got a list"),
        (lambda p: p.write_text('"running"'), "not a run manifest (a JSON object), got a string"),
        (lambda p: p.write_bytes(b"\xff\xfe{}"), "invalid JSON"),
        (lambda p: p.write_text("[" * 100_000 + "]" * 100_000), "invalid JSON"),
        (_edit_manifest(lambda m: m | {"environment": "x"}), "field 'environment' must be an object"),
        (_edit_manifest(lambda m: m | {"suite": {"name": 5}}), "field 'suite.name' must be a string"),
        (_edit_manifest(lambda m: m | {"policies": [5]}), "field 'policies' entry 0 must be an object"),
        (
            _edit_manifest(lambda m: m | {"calibration": {"start": {"passes_per_s": "fast"}}}),
            "field 'calibration.start.passes_per_s' must be a number",
        ),
    ],
)
def test_a_manifest_that_is_not_the_object_the_harness_writes_is_refused_by_every_reader(
    cli, tmp_path, spoil, message
):
    good, bad = tmp_path / "good", tmp_path / "bad"
    for out in (good, bad):
        assert cli(*MT1, "--out", str(out))[0] == 0
    spoil(bad / "manifest.json")
    before = {p.name: p.read_bytes() for p in bad.iterdir()}
    for argv in (
        ["show", str(bad)],
        [*MT1, "--out", str(bad), "--resume"],
        ["leaderboard", str(bad)],
        ["gate", "--baseline", str(good), "--candidate", str(bad)],
        ["gate", "--baseline", str(bad), "--candidate", str(good)],
    ):
        code, _, err = cli(*argv)
        assert code == 2 and message in err and err.count("\n") == 1, (argv, err)
    assert {p.name: p.read_bytes() for p in bad.iterdir()} == before


def test_a_manifest_lacking_a_field_is_read_for_what_it_says_and_refused_for_resume(cli, tmp_path):
    out = tmp_path / "run"
    assert cli(*MT1, "--out", str(out))[0] == 0
    _edit_manifest(lambda m: {k: v for k, v in m.items() if k not in ("suite", "run_id", "resumed_at")})(
        out / "manifest.json"
    )
    code, text, err = cli("show", str(out))
    assert code == 0 and "run ? (finished), suite metaworld/mt1/reach-v3, 1 episodes" in text
    assert cli("leaderboard", str(out))[0] == 0
    code, _, err = cli(*MT1, "--out", str(out), "--resume")
    assert code == 2 and "lacks field 'run_id'" in err and err.count("\n") == 1


def test_the_cli_states_a_dtype_conversion_in_one_line(cli, tmp_path):
    good = make_checkpoint(tmp_path / "good.safetensors", "bidirectional")
    half = {k: v.half() if v.is_floating_point() else v for k, v in load_file(str(good)).items()}
    path = _rewrite(good, tmp_path / "half.safetensors", tensors=half)
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", f"bidirectional:checkpoint={path}",
        "--episodes-per-task", "1", "--out", str(tmp_path / "run"), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    line = (
        f"dvla-harness run: warning: {path}: weights stored as torch.float16, converted to float32 on load\n"
    )
    # the speed verdict on a busy machine (drift, starved episodes) is no part of the checkpoint's
    assert [ln for ln in err.splitlines(keepends=True) if "speed figures of this run" not in ln] == [line]


# --- things in a run folder that are not the files the harness writes -----------------


@pytest.fixture
def no_hang():
    """Fail a call that blocks (opening a FIFO waits for a writer forever) instead of
    hanging the test session: SIGALRM interrupts the blocked open."""
    import signal

    def alarm(signum, frame):
        raise TimeoutError("blocked for 30 s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(30)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def _snapshot(folder):
    return {p.name: p.read_bytes() if p.is_file() else p.stat().st_mode for p in folder.iterdir()}


@pytest.mark.parametrize(
    ("name", "kind", "said"),
    [
        ("events.jsonl", "fifo", "is a FIFO (named pipe), not a regular file"),
        ("pending.jsonl", "fifo", "is a FIFO (named pipe), not a regular file"),
        ("traces.jsonl", "fifo", "is a FIFO (named pipe), not a regular file"),
        ("writer.lock", "fifo", "not a regular file"),
        ("episodes.parquet", "dir", "is a folder, not a regular file"),
        ("pending.jsonl", "dir", "is a folder, not a regular file"),
    ],
)
def test_a_fifo_or_folder_in_place_of_a_run_file_is_refused_not_waited_on(
    cli, tmp_path, no_hang, name, kind, said
):
    import os

    out = tmp_path / "run"
    assert cli(*MT1, "--out", str(out))[0] == 0
    target = out / name
    target.unlink(missing_ok=True)
    os.mkfifo(target) if kind == "fifo" else target.mkdir()
    before = _snapshot(out)
    for argv in (
        [*MT1, "--episodes-per-task", "2", "--out", str(out), "--resume"],  # appends a row
        ["show", str(out)],
        ["leaderboard", str(out)],
    ):
        code, text, err = cli(*argv)
        assert code == 2 and said in err and err.count("\n") == 1, (argv, code, text, err)
        assert "Traceback" not in err
    assert _snapshot(out) == before


def test_an_empty_flag_value_is_refused_not_read_as_the_default(cli, tmp_path):
    out = tmp_path / "run"
    for argv, name in (
        (["run", "--suite", "", "--policy", "random", "--out", str(out)], "--suite"),
        (["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--config", " "], "--config"),
        (["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--out", ""], "--out"),
        (["show", ""], "RUN_DIR"),
        (["report", "html", str(out), "--out", ""], "--out"),
    ):
        code, _, err = cli(*argv)
        assert code == 2 and f"{name} is empty" in err and err.count("\n") == 1, (argv, err)
    assert not out.exists() and not (tmp_path / "runs").exists()


# --- chain files -------------------------------------------------------------------------


CHAIN_SCENE = "living_room_scene3"


def _chain_file(folder, edit):
    """Edit the chain file and record its new hash, as a deliberate change would, so the
    checks behind the hash (adapters/chain_scenes.check_chains_hash) see the edit."""
    from adapters import chain_scenes as cs

    path = folder / f"{CHAIN_SCENE}.chains.json"
    path.write_text(edit(json.loads(path.read_text()), path.read_text()))
    cs.record_chains_hash(CHAIN_SCENE)


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        # chain 200 starts from initial state 0 (200 % 50), as chain 0 does: the same episode twice
        (
            lambda d, t: json.dumps(d | {"chains": [*d["chains"], d["chains"][0]]}),
            "chain 200 repeats chain 0",
        ),
        # json keeps the last of two "chains": the first list would be dropped unseen
        (lambda d, t: t.replace('"chains":', '"chains": [], "chains":', 1), "key 'chains' appears twice"),
    ],
)
def test_a_chain_file_that_repeats_an_episode_is_refused_when_the_suite_loads(
    cli, tmp_path, chain_data, edit, needle
):
    from adapters import libero

    if not libero.installed():
        pytest.skip("needs the libero extra")
    _chain_file(chain_data, edit)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", f"chains/{CHAIN_SCENE}", "--policy", "libero_scripted", "--episodes-per-task", "1",
        "--out", str(out),
    )  # fmt: skip
    assert code == 2 and needle in err and err.count("\n") == 1, err
    assert not out.exists()


def test_the_shipped_chains_repeat_only_from_other_initial_states():
    """The sampler draws each chain independently: a few repeat, each from another start,
    so each is its own episode and the shipped suites load."""
    from adapters import chain_scenes as cs
    from adapters import libero

    for scene in cs.scene_names():
        chains = cs.load_chains(scene).chains
        assert len(set(chains)) < len(chains) == cs.CHAINS_PER_SCENE, scene
        cs.check_distinct(chains, libero.EPISODES_PER_TASK, scene)


def test_the_docs_say_openpi_client_needs_typing_extensions():
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "docs" / "remote-policies.md").read_text()
    install = next(line for line in text.splitlines() if "pip install" in line and "openpi-client" in line)
    assert "typing_extensions" in install and "does not" in text.split(install)[1][:400]


@pytest.mark.parametrize(
    ("suite", "key"),
    [
        ("libero/spatial:perturb=swap,perturb=lan", "perturb"),
        ("libero/spatial:perturb=swap,perturb=task", "perturb"),
        ("libero/spatial:obs=state, obs = images", "obs"),
        ("metaworld/mt10:layouts=upstream,seed=1,seed=2", "seed"),
        ("simpler/all:obs=images,obs=state", "obs"),
        ("chains/all:goal_positions=on,goal_positions=off", "goal_positions"),
    ],
)
def test_a_suite_option_given_twice_is_refused_not_read_as_its_last_value(suite, key):
    from adapters.base import SuiteOptionError
    from adapters.registry import load_suite

    with pytest.raises(SuiteOptionError, match=f"suite option '{key}' is given twice"):
        load_suite(suite)


def test_the_cli_refuses_a_repeated_suite_option_in_one_line_with_nothing_written(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3:layouts=upstream,layouts=fixed", "--policy", "random",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 2 and "'layouts' is given twice" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
