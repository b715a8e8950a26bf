"""The CI regression gate: does a candidate run hold up against a baseline run?

Pure functions on episode tables (and manifests, for the timing reference), so a
notebook can call `gate(base_df, cand_df)` and get the same verdict as the CLI.
docs/ci-gate.md explains the rules; in short:

* Configurations are paired by policy name + params + checkpoint hash (a checkpoint is
  its content, not its path, so runs from two clones still pair); then, among the
  unpaired, by policy name when that is unambiguous; then, if exactly one is left on
  each side, those two. Anything still unpaired is refused.
* Episodes are paired by (suite, task, episode_index, seed, init_state_id), and a
  configuration pair must hold exactly the same episodes on both sides, else refused.
* Success: McNemar's exact test, one-sided. Paired episodes whose outcome is the same
  carry no evidence; of the n discordant pairs, under "no change" the drops are
  Binomial(n, 1/2), so p = P(X >= drops). Exact because CI evaluations are small, where
  the chi-square approximation is poor. Gated overall at alpha and per task at
  alpha / tasks (Bonferroni), so one collapsed task is caught without every task
  being another chance of a false alarm.
* NFE per chunk (total passes / total chunks) is deterministic for deterministic
  decoders: any increase fails.
* tokens/s is compared only as a ratio to each run's own calibration speed.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from results.runs import Run

PAIR_KEY = ("suite", "task", "episode_index", "seed", "init_state_id")
_SHOWN = 5  # mismatched episodes listed in a refusal


class GateInputError(ValueError):
    """The two runs cannot be compared (different episodes or configurations)."""


def mcnemar_drop_p(drops: int, gains: int) -> float:
    """One-sided exact McNemar p-value that `drops` this large arose by chance."""
    n = drops + gains
    if drops <= 0:
        return 1.0
    return sum(math.comb(n, k) for k in range(drops, n + 1)) / 2**n


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


@dataclass(frozen=True)
class TaskDiff:
    """One configuration pair on one task (or `ALL`)."""

    pair: str
    task: str
    episodes: int
    baseline_successes: int
    candidate_successes: int
    drops: int  # baseline succeeded, candidate failed
    gains: int
    p_value: float
    alpha: float  # the level this row is tested at
    baseline_nfe: float | None  # passes per chunk
    candidate_nfe: float | None
    nfe_gated: bool = True

    @property
    def success_regressed(self) -> bool:
        return self.p_value <= self.alpha

    @property
    def nfe_increased(self) -> bool:
        if self.baseline_nfe is None or self.candidate_nfe is None:
            return False
        return self.candidate_nfe > self.baseline_nfe * (1 + 1e-9) + 1e-12


@dataclass(frozen=True)
class SpeedDiff:
    """tokens/s over the calibration speed (tokens per reference pass), per pair."""

    pair: str
    baseline_tokens_per_s: float
    candidate_tokens_per_s: float
    baseline_reference: float
    candidate_reference: float
    max_slowdown: float

    @property
    def change(self) -> float:
        base = self.baseline_tokens_per_s / self.baseline_reference
        cand = self.candidate_tokens_per_s / self.candidate_reference
        return cand / base - 1.0

    @property
    def regressed(self) -> bool:
        return self.change < -self.max_slowdown


@dataclass(frozen=True)
class GateResult:
    pairs: tuple[ConfigPair, ...]
    tasks: tuple[TaskDiff, ...]
    speed: tuple[SpeedDiff, ...]
    notes: tuple[str, ...] = field(default=())  # skipped comparisons and why
    # Pairs whose candidate raised in more episodes than the baseline did.
    raised: tuple[str, ...] = field(default=())

    @property
    def failures(self) -> list[str]:
        out = list(self.raised)
        for t in self.tasks:
            if t.success_regressed:
                out.append(
                    f"{t.pair} / {t.task}: success {t.baseline_successes} -> {t.candidate_successes} "
                    f"of {t.episodes} ({t.drops} drops, {t.gains} gains, p = {t.p_value:.3g} <= {t.alpha:.3g})"
                )
            if t.nfe_increased and t.nfe_gated:
                out.append(f"{t.pair} / {t.task}: NFE/chunk {t.baseline_nfe:.3f} -> {t.candidate_nfe:.3f}")
        for s in self.speed:
            if s.regressed:
                out.append(
                    f"{s.pair}: tokens/s per calibration speed {s.change:+.1%} "
                    f"(allowed -{s.max_slowdown:.0%})"
                )
        return out

    @property
    def passed(self) -> bool:
        return not self.failures


# ---- pairing ---------------------------------------------------------------------


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


def _keys(df: pd.DataFrame) -> pd.DataFrame:
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


def check_episodes_match(baseline: pd.DataFrame, candidate: pd.DataFrame, pair: ConfigPair) -> None:
    """Refuse (listing why) unless both sides of `pair` hold exactly the same episodes."""
    b = baseline[baseline["policy_config_id"] == pair.baseline_id]
    c = candidate[candidate["policy_config_id"] == pair.candidate_id]
    problems = []
    for col in ("suite", "suite_version"):
        bs, cs = sorted(b[col].unique()), sorted(c[col].unique())
        if bs != cs:
            problems.append(f"{col}: baseline {', '.join(bs)}; candidate {', '.join(cs)}")
    if not problems:
        bk, ck = _keys(b)[list(PAIR_KEY)], _keys(c)[list(PAIR_KEY)]
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


# ---- comparing -------------------------------------------------------------------


_MEASURES = ("success", "nfe_total", "chunks", "action_tokens_total", "policy_time_s", "task_index")


def _side(merged: pd.DataFrame, side: str) -> pd.DataFrame:
    """One run's measures from a merged pair table (`side` is "b" or "c")."""
    return merged[[f"{m}_{side}" for m in _MEASURES]].set_axis(list(_MEASURES), axis=1)


