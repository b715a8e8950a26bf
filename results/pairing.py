"""Pairing two runs for the gate: which configuration of the baseline answers to which
of the candidate, and whether a pair holds exactly the same episodes on both sides.

The rules (results/gate.py's docstring, docs/ci-gate.md): configurations pair by policy
name + params + checkpoint hash, then by name when that is unambiguous, then the only one
left on each side; episodes pair by PAIR_KEY. Anything that does not pair is refused with
GateInputError, listing what, before anything is judged.
"""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from dataclasses import dataclass
from typing import Any

import pandas as pd

PAIR_KEY = ("suite", "task", "episode_index", "seed", "init_state_id", "variant")
_SHOWN = 5  # mismatched episodes listed in a refusal


class GateInputError(ValueError):
    """The two runs cannot be compared (different episodes or configurations)."""


@dataclass(frozen=True)
class ConfigPair:
    baseline_id: str  # policy_config_id in the baseline
    candidate_id: str
    baseline: str  # policy name
    candidate: str
    changes: str  # params (or checkpoint) that differ, "key: old -> new; ..."
    rule: str  # why these two were paired
    tag: str = ""  # set when another pair would carry the same label (the baseline's config id)

    @property
    def short(self) -> str:
        return self.baseline if self.baseline == self.candidate else f"{self.baseline} -> {self.candidate}"

    @property
    def label(self) -> str:
        if self.baseline != self.candidate:
            label = f"{self.baseline} -> {self.candidate}"
        else:
            label = f"{self.baseline} ({self.changes})" if self.changes else self.baseline
        return f"{label} [{self.tag}]" if self.tag else label


def _identity(row: pd.Series) -> tuple[str, dict[str, Any], str]:
    params = json.loads(row["policy_params"] or "{}")
    if row["checkpoint_sha256"]:
        params.pop("checkpoint", None)  # the hash says which weights; the path is the clone's
    return row["policy"], params, row["checkpoint_sha256"] or ""


def _configs(df: pd.DataFrame) -> dict[str, tuple[str, dict[str, Any], str]]:
    ordered = df.sort_values("started_at", kind="stable") if "started_at" in df else df
    first = ordered.drop_duplicates("policy_config_id")  # in the order they ran
    return {r["policy_config_id"]: _identity(r) for _, r in first.iterrows()}


def _changes(base: tuple[str, dict[str, Any], str], cand: tuple[str, dict[str, Any], str]) -> str:
    """What differs between two configurations of the same policy, for the table."""
    if base[0] != cand[0]:
        return ""
    keys = sorted(set(base[1]) | set(cand[1]))
    old, new = base[1], cand[1]
    diff = [
        f"{k}: {old.get(k, '(absent)')} -> {new.get(k, '(absent)')}" for k in keys if old.get(k) != new.get(k)
    ]
    if base[2] != cand[2]:
        diff.append(f"checkpoint: {base[2][:8]} -> {cand[2][:8]}")
    return "; ".join(diff)


def pair_configs(baseline: pd.DataFrame, candidate: pd.DataFrame) -> list[ConfigPair]:
    """Pair configurations (rules in the module docstring); GateInputError if some stay single."""
    base, cand = _configs(baseline), _configs(candidate)
    pairs: list[tuple[str, str, str]] = []

    def take(rule: str, match: Any) -> None:
        for b in list(base):
            found = [c for c in cand if match(base[b], cand[c])]
            if len(found) == 1 and sum(match(base[x], cand[found[0]]) for x in base) == 1:
                pairs.append((b, found[0], rule))
                del base[b], cand[found[0]]

    take("same policy and params", lambda x, y: x == y)
    take("same policy, params differ", lambda x, y: x[0] == y[0])
    if len(base) == 1 and len(cand) == 1:
        pairs.append((next(iter(base)), next(iter(cand)), "the only configuration left on each side"))
        base, cand = {}, {}
    if base or cand:
        lines = [f"baseline {i[0]} {json.dumps(i[1])} ({b})" for b, i in base.items()]
        lines += [f"candidate {i[0]} {json.dumps(i[1])} ({c})" for c, i in cand.items()]
        raise GateInputError(
            "policy configurations without a partner: " + "; ".join(lines) + " (configurations pair by "
            "name and params, then by name alone, then the only one left on each side)"
        )
    full_b, full_c = _configs(baseline), _configs(candidate)
    order = list(full_b)  # the baseline's order, whichever rule paired them
    pairs.sort(key=lambda pair: order.index(pair[0]))
    out = [
        ConfigPair(b, c, full_b[b][0], full_c[c][0], _changes(full_b[b], full_c[c]), rule)
        for b, c, rule in pairs
    ]
    # Labels key the report's rows: two configurations of one policy (a sweep) must not
    # share one, or one pair's verdict would be printed under the other's name.
    counts = Counter(p.label for p in out)
    return [dataclasses.replace(p, tag=p.baseline_id) if counts[p.label] > 1 else p for p in out]


