"""Counted work (harness/episode/work.py): the NFE hooks' FLOP and token counts equal a hand count
on a toy model for every decoder's pass shapes, do not depend on threads or the batch,
say "not measured" rather than 0, travel over the wire, and fail the gate when they grow."""

from __future__ import annotations

import threading

import pandas as pd
import pytest
import torch

from harness.episode.nfe import NFECounter
from harness.episode.work import NOT_MEASURED, Work
from policies.dvla.decoders import decode_autoregressive, decode_bidirectional, decode_block_diffusion
from policies.dvla.fast_dllm import decode_fast_dllm
from policies.dvla.fast_dvla import decode_fast_dvla
from policies.dvla.model import ActionTokenModel, ModelConfig
from results.gate import gate
from tests.test_gate import ALL_OK, episodes, write_run

B = 2  # batch rows in every decode below


def toy(pattern: str) -> ActionTokenModel:
    """One attention layer and one MLP (plus the state MLP, embeddings and head)."""
    torch.manual_seed(0)
    cfg = ModelConfig(
        action_dim=2, chunk_len=4, state_dim=3, bins=16, vocab_words=20, max_words=4,
        state_tokens=2, width=16, layers=1, heads=2, ffn=24, pattern=pattern,
    )  # fmt: skip
    return ActionTokenModel(cfg).eval()


def inputs(batch: int = B) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    return torch.randint(1, 20, (batch, 4), generator=g), torch.randn(batch, 3, generator=g)


def hand(cfg: ModelConfig, actions: int, prefix: bool, cached: int, batch: int = B) -> Work:
    """One pass by hand: `actions` action positions run (with the prefix's P positions
    when `prefix`) against `cached` cached positions. FLOPs = 2 per multiply-accumulate."""
    w, f = cfg.width, cfg.ffn
    n = actions + (cfg.prefix_len if prefix else 0)  # positions computed
    s = cached + n  # positions attended
    flops = 0
    if prefix:  # state MLP: Linear(state_dim, w), Linear(w, state_tokens * w), one row each
        flops += 2 * batch * (cfg.state_dim * w + w * cfg.state_tokens * w)
    flops += 2 * batch * n * (w * 3 * w + w * w + w * f + f * w)  # qkv, proj, MLP
    flops += 2 * batch * n * s * 2 * w  # scores and weighted sum, all heads (heads * head_dim = w)
    flops += 2 * batch * actions * w * cfg.bins  # head, on the action positions
    return Work(flops, batch * n, batch * s, batch * cached)


def total(passes: list[Work]) -> Work:
    return sum(passes, Work())


def counted(fn, model, **kw) -> tuple[Work, int, object]:
    counter = NFECounter()
    with torch.inference_mode(), counter.counting():
        out = fn(model, *inputs(), **kw)
    work, nfe = counter.take_work(), counter.take()
    counter.close()
    return work, nfe, out


def test_bidirectional_is_t_full_passes_and_with_a_prefix_cache_reads_the_prefix():
    model = toy("bidirectional")
    cfg, a, p = model.cfg, model.cfg.action_tokens, model.cfg.prefix_len
    work, nfe, _ = counted(decode_bidirectional, model, steps=3)
    assert nfe == 3 and work == total([hand(cfg, a, True, 0)] * 3)
    work, nfe, _ = counted(decode_bidirectional, model, steps=3, reuse_prefix_cache=True)
    assert work == hand(cfg, a, True, 0) + total([hand(cfg, a, False, p)] * 2)
    assert work.kv_cached_tokens == 2 * B * p  # the two later passes read the prefix


def test_autoregressive_is_one_position_a_pass_against_a_growing_cache():
    model = toy("causal")
    cfg, a, p = model.cfg, model.cfg.action_tokens, model.cfg.prefix_len
    work, nfe, _ = counted(decode_autoregressive, model)
    assert nfe == a
    assert work == hand(cfg, 1, True, 0) + total([hand(cfg, 1, False, p + i) for i in range(1, a)])