def _nfe(df: pd.DataFrame) -> float | None:
    chunks = int(df["chunks"].sum())
    return float(df["nfe_total"].sum()) / chunks if chunks else None


def _tokens_per_s(df: pd.DataFrame) -> float | None:
    decoded = df[df["action_tokens_total"] > 0]
    time_s = float(decoded["policy_time_s"].sum())
    return float(decoded["action_tokens_total"].sum()) / time_s if len(decoded) and time_s > 0 else None


def _task_diff(pair: str, task: str, merged: pd.DataFrame, alpha: float, gate_nfe: bool) -> TaskDiff:
    b, c = _side(merged, "b"), _side(merged, "c")
    base, cand = b["success"].astype(bool), c["success"].astype(bool)
    drops, gains = int((base & ~cand).sum()), int((~base & cand).sum())
    return TaskDiff(
        pair=pair,
        task=task,
        episodes=len(merged),
        baseline_successes=int(base.sum()),
        candidate_successes=int(cand.sum()),
        drops=drops,
        gains=gains,
        p_value=mcnemar_drop_p(drops, gains),
        alpha=alpha,
        baseline_nfe=_nfe(b),
        candidate_nfe=_nfe(c),
        nfe_gated=gate_nfe,
    )


def gate(
    baseline: pd.DataFrame,
    candidate: pd.DataFrame,
    *,
    alpha: float = 0.05,
    max_slowdown: float = 0.10,
    allow_nfe_increase: bool = False,
    baseline_reference: float | None = None,
    candidate_reference: float | None = None,
    speed_skipped: str = "",
) -> GateResult:
    """Compare two episode tables; references are calibration speeds (passes/s), if any.

    Raises GateInputError when the runs cannot be compared (nothing is judged then).
    """
    pairs = pair_configs(baseline, candidate)
    for pair in pairs:
        check_episodes_match(baseline, candidate, pair)
    timed = not speed_skipped and baseline_reference is not None and candidate_reference is not None
    if not timed:
        speed_skipped = speed_skipped or "time comparison skipped (no calibration speed for both runs)"
    notes = [speed_skipped] if speed_skipped else []
    tasks: list[TaskDiff] = []
    speed: list[SpeedDiff] = []
    errors: list[str] = []
    for pair in pairs:
        b = _keys(baseline[baseline["policy_config_id"] == pair.baseline_id])
        c = _keys(candidate[candidate["policy_config_id"] == pair.candidate_id])
        cols = [*PAIR_KEY, *_MEASURES]
        merged = b[cols].merge(c[cols], on=list(PAIR_KEY), suffixes=("_b", "_c"))
        order = list(dict.fromkeys(merged.sort_values("task_index_b", kind="stable")["task"]))
        for task in order:
            rows = merged[merged["task"] == task]
            tasks.append(_task_diff(pair.label, task, rows, alpha / len(order), not allow_nfe_increase))
        tasks.append(_task_diff(pair.label, "ALL", merged, alpha, not allow_nfe_increase))
        raised = {
            side: int(rows["failure_reason"].notna().sum())
            for side, rows in (("baseline", b), ("candidate", c))
        }
        for side, count in raised.items():
            if count:
                notes.append(f"{pair.label}: {count} {side} episode(s) raised; counted as failures")
        if raised["candidate"] > raised["baseline"]:
            # Episodes that raise decode nothing, so NFE and speed cannot catch them, and a
            # baseline with few successes leaves McNemar's test no room to: fail outright.
            errors.append(
                f"{pair.label}: {raised['candidate']} candidate episode(s) raised, "
                f"{raised['baseline']} in the baseline (failure_reason in the rows)"
            )
        if not timed:
            continue
        base_tps, cand_tps = _tokens_per_s(_side(merged, "b")), _tokens_per_s(_side(merged, "c"))
        if base_tps is None or cand_tps is None:
            notes.append(f"{pair.label}: tokens/s not compared (no action tokens decoded on both sides)")
            continue
        assert baseline_reference is not None and candidate_reference is not None
        speed.append(
            SpeedDiff(pair.label, base_tps, cand_tps, baseline_reference, candidate_reference, max_slowdown)
        )
    if allow_nfe_increase:
        notes.append("NFE increases reported but allowed (--allow-nfe-increase)")
    return GateResult(tuple(pairs), tuple(tasks), tuple(speed), tuple(notes), tuple(errors))


