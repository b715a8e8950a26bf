"""Inference latency (harness/episode/latency.py, harness/episode/plan.py): d control steps per chunk,
sync holds, async skips, chains, determinism across threads and workers, the gate and
the CLI's refusals."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import pandas as pd
import pytest
import torch

from adapters.base import EpisodeSpec
from harness.backends import Execution
from harness.episode.latency import LatencyPlan, delay_steps, parse_latency
from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from policies.base import ChunkBatch, EpisodeContext
from results.gate import GateInputError, gate
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS
from tests.fakes import CountdownEnv, context, fake_resolved, run_one
from tests.test_remote import serve_process  # noqa: F401  (a fixture)

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

HZ = 10.0  # the fake suite's control frequency: 100 ms a step


class PassingPolicy:
    """Chunk k (from 1) holds actions k*10 + i, so the env's actions say which chunk and
    index ran; each call runs `passes` (a sequence, cycled) forward passes of a real
    module, which the harness counts; it records the observations and instructions seen."""

    def __init__(self, chunk: int = 4, passes: Sequence[int] = (2,)):
        self.chunk, self.passes = chunk, tuple(passes)
        self.model = torch.nn.Linear(1, 1)
        self.seen: list[float] = []
        self.instructions: list[str] = []
        self.calls = self.since_reset = 0

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.instructions.append(episodes[0].instruction)
        self.since_reset = 0  # passes depend on the episode alone, whichever worker runs it

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        with torch.no_grad():
            for _ in range(self.passes[self.since_reset % len(self.passes)]):
                self.model(torch.zeros(1, 1))
        self.calls += 1
        self.since_reset += 1
        self.seen.append(float(np.asarray(observations[0])[0]))
        values = self.calls * 10 + np.arange(self.chunk, dtype=float)
        return ChunkBatch(actions=np.repeat(values[:, None], 2, axis=1)[None], action_tokens=self.chunk * 2)


def executed(env: CountdownEnv) -> list:
    """Per env step: (chunk, index) of the action it got, or "H" for a hold."""
    return ["H" if a[0] == 0 else (int(a[0]) // 10, int(a[0]) % 10) for a in env.actions]


def episode(mode: str, execution: str, replan_every: int = 0, max_steps: int = 20, env=None, policy=None):
    env = env or CountdownEnv(None)
    policy = policy or PassingPolicy()
    latency = parse_latency(mode)
    plan = None if latency.kind == "none" else LatencyPlan(latency, execution, HZ)
    out = run_one(env, policy, context(max_steps), EpisodeSpec(0, 1), replan_every, latency=plan)
    return out, env, policy


H = "H"


def test_delay_is_the_ceiling_of_latency_over_the_control_period():
    assert delay_steps(0.05, 20.0) == 1  # exactly one period: 1, not 2 from rounding
    assert delay_steps(0.051, 20.0) == 2
    assert delay_steps(0.0, 20.0) == 0
    assert parse_latency("passes:100").text == "passes:100"
    assert parse_latency("passes:2.5+10").fixed_ms == 10.0


def test_sync_holds_d_steps_before_every_chunk_against_the_budget():
    out, env, policy = episode("passes:100", "sync")  # 2 passes x 100 ms at 10 Hz: d = 2
    assert executed(env) == [H, H, *[(1, i) for i in range(4)], H, H, *[(2, i) for i in range(4)],
                             H, H, *[(3, i) for i in range(4)], H, H]  # fmt: skip
    assert policy.seen == [0, 6, 12, 18]  # each request from the observation when it was made
    assert out.steps == 20 and out.hold_steps == 8 and out.chunks == 4
    assert (out.delay_steps_mean, out.delay_steps_max) == (2.0, 2)
    assert out.late_chunks == 2  # chunks 2 and 3; the first is awaited, the fourth never came


def test_async_skips_exactly_d_actions_of_every_chunk_that_follows_another():
    out, env, policy = episode("passes:100", "async", replan_every=2)
    # first chunk awaited (nothing moving); then a request every 2 steps, each chunk
    # arriving while the previous one still has actions: no holds, first 2 actions skipped
    assert executed(env)[:10] == [H, H, (1, 0), (1, 1), (1, 2), (1, 3), (2, 2), (2, 3), (3, 2), (3, 3)]
    assert policy.seen[:4] == [0, 4, 6, 8]
    assert out.hold_steps == 2 and out.late_chunks == 0


def test_async_holds_when_the_chunk_runs_out_before_the_next_arrives():
    out, env, policy = episode("passes:100", "async")  # replan_every 0: ask when the chunk ends
    assert executed(env)[:12] == [H, H, (1, 0), (1, 1), (1, 2), (1, 3), H, H, (2, 2), (2, 3), H, H]
    assert policy.seen[:3] == [0, 6, 10]
    assert out.late_chunks >= 2 and out.hold_steps == executed(env).count(H)


def test_a_delay_longer_than_the_chunk_skips_it_whole_and_asks_again_at_once():
    out, env, _ = episode("passes:300", "async", replan_every=2)  # d = 6 > chunk of 4
    assert all(a == H for a in executed(env)[:6])
    assert set(executed(env)[6:]) <= {H, (1, 0), (1, 1), (1, 2), (1, 3)}  # later chunks all skipped
    assert out.delay_steps_max == 6


def test_varying_passes_give_each_chunk_its_own_delay():
    policy = PassingPolicy(passes=(1, 3))  # d = 1, 3, 1, 3 ...
    out, env, _ = episode("passes:100", "async", replan_every=2, policy=policy)
    assert executed(env)[:7] == [H, (1, 0), (1, 1), (1, 2), (1, 3), H, (2, 3)]
    assert out.delay_steps_max == 3 and 1 < out.delay_steps_mean < 3


@pytest.mark.parametrize("execution", ["sync", "async"])
@pytest.mark.parametrize("replan_every", [0, 1, 3])
def test_passes_zero_is_the_upstream_loop(execution, replan_every):
    a, env_a, pol_a = episode("none", execution, replan_every)
    b, env_b, pol_b = episode("passes:0", execution, replan_every)
    assert executed(env_a) == executed(env_b) and pol_a.seen == pol_b.seen
    fields = ("success", "steps", "chunks", "nfe_total", "action_tokens_total", "delay_steps_mean",
              "delay_steps_max", "late_chunks", "hold_steps", "failure_reason")  # fmt: skip
    assert [getattr(a, f) for f in fields] == [getattr(b, f) for f in fields]


class ChainEnv(CountdownEnv):
    """A two-instruction chain: the second instruction is in force from step `switch_at`."""

    def __init__(self, switch_at: int):
        super().__init__(None)
        self.switch_at = switch_at

    def _info(self) -> dict:
        k = int(self.t >= self.switch_at)
        return {"success": False, "instruction": ("first", "second")[k], "subtask_index": k}

    def reset(self, *, seed=None, options=None):
        obs, _ = super().reset(seed=seed, options=options)
        return obs, self._info()

    def step(self, action):
        obs, r, term, trunc, _ = super().step(action)
        return obs, r, term, trunc, self._info()


@pytest.mark.parametrize("execution", ["sync", "async"])
def test_an_instruction_switch_mid_delay_drops_the_chunk_in_flight_and_awaits_a_new_one(execution):
    # chunk 2 is requested at step 4 (async) and in flight when the switch lands after step 5
    _, env, policy = episode("passes:100", execution, replan_every=2, env=ChainEnv(5), policy=PassingPolicy())
    steps = executed(env)
    if execution == "async":
        assert steps[:9] == [H, H, (1, 0), (1, 1), (1, 2), H, H, (3, 0), (3, 1)]
        assert policy.seen[:3] == [0, 4, 5]
    else:  # sync: chunk 2 requested at step 4, the robot holding, when the switch comes
        assert steps[:9] == [H, H, (1, 0), (1, 1), H, H, H, (3, 0), (3, 1)]
        assert policy.seen[:3] == [0, 4, 5]
    assert policy.instructions == ["first", "second"]
    assert all(s[0] != 2 for s in steps if s != H)  # decoded for the old instruction: never run


TIMING = TIMING_COLUMNS | PROVENANCE_COLUMNS  # how fast, when and where: not what happened


def rows_of(report) -> pd.DataFrame:
    df = report.run_dir.read_episodes()
    keep = [c for c in df.columns if c not in TIMING]
    return df[keep].sort_values(["task", "episode_index"]).reset_index(drop=True)


@dataclasses.dataclass(frozen=True)
class LatencyBuild:
    """The fake run at a latency, rebuilt the same in each worker process."""

    mode: str = "none"
    execution: str = "sync"
    replan_every: int = 2

    def __call__(self):
        resolved = fake_resolved(PassingPolicy(passes=(1, 2, 3)), episodes=3, succeed_at=None, tasks=2)
        config = dataclasses.replace(
            resolved.config,
            inference_latency=self.mode,
            execution=self.execution,
            replan_every=self.replan_every,
        )
        suite = dataclasses.replace(resolved.suite, control_hz=HZ)
        return dataclasses.replace(resolved, config=config, suite=suite)


@pytest.mark.parametrize(
    ("given", "recorded", "ms", "fixed_ms"),
    [
        ("passes:1000000", "passes:1000000", 1e6, 0.0),
        ("passes:1e6", "passes:1000000", 1e6, 0.0),
        ("passes:4.1234567", "passes:4.1234567", 4.1234567, 0.0),
        ("passes:1e+3+5", "passes:1000+5", 1000.0, 5.0),
        ("passes:2.5+0.001", "passes:2.5+0.001", 2.5, 0.001),
        ("passes:1e20", "passes:1e20", 1e20, 0.0),
    ],
)
def test_a_latency_is_recorded_in_a_form_every_later_reading_takes_as_the_same(
    tmp_path, given, recorded, ms, fixed_ms
):
    """The config records the value's text, and the plan, each worker and --resume parse
    that text again: it must read back as the very numbers the user gave."""
    from harness.config import build_config

    config = build_config({"suite": "fake", "policy": [{"name": "random"}], "inference_latency": given})
    assert config.inference_latency == recorded
    again = parse_latency(config.inference_latency)
    assert (again.text, again.ms_per_pass, again.fixed_ms) == (recorded, ms, fixed_ms)
    rows = rows_of(run(LatencyBuild(config.inference_latency)(), tmp_path / "r"))
    assert set(rows["inference_latency"]) == {recorded}


def test_rows_record_the_mode_and_passes_zero_rows_equal_none_rows(tmp_path):
    none = rows_of(run(LatencyBuild("none", "async")(), tmp_path / "a"))
    zero = rows_of(run(LatencyBuild("passes:0", "async")(), tmp_path / "b"))
    assert set(none["inference_latency"]) == {"none"} and set(zero["inference_latency"]) == {"passes:0"}
    rest = [c for c in none.columns if c != "inference_latency"]
    pd.testing.assert_frame_equal(none[rest], zero[rest])
    assert (none["hold_steps"] == 0).all() and (none["delay_steps_max"] == 0).all()


@pytest.mark.parametrize("execution", ["sync", "async"])
def test_deterministic_modes_give_the_same_rows_on_two_thread_counts_and_two_workers(tmp_path, execution):
    build = LatencyBuild("passes:60+20", execution)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = rows_of(run(build(), tmp_path / "t1"))
        torch.set_num_threads(2)
        two = rows_of(run(build(), tmp_path / "t2"))
    finally:
        torch.set_num_threads(threads)
    workers = rows_of(run(build(), tmp_path / "w2", execution=Execution(workers=2, rebuild=build)))
    assert (one["hold_steps"] > 0).all() and one["delay_steps_max"].max() == 2  # 2 x 60 + 20 ms at 10 Hz
    pd.testing.assert_frame_equal(one, two)
    pd.testing.assert_frame_equal(one, workers)


def test_resume_refuses_another_latency(tmp_path):
    out = tmp_path / "r"
    run(LatencyBuild("passes:10")(), out)
    with pytest.raises(UsageError, match=r'inference_latency: "passes:10" -> "passes:20"'):
        run(LatencyBuild("passes:20")(), out, OpenMode.RESUME)
    with pytest.raises(UsageError, match=r'execution: "sync" -> "async"'):
        run(LatencyBuild("passes:10", "async")(), out, OpenMode.RESUME)


def test_the_gate_refuses_runs_at_different_latencies(tmp_path, cli):
    a = run(LatencyBuild("none")(), tmp_path / "a")
    b = run(LatencyBuild("passes:100", "async")(), tmp_path / "b")
    with pytest.raises(GateInputError, match="inference latency: baseline none; candidate passes:100 async"):
        gate(a.run_dir.read_episodes(), b.run_dir.read_episodes())
    code, _, err = cli("gate", "--baseline", str(tmp_path / "a"), "--candidate", str(tmp_path / "b"))
    assert code == 2 and "inference latency" in err
    # rows written before latency was recorded ran at none: they pair with none
    old = a.run_dir.read_episodes().drop(columns=["inference_latency", "execution"])
    gate(old, a.run_dir.read_episodes())


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--inference-latency", "fast"], "choose one of none, passes:MS[+FIXED_MS], profile:NAME, measured"),
        (["--inference-latency", "passes:-1"], "MS (milliseconds per forward pass) must be a number >= 0"),
        (["--inference-latency", "profile:nope"], "shipped profiles: ddvla-h800, fast-dvla-ddvla"),
        (["--inference-latency", "profile:ddvla-h800"], "no chunk latency for policy 'random'; it covers"),
        # batching is not refused at a latency; a policy that cannot batch still is
        (["--inference-latency", "passes:1", "--batch-envs", "2"], "policy random cannot batch"),
    ],
)
def test_bad_modes_and_profiles_exit_2_naming_the_valid_ones(cli, tmp_path, flags, message):
    out = tmp_path / "r"
    argv = ["run", "--suite", "metaworld/mt10", "--tasks", "0", "--episodes-per-task", "1"]
    code, _, err = cli(*argv, "--policy", "random", *flags, "--out", str(out))
    assert code == 2 and message in " ".join(err.split()), err
    assert not out.exists()


def test_execution_must_be_sync_or_async(cli):
    code, _, err = cli("run", "--execution", "later")
    assert code == 2 and "'sync', 'async'" in err


def test_list_latency_profiles_shows_each_with_its_source(cli):
    code, out, _ = cli("list", "latency-profiles")
    text = " ".join(out.split())
    assert (
        code == 0
        and "fast-dvla-ddvla" in text
        and "fast_dvla 139.1 ms" in text
        and "arXiv 2603.25661" in text
    )


def test_measured_turns_the_calls_wall_clock_into_steps():
    from tests.fakes import ChunkPolicy

    policy = ChunkPolicy(chunk=4, delay=0.15)  # at 10 Hz: at least 2 steps a call
    env = CountdownEnv(None)
    plan = LatencyPlan(parse_latency("measured"), "sync", HZ)
    out = run_one(env, policy, context(8), EpisodeSpec(0, 1), latency=plan)
    assert out.delay_steps_max >= 2 and out.hold_steps >= 2
    assert not env.actions[0].any()  # the first steps hold while the first chunk decodes


def test_the_manifest_records_the_mode_and_show_prints_the_latency_table_only_at_a_latency(tmp_path, cli):
    at = run(LatencyBuild("passes:100", "async")(), tmp_path / "at")
    assert at.run_dir.read_manifest()["config"]["inference_latency"] == "passes:100"
    assert at.run_dir.read_manifest()["config"]["execution"] == "async"
    code, out, _ = cli("show", str(tmp_path / "at"))
    assert code == 0 and "inference latency" in out and "passes:100 async" in out
    run(LatencyBuild("none")(), tmp_path / "none")
    code, out, _ = cli("show", str(tmp_path / "none"))
    assert code == 0 and "inference latency" not in out


def test_runs_at_two_latencies_read_together_keep_both_measurements(tmp_path):
    from results.runs import combined_episodes, load_runs

    run(LatencyBuild("none")(), tmp_path / "a")
    run(LatencyBuild("passes:100", "async")(), tmp_path / "b")
    run(LatencyBuild("passes:100", "sync")(), tmp_path / "c")
    df = combined_episodes(load_runs([tmp_path / "a", tmp_path / "b", tmp_path / "c"]))
    assert len(df) == 18 and df.attrs["duplicates"] == 0
    again = combined_episodes(load_runs([tmp_path / "b", tmp_path / "b"]))
    assert len(again) == 6  # the same folder twice still counts once


def test_plot_latency_draws_a_line_per_decoder_and_execution_and_refuses_runs_all_at_none(tmp_path, cli):
    from results.latency_plot import latency_frame
    from results.runs import combined_episodes, load_runs

    for name, build in (
        ("n", LatencyBuild("none")),
        ("s", LatencyBuild("passes:100")),
        ("a", LatencyBuild("passes:100", "async")),
    ):
        run(build(), tmp_path / name)
    frame = latency_frame(combined_episodes(load_runs([tmp_path / n for n in "nsa"])))
    lines = frame.groupby("decoder, execution")["latency"].apply(lambda s: sorted(set(s))).to_dict()
    assert lines == {"fake, async": ["none", "passes:100"], "fake, sync": ["none", "passes:100"]}
    code, out, _ = cli(
        "plot", "latency", *(str(tmp_path / n) for n in "nsa"), "--out", str(tmp_path / "l.png")
    )
    assert code == 0 and "wrote" in out and (tmp_path / "l.png").stat().st_size > 0
    code, _, err = cli("plot", "latency", str(tmp_path / "n"), "--out", str(tmp_path / "m.png"))
    assert code == 2 and "no run at an inference latency other than none" in err


def test_a_remote_policy_is_charged_the_servers_passes_per_call_like_the_local_one(
    cli,
    tmp_path,
    serve_process,  # noqa: F811
):
    url = serve_process("--policy", "fast_dvla", "--suite", "metaworld/mt10", "--task", "reach-v3")
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt10", "--tasks", "reach-v3", "--episodes-per-task", "2",
        "--policy", f"remote:url={url}", "--policy", "fast_dvla", "--replan-every", "4",
        "--inference-latency", "passes:4", "--execution", "async", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    rows = pd.read_parquet(out / "episodes.parquet").set_index(["policy", "episode_index"])
    remote, local = rows.loc["remote"], rows.loc["fast_dvla"]
    assert (local["delay_steps_max"] > 0).all()
    for column in ("success", "steps", "chunks", "nfe_total", "delay_steps_mean", "delay_steps_max",
                   "late_chunks", "hold_steps"):  # fmt: skip
        assert list(remote[column]) == list(local[column]), column
