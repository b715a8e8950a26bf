"""The commit and activation rules of Fast-dVLA and Fast-dLLM, driven by scripted
confidences (a trained model's confidences are not needed to reach every branch)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.dvla.decoding import commit_confident, score
from policies.dvla.fast_dvla import FULL, INACTIVE, SEMI, advance, commit_full, commit_semi

ALL = np.ones(7, dtype=bool)


def test_semi_activated_blocks_commit_only_what_clears_tau_conf():
    conf = np.array([0.2, 0.6, 0.5, 0.49, 0.9, 0.1, 0.3])
    assert commit_semi(ALL, conf, 0.5).tolist() == [False, True, True, False, True, False, False]
    assert not commit_semi(ALL, np.full(7, 0.1), 0.5).any()  # a semi block may commit nothing
    masked = ALL.copy()
    masked[4] = False  # already committed: never again
    assert not commit_semi(masked, conf, 0.5)[4]


def test_fully_activated_blocks_commit_at_least_a_fraction_one_over_n():
    conf = np.array([0.1, 0.2, 0.3, 0.15, 0.25, 0.05, 0.12])
    # R = 7, n = 2: k = 3, so the 3 best (0.3, 0.25, 0.2) although none clears tau_conf
    assert commit_full(ALL, conf, 0.5, 2).sum() == 3
    assert set(np.nonzero(commit_full(ALL, conf, 0.5, 2))[0]) == {1, 2, 4}
    assert commit_full(ALL, conf, 0.5, 3).sum() == 2  # k = floor(7 / 3)
    # and everything that clears tau_conf, however many that is
    high = np.array([0.9, 0.8, 0.7, 0.6, 0.55, 0.1, 0.2])
    assert commit_full(ALL, high, 0.5, 2).tolist() == [True] * 5 + [False] * 2


def test_one_masked_token_left_is_forced():
    masked = np.zeros(7, dtype=bool)
    masked[3] = True  # R = 1: k = 0, and its confidence is under tau_conf
    assert np.nonzero(commit_full(masked, np.full(7, 0.01), 0.5, 2))[0].tolist() == [3]
    assert not commit_full(np.zeros(7, dtype=bool), np.full(7, 0.9), 0.5, 2).any()


def test_blocks_are_added_then_fully_activated_by_their_predecessors_progress():
    k = 7
    status = np.array([FULL, INACTIVE, INACTIVE, INACTIVE], dtype=np.int8)
    done = np.array([2, 0, 0, 0])  # 2/7 = tau_add exactly: not above it
    advance(status, done, k, 2 / 7, 4 / 7)
    assert status.tolist() == [FULL, INACTIVE, INACTIVE, INACTIVE]
    done[0] = 3
    advance(status, done, k, 2 / 7, 4 / 7)
    assert status.tolist() == [FULL, SEMI, INACTIVE, INACTIVE]
    done[0], done[1] = 5, 3  # 5/7 > tau_act: block 1 full; block 1's 3/7 adds block 2
    advance(status, done, k, 2 / 7, 4 / 7)
    assert status.tolist() == [FULL, FULL, SEMI, INACTIVE]
    done[2] = 7  # a complete block activates its successor fully, whatever the taus
    advance(status, done, k, 1.0, 1.0)
    assert status.tolist() == [FULL, FULL, SEMI, FULL]


def test_tau_one_means_block_by_block():
    status = np.array([FULL, INACTIVE, INACTIVE], dtype=np.int8)
    done = np.array([6, 0, 0])
    advance(status, done, 7, 1.0, 1.0)
    assert status.tolist() == [FULL, INACTIVE, INACTIVE]
    done[0] = 7
    advance(status, done, 7, 1.0, 1.0)
    assert status.tolist() == [FULL, FULL, INACTIVE]


def test_fast_dllm_commits_everything_over_the_threshold_and_at_least_one():
    masked = torch.tensor([[True, True, True, False], [True, True, False, False], [False] * 4])
    conf = torch.tensor([[0.95, 0.91, 0.2, 0.99], [0.3, 0.5, 0.99, 0.99], [0.99] * 4])
    commit = commit_confident(masked, conf, 0.9)
    assert commit.tolist() == [
        [True, True, False, False],  # both over 0.9; the committed 0.99 is not masked
        [False, True, False, False],  # none over 0.9: the most confident masked one
        [False] * 4,  # nothing masked: nothing
    ]


@pytest.mark.parametrize("confidence", ["max_prob", "margin", "entropy", "random"])
def test_confidence_measures_rank_a_peaked_position_first(confidence):
    logits = torch.tensor([[[5.0, 0.0, 0.0], [1.0, 0.9, 0.8]]])
    choice, conf = score(logits, confidence, generator=torch.Generator().manual_seed(1))
    assert choice.tolist() == [[0, 0]]
    if confidence != "random":
        assert conf[0, 0] > conf[0, 1]
    again = score(logits, confidence, generator=torch.Generator().manual_seed(1))[1]
    assert torch.equal(conf, again)  # seeded: the same draws


def test_temperature_samples_with_the_seed_and_greedy_ignores_it():
    logits = torch.zeros(1, 64, 8)
    a = score(logits, "max_prob", 1.0, torch.Generator().manual_seed(1))[0]
    b = score(logits, "max_prob", 1.0, torch.Generator().manual_seed(1))[0]
    c = score(logits, "max_prob", 1.0, torch.Generator().manual_seed(2))[0]
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert len(set(a.flatten().tolist())) > 1  # sampled, not arg-max
    assert (score(logits, "max_prob", 0.0)[0] == 0).all()