def test_block_diffusion_reruns_the_finished_block_with_the_next_ones_first_pass():
    model = toy("block_causal")
    cfg, a, p, k, steps = model.cfg, model.cfg.action_tokens, model.cfg.prefix_len, model.cfg.block, 3
    work, nfe, _ = counted(decode_block_diffusion, model, steps_per_block=steps)
    passes = [hand(cfg, k, True, 0)] + [hand(cfg, k, False, p)] * (steps - 1)
    for j in range(1, a // k):
        passes += [hand(cfg, 2 * k, False, p + (j - 1) * k)]
        passes += [hand(cfg, k, False, p + j * k)] * (steps - 1)
    assert nfe == len(passes) and work == total(passes)


@pytest.mark.parametrize("cache", ["dual", "prefix", "none"])
def test_fast_dllm_per_block_one_full_pass_then_cached_ones(cache):
    model = toy("bidirectional")
    cfg, a, p, k, steps = model.cfg, model.cfg.action_tokens, model.cfg.prefix_len, 4, 2
    work, nfe, _ = counted(
        decode_fast_dllm, model, block_size=k, threshold=0.0, cache=cache, steps_per_block=steps
    )
    passes = []
    for start in range(0, a, k):
        passes.append(hand(cfg, a, True, 0))
        later = {
            "dual": hand(cfg, k, False, p + a - k),
            "prefix": hand(cfg, a - start, False, p + start),
            "none": hand(cfg, a, True, 0),
        }[cache]
        passes += [later] * (steps - 1)
    assert nfe == len(passes) and work == total(passes)


def test_fast_dvla_passes_by_hand_from_the_shapes_it_ran():
    """fast_dvla is adaptive: which passes it runs depends on its confidences, so the hand
    count takes each pass's shape (positions run, prefix or not, cached length) from its
    trace, and the hooks' count must agree pass for pass."""
    model = toy("block_causal")
    work, nfe, out = counted(decode_fast_dvla, model)
    passes = [hand(model.cfg, len(x.query), x.prefix, x.cached) for x in out.passes]
    assert nfe == len(passes) > 1 and work == total(passes)
    assert work.kv_cached_tokens > 0  # it decodes against its cache


@pytest.mark.parametrize(
    ("fn", "pattern"),
    [(decode_bidirectional, "bidirectional"), (decode_fast_dvla, "block_causal")],
)
def test_work_is_identical_at_one_and_two_threads_and_with_other_threads_alive(fn, pattern):
    model = toy(pattern)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = counted(fn, model)[0]
        torch.set_num_threads(2)
        two = counted(fn, model)[0]
    finally:
        torch.set_num_threads(before)
    stop = threading.Event()
    alive = threading.Thread(target=stop.wait)  # a second Python thread: the hooks stay on
    alive.start()
    try:
        threaded = counted(fn, model)[0]
    finally:
        stop.set()
        alive.join()
    assert one == two == threaded and one.flops > 0


def test_a_batch_of_k_is_k_times_one_row_and_splits_back_to_the_rows_work():
    model = toy("bidirectional")
    counter = NFECounter()
    works = {}
    for batch in (1, 3):
        with torch.inference_mode(), counter.counting():
            decode_bidirectional(model, *inputs(batch), steps=2)
        works[batch] = counter.take_work()
    assert works[3] == Work(*(3 * v for v in works[1].to_wire().values()))
    assert works[3].split(3) == [works[1]] * 3  # each episode of the call: its row's work
    assert Work(7, 5, None, 0).split(2) == [Work(4, 3, None, 0), Work(3, 2, None, 0)]


class Custom(torch.nn.Module):
    """A layer whose products the hooks cannot see (F.linear on its own parameter)."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.ones(4, 4))

    def forward(self, x):
        return torch.nn.functional.linear(x, self.weight)


def test_unseen_products_leave_flops_not_measured_and_no_attention_leaves_tokens_unmeasured():
    counter = NFECounter()
    mlp = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.ReLU(), torch.nn.Linear(8, 4))
    with torch.inference_mode(), counter.counting():
        mlp(torch.zeros(3, 4))
    assert counter.take_work() == Work(2 * 3 * (4 * 8 + 8 * 4), None, None, None)
    hidden = torch.nn.Sequential(torch.nn.Linear(4, 4), Custom())
    with torch.inference_mode(), counter.counting():
        hidden(torch.zeros(1, 4))
    assert counter.take_work().flops is None  # not an under-count presented as a count
    with counter.counting():
        pass  # a policy call without passes (a scripted expert): nothing, and 0 is true
    assert counter.take_work() == Work()
    counter.close()


def test_a_conv_counts_its_output_times_its_kernel():
    counter = NFECounter()
    conv = torch.nn.Conv2d(3, 8, 5, stride=2, padding=2)
    with torch.inference_mode(), counter.counting():
        conv(torch.zeros(2, 3, 16, 16))
    assert counter.take_work().flops == 2 * (2 * 8 * 8 * 8) * (3 * 5 * 5)
    counter.close()


@pytest.mark.parametrize("batch_first", [False, True])
def test_multihead_attention_counts_what_torchs_flop_counter_counts(batch_first):
    """LeRobot's ACT attends through nn.MultiheadAttention, cross-attention included (keys
    of another length and width): its projections and attention, as torch.utils.flop_counter
    counts the same products (in training mode with the weights returned, where torch
    multiplies through bmm, which it counts, rather than a fused CPU kernel, which it does not)."""
    from torch.utils.flop_counter import FlopCounterMode

    torch.manual_seed(0)
    mha = torch.nn.MultiheadAttention(16, 4, kdim=12, vdim=10, batch_first=batch_first)
    sizes = [(2, 5, 16), (2, 7, 12), (2, 7, 10)] if batch_first else [(5, 2, 16), (7, 2, 12), (7, 2, 10)]
    q, k, v = (torch.randn(*s) for s in sizes)
    with FlopCounterMode(display=False) as reference:
        mha.train()(q, k, v, need_weights=True)  # the explicit bmm path, which it counts
    counter = NFECounter()
    with torch.inference_mode(), counter.counting():
        mha.eval()(q, k, value=v)  # ACT passes the value by keyword
    assert counter.take() == 1
    assert counter.take_work().flops == reference.get_total_flops() > 0
    counter.close()


@pytest.mark.parametrize("threaded", [False, True])
def test_multihead_attention_called_by_keyword_is_counted_alone_and_beside_threads(threaded):
    """ACT's decoder calls its cross-attention as `multihead_attn(query=, key=, value=)`:
    counted in a single-thread pass (the wrapped forward sees keywords) and beside another
    thread, as in a server (the process-wide post-hook sees them; its pre-hook does not),
    to torch's flop count of the same call."""
    from torch.utils.flop_counter import FlopCounterMode

    torch.manual_seed(0)
    layer = torch.nn.Sequential(torch.nn.Linear(16, 16))  # a pass holding the attention
    mha = torch.nn.MultiheadAttention(16, 4, kdim=12, vdim=10)
    q, k, v = torch.randn(5, 2, 16), torch.randn(7, 2, 12), torch.randn(7, 2, 10)

    class Decoder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.layer, self.attention = layer, mha

        def forward(self, x):
            return self.attention(query=self.layer(x), key=k, value=v, need_weights=True)[0]

    decoder = Decoder().train()  # torch's explicit bmm path, which its flop counter counts
    with FlopCounterMode(display=False) as reference:
        decoder(q)
    stop = threading.Event()
    alive = threading.Thread(target=stop.wait)
    if threaded:
        alive.start()
    counter = NFECounter()
    try:
        with counter.counting():
            decoder(q)
    finally:
        stop.set()
        if threaded:
            alive.join()
    assert counter.take() == 1
    assert counter.take_work().flops == reference.get_total_flops() > 0
    counter.close()


