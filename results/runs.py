"""Loading runs for outputs that combine several of them (leaderboards, gates, plots).

A run is a run folder (manifest.json + episodes.parquet and/or pending.jsonl) or a bare
episodes Parquet file, whose manifest is read from beside it when there is one. Every
cross-run output starts here, so a missing, foreign or wrong-version file is refused in
one place with one message, and temporary files a killed writer left are removed here
(RunDir.remove_temporaries_unless_locked) as `run --resume` would.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from results.labels import with_config_labels
from results.schema import COLUMN_NAMES, EPISODE_KEY
from results.store import EPISODES, MANIFEST, ResultsFileError, RunDir, read_table


@dataclass(frozen=True)
class Run:
    path: Path
    manifest: dict[str, Any] = field(repr=False)
    episodes: pd.DataFrame = field(repr=False)

    @property
    def machine(self) -> str:
        """What timings depend on: host, CPU model and GPU; '' when no manifest says."""
        env = self.manifest.get("environment") or {}
        if not env:
            return ""
        return f"{env.get('host')} | {env.get('cpu')} | GPU {env.get('gpu') or 'none'}"

    def row_machines(self) -> pd.Series | str:
        """Each row's machine: the run's, except rows a Ray worker ran on another node
        (their `host` column), which get that node's own, so no speedup pairs them with
        rows timed elsewhere."""
        own = self.machine
        if "host" not in self.episodes or not own:
            return own
        run_host = (self.manifest.get("environment") or {}).get("host")
        hosts = self.episodes["host"]
        elsewhere = hosts.notna() & (hosts != run_host)
        if not elsewhere.any():
            return own
        return hosts.where(elsewhere, "").map(lambda h: f"{h} | node of a Ray cluster" if h else own)

    @property
    def label(self) -> str:
        return str(self.path)

    @property
    def speed_warning(self) -> str:
        """Why this run's speed figures are unreliable, or '' (calibration drift, starved
        episodes)."""
        return speed_warning(self.manifest)


# How far a run's calibration may move between its start and its end before its speed
# figures are flagged as unreliable. Idle and steadily loaded runs of this project moved
# 0-4%; a machine whose load changed mid-run moved 2x (docs/ci-gate.md has the numbers).
CALIBRATION_DRIFT_TOLERANCE = 0.25


def calibration_drift(manifest: Mapping[str, Any]) -> float | None:
    """end / start - 1 of a run's calibration speed; None without both measurements."""
    cal = (manifest or {}).get("calibration") or {}
    start, end = cal.get("start"), cal.get("end")
    if not (start and end and start.get("passes_per_s") and end.get("passes_per_s")):
        return None
    return float(end["passes_per_s"]) / float(start["passes_per_s"]) - 1.0


def speed_warning(manifest: Mapping[str, Any]) -> str:
    """Why a run's speed figures are unreliable, or '' (the manifest's own verdict when it
    recorded one, else computed from its calibration, so older runs are judged too)."""
    manifest = manifest or {}
    if manifest.get("speed_reliable") is False:
        return str(manifest.get("speed_warning") or "flagged unreliable in its manifest")
    if manifest.get("speed_reliable") is True:
        return ""
    return "; ".join(speed_reasons(manifest))


def speed_reasons(manifest: Mapping[str, Any]) -> list[str]:
    """Each reason a run's speed figures are unreliable, from what its manifest measured:
    a calibration drift beyond the tolerance, and starved episodes (harness/episode/cpu_time.py)."""
    reasons = []
    drift = calibration_drift(manifest)
    if drift is not None and abs(drift) > CALIBRATION_DRIFT_TOLERANCE:
        reasons.append(drift_reason(manifest, drift))
    starvation = (manifest or {}).get("starvation") or {}
    if starvation.get("starved_episodes"):
        worst = starvation.get("worst_ratio")
        reasons.append(
            f"{starvation['starved_episodes']} of {starvation.get('judged_episodes', '?')} episodes "
            f"judged were starved (policy time over {starvation.get('factor', '?')}x its CPU time"
            + (f", worst {worst:.2f}x" if isinstance(worst, (int, float)) else "")
            + "): the policy waited for a core the machine gave to other work"
        )
    return reasons


