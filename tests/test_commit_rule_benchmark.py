"""benchmarks/commit_rule.py: the confidence each token had when pipelined decoding
committed it, read without changing the decoder."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

ROOT = Path(__file__).resolve().parent.parent
CKPT = ROOT / "policies" / "checkpoints"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location(
        "commit_rule_benchmark", ROOT / "benchmarks" / "commit_rule.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(bench, demos, tmp_path, settings: str) -> dict:
    out = tmp_path / "out.json"
    argv = [
        "--demos",
        str(demos),
        "--student",
        str(CKPT / "metaworld-mt10-fast_dvla.safetensors"),
        "--teacher",
        str(CKPT / "metaworld-mt10-bidirectional.safetensors"),
        "--settings",
        settings,
        "--samples",
        "24",
        "--batch",
        "8",
        "--json",
        str(out),
    ]
    assert bench.main(argv) == 0
    return json.loads(out.read_text())


def test_every_token_gets_the_confidence_it_was_committed_with(bench, demos, tmp_path, capsys):
    result = _run(bench, demos, tmp_path, ";tau_conf=0;tau_add=1,tau_act=1")
    teacher, default, nothing_below, block_by_block = result["rows"]
    assert teacher["same_as_teacher"] == 1.0 and teacher["below_tau_conf"] is None
    # tau_conf = 0: every token clears it, so the k-th-highest floor never decides one.
    assert nothing_below["below_tau_conf"] == 0.0
    assert nothing_below["same_as_teacher_below"] is None
    # The defaults commit some tokens below 0.5 (the floor is what makes pipelining fast
    # on a model whose confidences are not sharp) and decode in fewer passes than the
    # same weights block after block.
    assert 0.0 < default["below_tau_conf"] < 1.0
    assert default["nfe_per_chunk"] < block_by_block["nfe_per_chunk"]
    assert "| fast_dvla:tau_conf=0 |" in capsys.readouterr().out


def test_a_commit_record_out_of_step_with_the_passes_is_an_error(bench):
    from policies.dvla.decoding import Pass

    passes = [Pass([0, 1], True, 0, [[0]]), Pass([1], False, 1, [[1]])]
    calls = [np.array([0.9]), np.array([0.4])]
    conf = bench.commit_confidence(passes, calls, 1, 2)
    assert conf.tolist() == [[0.9, 0.4]]
    with pytest.raises(RuntimeError, match="out of step"):
        bench.commit_confidence(passes, [*calls, np.array([0.3])], 1, 2)


def test_confidences_land_on_their_rows_and_positions(bench):
    from policies.dvla.decoding import Pass

    # One pass over two rows: row 0 commits position 0 (block 0) and 2 (block 1), row 1
    # position 1; the decoder calls the commit rules row by row, block by block.
    passes = [Pass([0, 1, 2], True, 0, [[0, 2], [1]])]
    calls = [np.array([0.9]), np.array([0.8]), np.array([0.7])]
    conf = bench.commit_confidence(passes, calls, 2, 3)
    assert np.array_equal(conf, [[0.9, np.nan, 0.8], [np.nan, 0.7, np.nan]], equal_nan=True)


def test_the_decoders_commit_rules_are_restored_afterwards(bench):
    from policies.dvla import fast_dvla

    before = fast_dvla.commit_full
    with bench.recording_commits():
        assert fast_dvla.commit_full is not before
    assert fast_dvla.commit_full is before


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (
            {"--teacher": str(CKPT / "libero-spatial-bidirectional.safetensors")},
            "tokenize actions differently",
        ),
        ({"--settings": "n=0"}, "n=0 is out of range"),
        ({"--demos": "no-such-folder"}, "not a demonstrations folder"),
    ],
)
def test_bad_input_exits_2_naming_it_and_writes_nothing(bench, demos, tmp_path, capsys, change, named):
    out = tmp_path / "out.json"
    args = {
        "--demos": str(demos),
        "--student": str(CKPT / "metaworld-mt10-fast_dvla.safetensors"),
        "--teacher": str(CKPT / "metaworld-mt10-bidirectional.safetensors"),
        "--settings": "",
        "--samples": "8",
        "--json": str(out),
    } | change
    assert bench.main([item for pair in args.items() for item in pair]) == 2
    assert named in capsys.readouterr().err
    assert not out.exists()


def test_a_sample_count_below_one_is_a_usage_error(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bench.main(["--demos", "d", "--student", "s", "--teacher", "t", "--samples", "0"])
    assert stop.value.code == 2
    assert "--samples must be at least 1, got 0" in capsys.readouterr().err
