"""Loading runs for outputs that combine several of them (leaderboards, gates, plots).

A run is a run folder (manifest.json + episodes.parquet and/or pending.jsonl) or a bare
episodes Parquet file, whose manifest is read from beside it when there is one. Every
cross-run output starts here, so a missing, foreign or wrong-version file is refused in
one place with one message.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

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

    @property
    def label(self) -> str:
        return str(self.path)


def load_run(path: str | os.PathLike[str]) -> Run:
    """One run from a run folder or an episodes Parquet file; ResultsFileError if unusable."""
    p = Path(path)
    if p.is_dir():
        run_dir = RunDir(p)
        if not run_dir.is_run():
            raise ResultsFileError(f"{p}: not a run folder (no {MANIFEST}; make one with `dvla-harness run`)")
        manifest = run_dir.read_manifest()
        episodes = run_dir.read_episodes()
    elif p.is_file():
        if p.suffix != ".parquet":
            raise ResultsFileError(f"{p}: expected a run folder or an episodes .parquet file")
        episodes = read_table(p).to_pandas()[list(COLUMN_NAMES)]
        beside = p.parent / MANIFEST
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
    frames = [r.episodes.assign(run=r.label, machine=r.machine) for r in runs]
    df, dropped = dedupe_episodes(pd.concat(frames, ignore_index=True))
    df.attrs["duplicates"] = dropped
    return df


def dedupe_episodes(episodes: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """(one row per episode and machine, the latest write of each; rows dropped)."""
    df = episodes.copy()
    for column in ("run", "machine"):
        if column not in df:
            df[column] = ""
    df["machine"] = df["machine"].fillna("")
    if "started_at" in df:
        df = df.sort_values("started_at", kind="stable")
    kept = df.drop_duplicates([*EPISODE_KEY, "machine"], keep="last").reset_index(drop=True)
    kept.attrs["duplicates"] = episodes.attrs.get("duplicates", 0) + len(df) - len(kept)
    return kept, kept.attrs["duplicates"]