# ---- remote ------------------------------------------------------------------------


class FakeSocket:
    def __init__(self, replies):
        self.replies = list(replies)

    def send(self, data):
        pass

    def recv(self, timeout=None):
        from policies.wire import pack

        return pack(self.replies.pop(0))


def test_a_servers_reported_work_adds_up_and_a_reply_without_it_is_not_measured():
    pytest.importorskip("msgpack")
    from policies.remote import RemoteParams, RemotePolicy

    policy = RemotePolicy(RemoteParams())
    reported = Work(100, 10, 30, 20)
    policy._ws = FakeSocket([{"dvla/nfe": 2, "dvla/work": reported.to_wire()}] * 2)
    policy._call({})
    policy._call({})
    assert policy.take_served().work == Work(200, 20, 60, 40)
    policy._ws = FakeSocket([{"dvla/nfe": 2, "dvla/work": reported.to_wire()}, {"actions": 0}])
    policy._call({})
    policy._call({})  # an openpi server: no work reported
    assert policy.take_served().work == NOT_MEASURED
    assert Work.from_wire(
        {"flops": -1, "query_tokens": "x", "kv_tokens": 3, "kv_cached_tokens": True}
    ) == Work(None, None, 3, None)


# ---- gate --------------------------------------------------------------------------


def table(flops_per_chunk: float | None) -> pd.DataFrame:
    """test_gate's run table (4 chunks an episode) with the counted work filled in."""
    df = episodes(ALL_OK)
    return df.assign(flops_total=None if flops_per_chunk is None else int(flops_per_chunk) * df["chunks"])