def episode_keys(df: pd.DataFrame) -> pd.DataFrame:
    """Episode keys normalised: nullable ints come back from Parquet as floats with NaN."""
    out = df.copy()
    for col in ("episode_index", "seed", "init_state_id"):
        out[col] = [None if pd.isna(v) else int(v) for v in out[col]]
        out[col] = out[col].astype(object)
    return out


def _describe(keys: pd.DataFrame) -> str:
    shown = [
        f"{r.task} #{r.episode_index} (seed {r.seed}, init {r.init_state_id})"
        for r in keys.head(_SHOWN).itertuples()
    ]
    more = f" and {len(keys) - _SHOWN} more" if len(keys) > _SHOWN else ""
    return ", ".join(shown) + more


def latency_labels(df: pd.DataFrame) -> list[str]:
    """The inference latencies a table ran at, with the execution where it matters:
    `none` for rows written before latency was recorded (docs/latency.md)."""
    if "inference_latency" not in df:
        return ["none"] if len(df) else []
    mode = df["inference_latency"].fillna("none")
    execution = df["execution"].fillna("sync") if "execution" in df else pd.Series("sync", index=df.index)
    labels = mode.where(mode == "none", mode + " " + execution)
    return sorted(set(labels))


def check_episodes_match(baseline: pd.DataFrame, candidate: pd.DataFrame, pair: ConfigPair) -> None:
    """Refuse (listing why) unless both sides of `pair` hold exactly the same episodes."""
    b = baseline[baseline["policy_config_id"] == pair.baseline_id]
    c = candidate[candidate["policy_config_id"] == pair.candidate_id]
    problems = []
    for col in ("suite", "suite_version"):
        bs, cs = sorted(b[col].unique()), sorted(c[col].unique())
        if bs != cs:
            problems.append(f"{col}: baseline {', '.join(bs)}; candidate {', '.join(cs)}")
    bl, cl = latency_labels(b), latency_labels(c)
    if bl != cl:  # success at one latency says nothing about success at another
        problems.append(f"inference latency: baseline {', '.join(bl)}; candidate {', '.join(cl)}")
    if not problems:
        bk, ck = episode_keys(b)[list(PAIR_KEY)], episode_keys(c)[list(PAIR_KEY)]
        for side, keys in (("baseline", bk), ("candidate", ck)):
            # A table (not a run folder, which keeps the latest write) may repeat an episode;
            # paired counts would then multiply it.
            repeated = keys[keys.duplicated()]
            if len(repeated):
                problems.append(f"the {side} holds some episodes twice: {_describe(repeated)}")
        both = bk.merge(ck, how="outer", indicator=True)
        only_b, only_c = both[both["_merge"] == "left_only"], both[both["_merge"] == "right_only"]
        if len(only_b) == len(bk) and len(only_c) == len(ck):
            problems.append("no common episodes")
        if len(bk) != len(ck):
            problems.append(f"{len(bk)} episodes in the baseline, {len(ck)} in the candidate")
        if len(only_b):
            problems.append(f"only in the baseline: {_describe(only_b)}")
        if len(only_c):
            problems.append(f"only in the candidate: {_describe(only_c)}")
    if problems:
        raise GateInputError(f"episodes of {pair.label} do not match: " + "; ".join(problems))