# ---- timing reference from manifests ---------------------------------------------


def reference_speed(manifest: dict[str, Any]) -> tuple[float | None, str]:
    """(calibration passes/s, '') or (None, why not); the mean of start and end when both exist."""
    cal = manifest.get("calibration") if manifest else None
    if not manifest:
        return None, "no manifest.json beside it"
    if not cal:
        return None, "its manifest has no calibration (made before calibration was recorded)"
    if "workload" not in cal:
        return None, f"it was not calibrated ({cal.get('skipped', 'no reason recorded')})"
    speeds = [m["passes_per_s"] for m in (cal.get("start"), cal.get("end")) if m]
    return sum(speeds) / len(speeds), ""


def workload_version(manifest: dict[str, Any]) -> Any:
    return ((manifest or {}).get("calibration") or {}).get("workload", {}).get("version")


def _calibration_notes(manifests: dict[str, dict[str, Any]]) -> list[str]:
    """What makes the time comparison less trustworthy, said next to the verdict."""
    notes = []
    for side, manifest in manifests.items():
        cal = manifest.get("calibration") or {}
        start, end = cal.get("start"), cal.get("end")
        if start and end:
            drift = end["passes_per_s"] / start["passes_per_s"] - 1.0
            if abs(drift) > 0.2:
                notes.append(
                    f"{side} calibration moved {drift:+.0%} during its run (the machine's load changed)"
                )
    threads = {side: (m.get("calibration") or {}).get("torch_threads") for side, m in manifests.items()}
    if len(set(threads.values())) > 1:
        notes.append(f"torch threads differ ({threads}); the single-thread calibration does not cover that")
    return notes


def gate_runs(baseline: Run, candidate: Run, **options: Any) -> GateResult:
    """`gate` on two loaded runs, with calibration speeds read from their manifests."""
    base_ref, base_why = reference_speed(baseline.manifest)
    cand_ref, cand_why = reference_speed(candidate.manifest)
    skipped = ""
    if base_why or cand_why:
        why = "; ".join(f"{side}: {w}" for side, w in (("baseline", base_why), ("candidate", cand_why)) if w)
        skipped = f"time comparison skipped ({why})"
    elif workload_version(baseline.manifest) != workload_version(candidate.manifest):
        skipped = "time comparison skipped (the runs were calibrated with different workload versions)"
    result = gate(
        baseline.episodes,
        candidate.episodes,
        baseline_reference=base_ref,
        candidate_reference=cand_ref,
        speed_skipped=skipped,
        **options,
    )
    if skipped:
        return result
    extra = _calibration_notes({"baseline": baseline.manifest, "candidate": candidate.manifest})
    return GateResult(result.pairs, result.tasks, result.speed, result.notes + tuple(extra))
