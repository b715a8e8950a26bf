"""benchmarks/decoders.py: replay runs exactly the passes a trace records (what the
README's speed table is made of), at tiny shapes."""

from __future__ import annotations

import importlib.util
import json
import random
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

ROOT = Path(__file__).resolve().parent.parent
# The paper's chunk (8 steps x 7-D actions = 56 tokens), so the committed traces fit;
# everything else tiny (prefix of 8 positions where the recording model had 22).
TINY = {
    "action_dim": 7,
    "chunk_len": 8,
    "state_dim": 5,
    "max_words": 6,
    "state_tokens": 2,
    "width": 32,
    "layers": 2,
    "heads": 4,
    "ffn": 64,
    "bins": 16,
    "vocab_words": 20,
}


def _decoders_benchmark():
    path = ROOT / "benchmarks" / "decoders.py"
    spec = importlib.util.spec_from_file_location("decoders_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


class Recording:
    """The model, recording what each call ran: query positions, prefix, cache length."""

    def __init__(self, model):
        self.model, self.cfg = model, model.cfg
        self.calls: list[tuple[list[int], bool, int]] = []

    def __call__(self, action_tokens=None, action_positions=None, words=None, state=None, cache=None, **kw):
        self.calls.append((action_positions.tolist(), words is not None, 0 if cache is None else len(cache)))
        return self.model(action_tokens, action_positions, words, state, cache, **kw)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny passes on a shared machine: a second thread only waits (70x slower, seen)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def bench():
    return _decoders_benchmark()


@pytest.fixture(scope="module")
def tiny(bench):
    import torch

    with torch.random.fork_rng(devices=[]), torch.inference_mode():
        return bench.build(TINY, "cpu")


def test_committed_traces_are_trained_56_token_chunks(bench):
    record = json.loads(bench.TRACES.read_text())
    assert set(record["decoders"]) == set(bench.RECORDED)
    assert bench.TRACES.stat().st_size < 1_000_000
    for name, d in record["decoders"].items():
        assert d["action_tokens"] == 56 and len(d["chunks"]) >= 100, name
    traces = bench.load_traces()
    # Trained weights: fast_dvla's blocks overlap (a pass runs more than one block) and
    # fast_dllm's blocks take a data-dependent number of steps (not the fixed 4).
    dvla = traces["fast_dvla"]["chunks"]
    assert max(len(q) for c in dvla for q in c.query) > 7
    assert len({len(c.query) for c in dvla}) > 1
    assert len({len(c.query) for c in traces["fast_dllm"]["chunks"]}) > 1


@pytest.mark.parametrize("name", ["fast_dvla", "fast_dllm"])
def test_replay_runs_the_recorded_passes(bench, tiny, name):
    import torch

    models, (words, state), _ = tiny
    rec = bench.load_traces()[name]
    model = Recording(models[bench.PATTERN[name]])
    p = model.cfg.prefix_len
    assert p != rec["prefix_len"]  # the cache reads move with the prefix
    with torch.inference_mode():
        for chunk in rec["chunks"][:12]:
            model.calls.clear()
            done = bench.replay(model, chunk.at_prefix(rec["prefix_len"], p), words, state)
            want = [
                (q, pre, c - rec["prefix_len"] + p if c else 0)
                for q, pre, c in zip(chunk.query, chunk.prefix, chunk.cached, strict=True)
            ]
            assert model.calls == want
            assert done["nfe"] == len(chunk.query)
            assert done["query_tokens"] == sum(len(q) for q in chunk.query)
            assert done["cached_read"] == sum(c for *_, c in want)
            assert done["tokens_run"] == done["query_tokens"] + p * sum(chunk.prefix)


@pytest.mark.parametrize(
    "name",
    ["bidirectional", "bidirectional_cached", "block_diffusion", "autoregressive", "fast_dvla", "fast_dllm"],
)
def test_replay_of_a_decoders_own_trace_makes_its_calls(bench, tiny, name):
    """A decode's passes, replayed, are the decoder's own calls (fixed-schedule decoders'
    traces are generated this way; on random weights the adaptive ones work too)."""
    import torch

    models, (words, state), _ = tiny
    model = Recording(models[bench.PATTERN[name]])
    with torch.inference_mode():
        chunk = bench.generated(name, model, words, state)
        decoded = list(model.calls)
        model.calls.clear()
        bench.replay(model, chunk, words, state)
    assert model.calls == decoded
    assert [pre for _, pre, _ in decoded] == chunk.prefix and [c for *_, c in decoded] == chunk.cached


def test_the_reference_row_decodes_the_bidirectional_rows_tokens(bench, tiny):
    """The prefix-cached reference is the bidirectional decode with less work: on the
    benchmark's own models, same tokens and commits, the prefix computed once."""
    import torch

    models, (words, state), _ = tiny
    with torch.inference_mode():
        plain = bench.decode("bidirectional", models[bench.PATTERN["bidirectional_cached"]], words, state)
        cached = bench.decode(
            "bidirectional_cached", models[bench.PATTERN["bidirectional_cached"]], words, state
        )
    assert torch.equal(plain.tokens, cached.tokens)
    assert [p.committed for p in plain.passes] == [p.committed for p in cached.passes]
    assert sum(p.prefix for p in plain.passes) == 12 and sum(p.prefix for p in cached.passes) == 1
    # its model shares the bidirectional one's weights; only the prefix's mask differs
    a, b = models["bidirectional"].state_dict(), models[bench.PATTERN["bidirectional_cached"]].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not models[bench.PATTERN["bidirectional_cached"]].cfg.prefix_sees_actions


def test_chunk_counts_what_each_pass_processes(bench):
    # a prefix pass over 2 queries, then 3 queries against a cache of 10 (prefix of 8)
    counts = bench.Chunk([[0, 1], [2, 3, 4]], [True, False], [0, 10]).counts(8)
    assert counts == {
        "nfe": 2,
        "prefix_passes": 1,
        "query_tokens": 5,
        "tokens_run": 13,
        "cached_read": 10,
        "kv_attended": 10 + 13,
        "scores": 10 * 10 + 3 * 13,
    }


def test_worker_times_every_decoder_side_by_side(bench, capsys):
    import torch

    grad = torch.is_grad_enabled()
    with torch.random.fork_rng(devices=[]):
        try:
            result = bench.measure(rounds=2, chunks=2, shape=TINY, device="cpu")
        finally:
            torch.set_grad_enabled(grad)
    rows = {r["decoder"]: r for r in result["rows"]}
    assert list(rows) == list(bench.DECODERS) and result["device"] == "cpu"
    # the shape timed is the one asked for (--width/--layers/...), recorded with its size
    assert result["shape"] == TINY and 0 < result["parameters"] < 10**6
    assert rows["bidirectional"]["nfe"] == 12 and rows["bidirectional"]["cached_read"] == 0
    assert rows["bidirectional"]["speedup_vs_bidirectional"] == pytest.approx(1.0)
    p, a = result["prefix_len"], result["action_tokens"]
    ref = rows["bidirectional_cached"]  # one prefix pass, 11 passes of the actions against it
    assert (ref["nfe"], ref["prefix_passes"], ref["query_tokens"]) == (12, 1, 12 * a)
    assert ref["tokens_run"] == p + 12 * a and ref["cached_read"] == 11 * p
    assert ref["kv_attended"] == rows["bidirectional"]["kv_attended"] == 12 * (p + a)
    assert ref["scores"] == (p + a) ** 2 + 11 * a * (p + a)
    assert rows["bidirectional"]["scores"] == 12 * (p + a) ** 2
    assert ref["speedup_vs_cached"] == pytest.approx(1.0)
    for row in rows.values():
        assert {
            "speedup_vs_bidirectional",
            "speedup_ci95",
            "speedup_vs_cached",
            "speedup_vs_cached_ci95",
        } <= set(row)
    bench.report(result)
    table = capsys.readouterr().out
    assert "bidirectional_cached" in table and "vs cached" in table and "kv attended" in table
    assert "caching the prefix alone buys" in table and "  fast_dvla: " in table
    assert f"width {TINY['width']}, {TINY['layers']} layers" in table
    assert rows["autoregressive"]["nfe"] == 56 and rows["autoregressive"]["query_tokens"] == 56
    assert rows["block_diffusion"]["nfe"] == 32
    # autoregressive pass i reads the prefix and tokens 0..i-1
    assert rows["autoregressive"]["cached_read"] == sum(p + i for i in range(1, 56))
    for row in rows.values():
        assert row["ms_per_chunk"] > 0 and row["ms_per_chunk_ci95"] >= 0 and row["chunks_timed"] == 4
    # the timed recorded chunks are the first four of the seeded shuffle, counted as replayed
    traces = bench.load_traces()
    for name in bench.RECORDED:
        chunks = [c.at_prefix(traces[name]["prefix_len"], p) for c in traces[name]["chunks"]]
        random.Random(0).shuffle(chunks)
        want = sum(sum(c.cached) for c in chunks[:4]) / 4
        assert rows[name]["cached_read"] == pytest.approx(want)
        assert rows[name]["all_chunks"]["chunks"] == len(chunks)


def test_threads_benchmark_compares_both_thread_counts_idle_and_under_load(tmp_path):
    """benchmarks/threads.py on one MT10 task, one scripted episode: both conditions, both
    thread counts, the comparison over common episodes, and no busy loop left behind."""
    import os
    import subprocess

    config = tmp_path / "tiny.toml"
    config.write_text(
        'suite = "metaworld/mt10"\ntasks = ["reach-v3"]\nepisodes_per_task = 1\n[[policy]]\nname = "scripted"\n'
    )
    out = tmp_path / "threads.json"
    argv = ["--config", str(config), "--load-procs", "1", "--time-box", "45", "--json", str(out)]
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "threads.py"), *argv],
        cwd=ROOT,
        env=os.environ | {"PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    assert list(result["conditions"]) == ["idle", "load"]
    assert result["conditions"]["load"]["load_procs"] == 1 and len(result["load_pids"]) == 1
    assert [c["order"] for c in result["conditions"].values()] == [[1, 2], [2, 1]]
    for condition in result["conditions"].values():
        runs = condition["runs"]
        assert [r["threads"] for r in runs] == [1, 2]
        for r in runs:
            assert r["episodes"] == r["episodes_planned"] == 1 and r["exit_status"] == 0
            assert {"load1_before", "load1_after", "run_wall_s", "stopped_at_time_box"} <= set(r)
        cmp = condition["comparison"]
        assert cmp["common_episodes"] == 1 and cmp["same_successes_and_steps"] is True
        assert cmp["episodes_differing"] == 0
        assert len(cmp["wall_clock_s"]) == len(cmp["policy_time_s"]) == len(cmp["tokens_per_s"]) == 2
        assert cmp["wall_clock_ratio"] > 0 and "policy_time_ratio" in cmp
    assert result["machine"]["cpu"] and "torch" in result["machine"]
    assert "| idle |" in done.stdout and "| load (1 busy loops) |" in done.stdout
    for pid in result["load_pids"]:  # killed and reaped: gone, or at least no longer the busy loop
        cmdline = Path(f"/proc/{pid}/cmdline")
        assert not cmdline.exists() or b"while True" not in cmdline.read_bytes()


def test_threads_benchmark_stops_a_run_at_its_time_box(tmp_path):
    """A run past its time box is stopped (SIGTERM, then SIGKILL) and its process is gone."""
    import argparse

    spec = importlib.util.spec_from_file_location("threads_benchmark", ROOT / "benchmarks" / "threads.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    args = argparse.Namespace(config=None, tasks="reach-v3", episodes_per_task=50)
    r = bench.timed_run(args, 1, tmp_path / "boxed", time_box=1.0)
    assert r["stopped_at_time_box"] and r["exit_status"] != 0
    assert r["run_wall_s"] < 1.0 + bench.GRACE_S


def test_scaling_benchmark_compares_batched_modes_less_what_batching_defines(tmp_path):
    """benchmarks/scaling.py on one MT10 task: the batched mode runs, is compared with the
    unbatched one on every result column but NFE, and the expert workload skips it."""
    import os
    import subprocess

    pytest.importorskip("metaworld")
    out = tmp_path / "scaling.json"
    argv = ["--workloads", "mt10", "--tasks", "reach-v3", "--episodes-per-task", "3"]
    argv += ["--modes", "local x1,local x1 b8", "--json", str(out)]
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "scaling.py"), *argv],
        cwd=ROOT,
        env=os.environ | {"PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    runs = json.loads(out.read_text())["workloads"]["mt10"]["runs"]
    assert [r["mode"] for r in runs] == ["local x1", "local x1 b8"]
    assert all(r["episodes"] == 3 and r["failed"] == 0 for r in runs)
    assert runs[1]["episodes_differing_from_first"] == 0  # same actions, batched or not
    assert (
        "episodes_nfe_differing_from_first" in runs[1] and "episodes_nfe_differing_from_first" not in runs[0]
    )
    bad = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "scaling.py"), "--modes", "local x9"],
        cwd=ROOT,
        env=os.environ | {"PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "valid: local x1, local x2, ray x2" in bad.stderr