def test_the_gate_fails_an_increase_of_counted_work_unless_allowed_and_names_the_change():
    base, more = table(1e8), table(1.2e8)
    result = gate(base, more, reference=None)
    assert not result.passed
    assert any(
        "fast_dvla / ALL: counted work 0.1 -> 0.12 GFLOP/chunk (+20.00%)" in f for f in result.failures
    )
    allowed = gate(base, more, reference=None, allow_work_increase=True)
    assert allowed.passed and any("--allow-work-increase" in n for n in allowed.notes)
    assert gate(more, base, reference=None).passed  # less work is never a regression
    assert gate(base, table(1e8), reference=None).passed


def test_the_gate_does_not_compare_work_that_either_side_did_not_measure():
    result = gate(table(None), table(1.2e8), reference=None)
    assert result.passed
    assert any("counted work not compared (not measured in the baseline)" in n for n in result.notes)
    bare = table(1.2e8).drop(columns=["flops_total"])  # a table from before counted work
    result = gate(table(1e8), bare, reference=None)
    assert result.passed and any("not measured in the candidate" in n for n in result.notes)


def test_the_gate_cli_prints_the_work_column_and_takes_the_flag(cli, tmp_path):
    base = write_run(tmp_path / "base", table(1e8))
    cand = write_run(tmp_path / "cand", table(1.3e8))
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 1 and "GFLOP/chunk" in out and "0.100 -> 0.130 (up)" in out and "FAIL work" in out
    assert "counted work 0.1 -> 0.13 GFLOP/chunk (+30.00%)" in err
    code, out, _ = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--allow-work-increase")
    assert code == 0 and "(up)" in out


def test_leaderboard_and_show_print_gflop_per_chunk_and_not_measured_for_old_rows(cli, tmp_path):
    measured = write_run(tmp_path / "new", table(2.5e8).assign(flops_per_chunk=2.5e8))
    old = write_run(tmp_path / "old", table(None))
    code, text, _ = cli("leaderboard", str(measured), "--format", "md")
    assert code == 0 and "GFLOP/chunk" in text and "| 0.250 |" in text
    code, text, _ = cli("leaderboard", str(old), "--format", "md")
    assert code == 0 and "not measured" in text
    code, text, _ = cli("show", str(measured))
    assert code == 0 and "GFLOP/chunk" in text and "0.250" in text


def test_prepacked_linears_count_as_the_linears_they_replace():
    from policies.dvla.kernels import pack_linears

    model = toy("block_causal")
    plain = counted(decode_fast_dvla, model)[0]
    if pack_linears(model, min_elements=0) == 0:
        pytest.skip("oneDNN prepacking is unavailable here")
    packed = counted(decode_fast_dvla, model)[0]
    assert packed == plain