def drift_reason(manifest: Mapping[str, Any], drift: float) -> str:
    cal = manifest["calibration"]
    return (
        f"the calibration moved {drift:+.0%} between the run's start and end "
        f"({cal['start']['passes_per_s']:,.0f} -> {cal['end']['passes_per_s']:,.0f} passes/s; "
        f"tolerance {CALIBRATION_DRIFT_TOLERANCE:.0%}): the machine's load changed during the run"
    )


def load_run(path: str | os.PathLike[str]) -> Run:
    """One run from a run folder or an episodes Parquet file; ResultsFileError if unusable."""
    p = Path(path)
    if p.is_dir():
        run_dir = RunDir(p)
        if not run_dir.is_run():
            raise ResultsFileError(f"{p}: not a run folder (no {MANIFEST}; make one with `dvla-harness run`)")
        run_dir.remove_temporaries_unless_locked()  # what a killed writer left
        manifest = run_dir.read_manifest()
        episodes = run_dir.read_episodes()
    elif p.is_file():
        if p.suffix != ".parquet":
            raise ResultsFileError(f"{p}: expected a run folder or an episodes .parquet file")
        episodes = with_config_labels(read_table(p).to_pandas()[list(COLUMN_NAMES)])
        beside = p.parent / MANIFEST
        if beside.is_file():
            RunDir(p.parent).remove_temporaries_unless_locked()
        manifest = RunDir(p.parent).read_manifest() if beside.is_file() else {}
    else:
        raise ResultsFileError(f"{p}: no such run folder or file")
    if episodes.empty:
        raise ResultsFileError(f"{p}: holds no episodes")
    return Run(
        path=p.parent if p.is_file() and p.name == EPISODES else p, manifest=manifest, episodes=episodes
    )


def load_runs(paths: Iterable[str | os.PathLike[str]]) -> list[Run]:
    paths = list(paths)
    if not paths:
        raise ResultsFileError("no runs given")
    return [load_run(p) for p in paths]


def combined_episodes(runs: Iterable[Run]) -> pd.DataFrame:
    """All rows of several runs, with `run` (its path) and `machine` columns added, one
    row per episode: every cross-run output (leaderboard, gate, reports, plots) reads
    through here, so they all count the same episodes. An episode found in several runs
    (a copied or resumed folder given twice) on one machine counts once, its latest
    write; how many were dropped is in `df.attrs["duplicates"]`."""
    frames = [r.episodes.assign(run=r.label, machine=r.row_machines()) for r in runs]
    df, dropped = dedupe_episodes(pd.concat(frames, ignore_index=True))
    df.attrs["duplicates"] = dropped
    return df


def _latency_key(df: pd.DataFrame) -> pd.Series:
    """A row's latency and execution; `none` for rows written before they were recorded."""
    if "inference_latency" not in df:
        return pd.Series("none", index=df.index)
    mode = df["inference_latency"].fillna("none")
    execution = df["execution"].fillna("sync") if "execution" in df else "sync"
    return mode.where(mode == "none", mode + " " + execution)


def dedupe_episodes(episodes: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """(one row per episode and machine, the latest write of each; rows dropped)."""
    df = episodes.copy()
    for column in ("run", "machine"):
        if column not in df:
            df[column] = ""
    df["machine"] = df["machine"].fillna("")
    if "started_at" in df:
        df = df.sort_values("started_at", kind="stable")
    # one episode at two inference latencies is two measurements (docs/latency.md)
    latency = _latency_key(df)
    kept = df.assign(_latency=latency).drop_duplicates([*EPISODE_KEY, "machine", "_latency"], keep="last")
    kept = kept.drop(columns="_latency").reset_index(drop=True)
    kept.attrs["duplicates"] = episodes.attrs.get("duplicates", 0) + len(df) - len(kept)
    return kept, kept.attrs["duplicates"]


def batch_sizes(df: pd.DataFrame) -> list[int]:
    """The --batch-envs sizes of `df`'s rows; rows from before the column existed ran
    unbatched (1)."""
    if "batch_envs" not in df:
        return [1] if len(df) else []
    return sorted({int(b) for b in df["batch_envs"].fillna(1)})
