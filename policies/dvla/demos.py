"""Demonstrations as training reads them: one `collect` folder, or several trained on as
one (clean and DART-noisy collections of a suite), with each step's target chunk of
actions, the camera images kept as PNG bytes until a batch needs them, and what the
manifests recorded about each task's state (where positions sit, how much of it is the
robot's own) for the `--state-features` that need it.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import torch


@dataclass
class Demos:
    observations: np.ndarray  # (N, obs_dim) float32
    actions: np.ndarray  # (N, action_dim)
    chunk_index: np.ndarray  # (N, H) rows of `actions` forming each step's target chunk
    instructions: list[str]  # per row
    sha256: str
    cameras: tuple[str, ...] = ()
    image_size: int = 0
    images: list[np.ndarray] = field(default_factory=list)  # per camera: (N,) PNG bytes
    state_dims: tuple[int, ...] = ()  # observation sizes before padding (one unless mixed)
    noisy: np.ndarray | None = None  # (N,) bool: row from a `collect --action-noise` folder
    # Where world positions sit in the state (the envs' `state_positions`), one tuple per
    # task the manifests recorded them for; `positions()` says whether they are usable.
    state_positions: dict[str, tuple[int, ...]] = field(default_factory=dict)
    tasks: frozenset[str] = frozenset()
    # Per folder, what the checkpoint's meta says it was trained on: suite (LIBERO's names
    # `initial_states=fresh` when the starts were held out from evaluation), split, hash.
    sources: list[dict[str, Any]] = field(default_factory=list)
    # How many leading state entries are the robot's own (the envs' `proprio_dim`), per task.
    proprio_dims: dict[str, int] = field(default_factory=dict)

    def proprio(self) -> int:
        """The one proprioception length every task shares; raises saying why not."""
        if not self.cameras:
            raise ValueError(
                "--state-features proprio: the demonstrations have no camera images, so the model "
                "would see no objects at all; collect with images (e.g. simpler/all:obs=images)"
            )
        return _shared(
            "proprio",
            self.tasks,
            self.proprio_dims,
            "how much of the state is the robot's own",
            "`proprio_dims`",
            "the tasks' robot states differ in length; train tasks of one robot",
        )

    def positions(self) -> tuple[int, ...]:
        """The one set of state positions every task shares; raises saying why not."""
        return _shared(
            "relative",
            self.tasks,
            self.state_positions,
            "where positions sit in the state",
            "`state_positions`",
            "the tasks keep positions at different places in their states (e.g. LIBERO goal/10/90); "
            "train one suite of one layout, or use --state-features raw",
        )

    def image_batch(self, rows: torch.Tensor) -> torch.Tensor | None:
        """(B, cameras, H, W, 3) uint8 for some rows, decoded on demand: the PNGs of a
        LIBERO suite are ~1 GB as pixels, a tenth of that compressed."""
        if not self.cameras:
            return None
        from policies.observations import unpng

        idx = rows.tolist()
        frames = [[unpng(column[i]) for column in self.images] for i in idx]
        return torch.from_numpy(np.asarray(frames, dtype=np.uint8))


def _shared(
    feature: str, tasks: frozenset[str], per_task: dict[str, Any], what: str, field_name: str, differ: str
) -> Any:
    """The one value of a per-task state property (recorded by collect) every task
    shares, for `--state-features FEATURE`; a missing or differing one is an error."""
    missing = sorted(tasks - set(per_task))
    if missing:
        raise ValueError(
            f"--state-features {feature}: the demonstrations do not record {what} for task "
            f"{missing[0]!r} (collected before {field_name} was recorded, or the suite's env does "
            "not declare it); collect them again or use --state-features raw"
        )
    found = {per_task[t] for t in tasks}
    if len(found) > 1:
        raise ValueError(f"--state-features {feature}: {differ}")
    return found.pop()


def load_demos(folders: str | Path | Sequence[str | Path], chunk_len: int) -> Demos:
    """One demonstrations folder, or several trained on as one (e.g. clean and DART-noisy
    collections of a suite): their episodes are concatenated, and the data hash is the
    folder's own, or for several the hash of their hashes in the order given."""
    paths = [Path(folders)] if isinstance(folders, str | Path) else [Path(f) for f in folders]
    manifests, frames = [], []
    for folder in paths:
        if not (folder / "manifest.json").is_file() or not (folder / "steps.parquet").is_file():
            raise ValueError(f"{folder}: not a demonstrations folder (needs manifest.json and steps.parquet)")
        manifests.append(json.loads((folder / "manifest.json").read_text()))
        frames.append(pq.read_table(folder / "steps.parquet").to_pandas())
    folder, manifest = paths[0], manifests[0]
    for other, m in zip(paths[1:], manifests[1:], strict=True):
        for key in ("cameras", "image_size", "action_dim"):
            if m.get(key) != manifest.get(key):
                raise ValueError(
                    f"{other}: {key} {m.get(key)!r} differs from {folder}'s {manifest.get(key)!r}; "
                    "demonstrations trained on together must match"
                )
    positions: dict[str, tuple[int, ...]] = {}
    proprio: dict[str, int] = {}
    for path, m in zip(paths, manifests, strict=True):
        for task, found in (m.get("state_positions") or {}).items():
            if positions.setdefault(task, tuple(found)) != tuple(found):
                raise ValueError(f"{path}: task {task!r} records other state positions than before")
        for task, size in (m.get("proprio_dims") or {}).items():
            if proprio.setdefault(task, int(size)) != int(size):
                raise ValueError(f"{path}: task {task!r} records another proprioception length than before")
    offset = 0
    for df, m in zip(frames, manifests, strict=True):
        df["episode_id"] += offset  # episode ids unique across folders: chunks never cross
        offset = int(df["episode_id"].max()) + 1
        df["_noisy"] = float(m.get("action_noise") or 0.0) > 0
    df = frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)
    sha256 = manifest.get("steps_sha256", "")
    if len(paths) > 1:
        joined = "+".join(m.get("steps_sha256", "") for m in manifests)
        sha256 = hashlib.sha256(joined.encode()).hexdigest()
    obs, state_dims = _padded(df["observation"].to_numpy())
    actions = np.stack(df["action"].to_numpy()).astype(np.float64)
    # Target chunk of step t: actions t..t+H-1 of the same episode, the last one repeated.
    episode = df["episode_id"].to_numpy()
    last = np.zeros(len(df), dtype=np.int64)
    for ep_end in np.flatnonzero(np.r_[episode[1:] != episode[:-1], True]):
        start = ep_end
        while start > 0 and episode[start - 1] == episode[ep_end]:
            start -= 1
        last[start : ep_end + 1] = ep_end
    idx = np.minimum(np.arange(len(df))[:, None] + np.arange(chunk_len)[None, :], last[:, None])
    cameras = tuple(manifest.get("cameras") or ())
    missing = [c for c in cameras if f"image_{c}" not in df.columns]
    if missing:
        raise ValueError(f"{folder}: the manifest lists cameras {missing} that steps.parquet lacks")
    return Demos(
        obs,
        actions,
        idx,
        df["instruction"].tolist(),
        sha256,
        cameras,
        int(manifest.get("image_size") or 0),
        [df[f"image_{c}"].to_numpy() for c in cameras],
        state_dims,
        df["_noisy"].to_numpy(dtype=bool),
        positions,
        frozenset(df["task"].unique()),
        [_source(m) for m in manifests],
        proprio,
    )


def _source(manifest: dict[str, Any]) -> dict[str, Any]:
    """A demonstrations folder as a checkpoint records it: which suite and split, and
    whether its initial states were fresh draws checked against evaluation's (LIBERO)."""
    return {
        "suite": manifest.get("suite", ""),
        "split": manifest.get("split", ""),
        "steps_sha256": manifest.get("steps_sha256", ""),
        "fresh_initial_states": bool(manifest.get("initial_states")),
    }


def _padded(rows: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """Observations as one (N, D) array, zero-padded at the end to the longest.

    LIBERO goal/10/90 tasks have different objects, so their state vectors differ in
    length; the instruction tells the model which layout it is reading. The sizes seen
    are recorded in the checkpoint so the policy pads (and accepts) exactly those."""
    sizes = tuple(sorted({len(r) for r in rows}))
    if len(sizes) == 1:
        return np.stack(rows).astype(np.float32), sizes
    out = np.zeros((len(rows), sizes[-1]), dtype=np.float32)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out, sizes
