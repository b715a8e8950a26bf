"""benchmarks/gate_stability.py: it runs the documented CI job, and its test policies
change only what they claim to change (time for slow15, work per pass for morework)."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from harness.episode.nfe import NFECounter
from policies.base import EpisodeContext
from policies.registry import get_policy, parse_params
from tests.test_dvla_policies import make_checkpoint

ROOT = Path(__file__).resolve().parent.parent


def load_benchmark():
    spec = importlib.util.spec_from_file_location("gate_stability", ROOT / "benchmarks" / "gate_stability.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_benchmark_runs_the_ci_job_the_docs_give():
    bench = load_benchmark()
    text = (ROOT / "docs" / "ci-gate.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S).group(1)
    documented = [shlex.split(line)[1:] for line in block.splitlines() if "dvla-harness" in line]
    documented = [[a for a in argv if a != "dvla-harness"] for argv in documented]
    ours = [[a.replace("{out}", "runs/ci") for a in command] for command in bench.CI_COMMANDS]
    assert documented == ours


def test_verdicts_are_read_from_the_gate_exit_and_its_warning():
    bench = load_benchmark()
    assert bench.verdict(0, "gate passed: ...") == "pass"
    assert bench.verdict(0, "warning: fast_dvla: replay speed inconclusive") == "inconclusive"
    assert bench.verdict(1, "gate failed:\n  fast_dvla: ...") == "fail"
    assert bench.verdict(2, "error: ...") == "error (exit 2)"
    wrapped = "note: x\nverdict: fast_dvla: speed pass on the replay, -1.0%; figure\ndoubtful: load\ngate passed: ok"
    assert bench.verdict_lines(wrapped) == [
        "verdict: fast_dvla: speed pass on the replay, -1.0%; figure doubtful: load"
    ]
    assert bench.failing_lines("table\ngate failed:\n  fast_dvla: NFE up") == [
        "gate failed:",
        "fast_dvla: NFE up",
    ]


def test_it_refuses_a_machine_whose_cpu_is_not_the_baselines(monkeypatch):
    # there the gate leaves speed "not comparable": every trial would pass, untimed
    bench = load_benchmark()
    import harness.run.manifest

    recorded = json.loads((ROOT / bench.BASELINE / "manifest.json").read_text())["environment"]
    other = {"cpu": "Some Other CPU", "cpu_identity": {"model_name": "Some Other CPU", "family": 6}}
    monkeypatch.setattr(harness.run.manifest, "environment", lambda: other)
    with pytest.raises(
        SystemExit, match=re.escape("this machine's CPU (Some Other CPU) is not the committed")
    ):
        bench.refuse_another_cpu()
    monkeypatch.setattr(harness.run.manifest, "environment", lambda: recorded)
    bench.refuse_another_cpu()  # the same CPU: no objection


def test_unknown_conditions_and_candidates_are_refused():
    bench = load_benchmark()
    with pytest.raises(SystemExit, match="valid: idle, busy2, busy8, tests"):
        bench.choices("idle,noisy", bench.CONDITIONS, "conditions")


def small_fast_dvla(tmp_path):
    """A small fast_dvla checkpoint's spec and params, with one Meta-World-shaped
    observation and its context."""
    ckpt = make_checkpoint(tmp_path / "m.safetensors", "block_causal", 4)
    spec = get_policy("fast_dvla")
    space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
    contexts = [
        EpisodeContext(
            "metaworld/mt10", "reach-v3", "reach the goal", space, gym.spaces.Box(-9, 9, (39,)), 50, 0
        )
    ]
    observations = [np.random.default_rng(0).uniform(-1, 1, 39).astype(np.float32)]
    return spec, parse_params(spec, {"checkpoint": str(ckpt)}), contexts, observations


def _decode(policy, observations, contexts):
    counter = NFECounter()
    policy.reset(contexts)
    with counter.counting():
        batch = policy.act(observations)
    return batch, counter.take(), counter.take_work()


def test_the_test_policies_keep_actions_and_passes(tmp_path, one_torch_thread):
    """slow15 and morework must differ from fast_dvla only in time and in work per pass;
    otherwise the benchmark's detection rates would measure something else."""
    bench = load_benchmark()
    spec, params, contexts, observations = small_fast_dvla(tmp_path)
    plain, plain_nfe, plain_work = _decode(spec.build(params), observations, contexts)

    slowed = spec.build(params)
    bench.spin_after_each_pass(slowed.model, 0.15)
    slow, slow_nfe, slow_work = _decode(slowed, observations, contexts)
    doubled, doubled_nfe, doubled_work = _decode(
        bench.DoubledBatch(spec.build(params)), observations, contexts
    )

    for batch, nfe in ((slow, slow_nfe), (doubled, doubled_nfe)):
        np.testing.assert_array_equal(batch.actions, plain.actions)
        assert batch.action_tokens == plain.action_tokens
        assert nfe == plain_nfe > 0
    assert slow_work == plain_work and plain_work.flops > 0
    assert doubled_work.flops == 2 * plain_work.flops  # the work the gate must catch


def test_the_raw_product_adds_work_only_the_dispatcher_sees(tmp_path, one_torch_thread, monkeypatch):
    """rawmatmul: the same actions and passes, and work the module hooks cannot see; the
    replay bench's warm-up counts it at the dispatcher, which the gate compares."""
    from harness.bench import warm_up_pass
    from policies.dvla import fast_dvla

    bench = load_benchmark()
    spec, params, contexts, observations = small_fast_dvla(tmp_path)
    policy = spec.build(params)
    plain = warm_up_pass(policy, contexts, observations)
    plain_batch, _, _ = _decode(policy, observations, contexts)
    monkeypatch.setattr(fast_dvla, "decode_fast_dvla", bench.with_raw_product(fast_dvla.decode_fast_dvla))
    raw = warm_up_pass(policy, contexts, observations)
    raw_batch, _, _ = _decode(policy, observations, contexts)
    np.testing.assert_array_equal(raw_batch.actions, plain_batch.actions)
    assert raw.nfe == plain.nfe > 0 and raw.action_tokens == plain.action_tokens
    assert raw.module_flops == plain.module_flops == plain.flops  # the hooks see nothing new
    width = policy.model.cfg.width
    assert raw.flops - plain.flops == plain.nfe * 2 * 16 * width * int(6.5 * width)  # one per pass
