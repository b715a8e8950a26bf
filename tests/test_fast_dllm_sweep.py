"""benchmarks/fast_dllm_sweep.py: the Pareto front and the rule that picks fast_dllm's
defaults, and the policy's defaults being the committed sweep's choice."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from policies.dvla.policy import FastDLLMParams, blocks_error

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

ROOT = Path(__file__).resolve().parent.parent
SWEEP = ROOT / "benchmarks" / "results" / "fast-dllm-sweep.json"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location(
        "fast_dllm_sweep", ROOT / "benchmarks" / "fast_dllm_sweep.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _row(blocks: int, threshold: float, nfe: float, agree: float, teacher_nfe: float = 12.0) -> dict:
    return {
        "blocks": blocks,
        "threshold": threshold,
        "nfe_per_chunk": nfe,
        "same_as_teacher": agree,
        "teacher_nfe": teacher_nfe,
    }


def test_pareto_front_keeps_only_unbeaten_points(bench):
    points = [(10.0, 0.70), (12.0, 0.80), (12.0, 0.75), (20.0, 0.80), (8.0, 0.60), (9.0, 0.55)]
    # (12, .75) is beaten by (12, .80); (20, .80) by (12, .80); (9, .55) by (8, .60)
    assert bench.pareto_front(points) == [0, 1, 4]
    assert bench.pareto_front([(5.0, 0.5), (5.0, 0.5)]) == [0, 1]  # equal points beat neither


def test_select_takes_the_fewest_passes_within_tolerance_of_each_sets_best(bench):
    sets = {
        "a": [
            _row(8, 0.9, 24.0, 0.70),
            _row(2, 0.5, 14.0, 0.79),
            _row(1, 0.3, 9.0, 0.74),
            _row(2, 0.3, 11.0, 0.78),
        ],
        "b": [
            _row(8, 0.9, 20.0, 0.72),
            _row(2, 0.5, 12.0, 0.73),
            _row(1, 0.3, 8.0, 0.73),
            _row(2, 0.3, 10.0, 0.72),
        ],
    }
    # best: a 0.79, b 0.73. Within 0.02: a keeps (2,.5) and (2,.3); b keeps all but (8,.9).
    # (1,.3) is cheapest but 0.05 short on a; (2,.3) is the cheapest that qualifies on both.
    assert bench.select(sets, tolerance=0.02) == (2, 0.3)
    # A looser tolerance lets the cheaper whole-chunk block in.
    assert bench.select(sets, tolerance=0.06) == (1, 0.3)


def test_select_compares_passes_relative_to_each_sets_teacher(bench):
    # On set "slow" the teacher takes 40 passes: 30 there is cheap, 11 on "fast" is not.
    sets = {
        "fast": [_row(1, 0.3, 11.0, 0.8, teacher_nfe=12.0), _row(2, 0.3, 6.0, 0.8, teacher_nfe=12.0)],
        "slow": [_row(1, 0.3, 20.0, 0.8, teacher_nfe=40.0), _row(2, 0.3, 36.0, 0.8, teacher_nfe=40.0)],
    }
    # (1): 11/12 and 20/40, mean 0.708; (2): 6/12 and 36/40, mean 0.70
    assert bench.select(sets, tolerance=0.0) == (2, 0.3)


def test_select_uses_only_settings_every_set_has_and_refuses_when_none_qualifies(bench):
    sets = {
        "a": [_row(1, 0.3, 5.0, 0.9), _row(2, 0.3, 9.0, 0.9)],
        "b": [_row(2, 0.3, 9.0, 0.9)],
    }
    assert bench.select(sets) == (2, 0.3)
    with pytest.raises(ValueError, match=r"within 0\.01"):
        bench.select(
            {
                "a": [_row(1, 0.3, 5.0, 0.9), _row(2, 0.3, 9.0, 0.5)],
                "b": [_row(1, 0.3, 5.0, 0.5), _row(2, 0.3, 9.0, 0.9)],
            },
            0.01,
        )
    with pytest.raises(ValueError, match="no sweep results"):
        bench.select({})


def test_policy_defaults_are_the_committed_sweeps_choice(bench):
    """The defaults and the sweep that chose them cannot drift apart: a new sweep that picks
    another setting fails here until FastDLLMParams follows it."""
    committed = json.loads(SWEEP.read_text())
    sets = {
        label: [r for r in result["rows"] if "blocks" in r] for label, result in committed["sets"].items()
    }
    chosen = bench.select(sets, committed["tolerance"])
    assert chosen == (committed["chosen"]["blocks"], committed["chosen"]["threshold"])
    params = FastDLLMParams(checkpoint=__file__)
    assert (params.blocks, params.threshold, params.block_size) == (*chosen, 0)
    assert {"metaworld-mt10", "libero-spatial", "chains-tray"} <= set(committed["sets"])


def test_blocks_that_do_not_divide_the_chunk_are_refused_with_the_valid_ones():
    params = FastDLLMParams(checkpoint=__file__, blocks=3)
    assert blocks_error(params, 32) == (
        "blocks=3 does not divide the chunk's 32 action tokens; valid: 1, 2, 4, 8, 16, 32 (or set block_size)"
    )
    assert blocks_error(FastDLLMParams(checkpoint=__file__, blocks=3, block_size=8), 32) is None
    assert blocks_error(FastDLLMParams(checkpoint=__file__, blocks=8), 56) is None


def test_measure_counts_each_states_passes_as_if_it_were_decoded_alone(bench, demos, tmp_path):
    out = tmp_path / "sweep.json"
    teacher = str(ROOT / "policies" / "checkpoints" / "metaworld-mt10-bidirectional.safetensors")
    argv = ["measure", "--label", "mt", "--demos", str(demos), "--teacher", teacher, "--thresholds", "0.5"]
    assert bench.main([*argv, "--samples", "6", "--batch", "6", "--json", str(out)]) == 0
    batched = json.loads(out.read_text())
    assert bench.main([*argv, "--samples", "6", "--batch", "1", "--json", str(out)]) == 0
    alone = json.loads(out.read_text())
    assert batched["teacher_row"]["nfe_per_chunk"] == 12.0
    assert [r["block_size"] for r in batched["rows"]] == [4, 8, 16, 32]
    assert [r["blocks"] for r in batched["rows"]] == [8, 4, 2, 1]
    for b, a in zip(batched["rows"], alone["rows"], strict=True):
        assert b["nfe_per_chunk"] == a["nfe_per_chunk"] and b["same_as_teacher"] == a["same_as_teacher"]
    # one action step a block refreshes 8 times: at least 8 passes, however sure the model
    assert batched["rows"][0]["nfe_per_chunk"] >= 8


def test_measure_refuses_a_bad_threshold_list(bench, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(
            [
                "measure",
                "--label",
                "x",
                "--demos",
                "d",
                "--teacher",
                "t",
                "--thresholds",
                "0.5,1.5",
                "--json",
                str(tmp_path / "o.json"),
            ]
        )
    assert exc.value.code == 2 and "each must be in (0, 1]" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()


def test_resume_does_not_adopt_rows_recorded_before_blocks_existed():
    """Such rows decoded one action step a block; `blocks`' default (the whole chunk) is
    another decoder, so they must not be counted as made at it."""
    from harness.run.resume import _added_at_default
    from policies.registry import params_json

    current = FastDLLMParams(checkpoint=__file__, threshold=0.9)
    recorded = json.loads(params_json(current))
    del recorded["blocks"]
    assert _added_at_default(json.dumps(recorded), params_json(current), FastDLLMParams) == {}
    # another parameter added at its default is still adopted
    recorded = json.loads(params_json(current))
    del recorded["seed"]
    assert _added_at_default(json.dumps(recorded), params_json(current), FastDLLMParams) == {"seed": 0}
