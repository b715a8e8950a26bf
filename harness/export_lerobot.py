"""Demonstrations as a LeRobotDataset v3, written with pyarrow alone (no lerobot import).

LeRobot trains and evaluates from its own dataset format, so a folder that `collect`
wrote becomes one that `lerobot-train` reads. The layout and the field formats are
LeRobot 0.6's v3 (codebase_version "v3.0"), checked against its own reader frame by
frame in the Python 3.12 environment (tests/lerobot/, docs/lerobot.md):

    DIR/data/chunk-000/file-000.parquet       one row per frame
    DIR/meta/info.json                         fps, features, counts, path templates
    DIR/meta/stats.json                        per-feature statistics (normalisation)
    DIR/meta/tasks.parquet                     the instructions, as LeRobot's tasks
    DIR/meta/episodes/chunk-000/file-000.parquet  per episode: length, rows, stats
    DIR/meta/dvla_harness.json                 what v3 has no slot for (sidecar)
    DIR/videos/<camera key>/chunk-000/file-000.mp4  with `video`: the cameras as AV1

The harness's observation maps onto LeRobot's feature names (FEATURES below): the
robot's own state (`proprio_dims` leading entries, as the manifest says: Meta-World's
hand and gripper, which is what LeRobot's Meta-World env calls `agent_pos`) is
`observation.state`; the whole state vector is `observation.environment_state`, which
ACT and Diffusion Policy read as the environment's state; camera `C` is
`observation.images.C` (PNG bytes as they are: v3's image mode stores encoded images in
the parquet; video mode encodes them as MP4, harness/export_lerobot_video.py). Per frame, the episode's seed, initial-state id and spec index go in
`harness.*` features (int64), which LeRobot's training ignores (only `observation.*` and
`action` become policy inputs); the suite, split, demonstrator, its parameters and the
folder's `steps_sha256` go in the sidecar.

Statistics are computed as LeRobot computes them (datasets/compute_stats.py): per
episode, min, max, mean, population std and count exactly, and quantiles q01..q99 from a
5,000-bin histogram over [min - 1e-10, max + 1e-10] interpolated within the bin; the
dataset's are the episodes' pooled: min of mins, max of maxes, count-weighted mean, the
parallel-variance std, count-weighted quantiles. Images: per channel in [0, 1], over
LeRobot's sample of frames.
"""

from __future__ import annotations

import io
import json
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from harness.errors import UsageError
from harness.export_lerobot_video import (
    CHUNKS_SIZE,
    VIDEO_FILE_MB,
    VIDEO_PATH,
    check_video_source,
    video_features,
    write_videos,
)

CODEBASE_VERSION = "v3.0"
STATE = "observation.state"
ENV_STATE = "observation.environment_state"
IMAGE_PREFIX = "observation.images."
ACTION = "action"
EXTRA = ("harness.seed", "harness.init_state_id", "harness.episode_index")  # per frame, int64
SIDECAR = "meta/dvla_harness.json"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_FILE_MB = 100  # LeRobot's default: a data file is closed past this size
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
HISTOGRAM_BINS = 5000


@dataclass(frozen=True)
class Frames:
    """The columns of one export, in frame order, and how each frame is placed."""

    features: dict[str, dict[str, Any]]
    columns: dict[str, np.ndarray | list[bytes]]
    episode_index: np.ndarray  # per frame, 0..
    tasks: list[str]  # task_index -> instruction
    fps: int


def features_of(
    state_dim: int, proprio_dim: int, action_dim: int, cameras: Mapping[str, Sequence[int]]
) -> dict:
    """info.json's `features` for an export (LeRobot's default features appended by `write`)."""
    out: dict[str, dict[str, Any]] = {
        STATE: _vector(proprio_dim, "state"),
        ENV_STATE: _vector(state_dim, "state"),
    }
    for camera, (height, width, channels) in cameras.items():
        out[IMAGE_PREFIX + camera] = {
            "dtype": "image",
            "shape": [height, width, channels],
            "names": ["height", "width", "channels"],
        }
    out[ACTION] = _vector(action_dim, "action")
    for name in EXTRA:
        out[name] = {"dtype": "int64", "shape": [1], "names": None}
    return out


def _vector(dim: int, kind: str) -> dict[str, Any]:
    return {"dtype": "float32", "shape": [dim], "names": [f"{kind}_{i}" for i in range(dim)]}


DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


# ---- statistics, as LeRobot's compute_stats.py defines them ----------------------------


def histogram_quantile(values: np.ndarray, q: float) -> float:
    """LeRobot's quantile of one column: the bin of a 5,000-bin histogram over [min - 1e-10,
    max + 1e-10] where the running count reaches q * n, interpolated within that bin; the
    first edge when the target falls before the first bin's count, the last past the end."""
    # in the column's own precision, as LeRobot's edges are (float32 for float32 data)
    edges = np.linspace(values.min() - 1e-10, values.max() + 1e-10, HISTOGRAM_BINS + 1)
    counts = np.cumsum(np.histogram(values, bins=edges)[0])
    target = q * values.size
    i = int(np.searchsorted(counts, target))
    if i == 0:
        return float(edges[0])
    if i >= counts.size:
        return float(edges[-1])
    before, inside = counts[i - 1], counts[i] - counts[i - 1]
    if inside == 0:
        return float(edges[i])
    return float(edges[i] + (target - before) / inside * (edges[i + 1] - edges[i]))


def column_stats(array: np.ndarray) -> dict[str, np.ndarray]:
    """One episode's statistics of a (frames, dim) array, per dimension."""
    array = array.astype(np.result_type(array.dtype, np.float32), copy=False)
    mean = array.mean(axis=0)
    std = np.sqrt(np.maximum(0.0, (array**2).mean(axis=0) - mean**2))
    stats = {"min": array.min(axis=0), "max": array.max(axis=0), "mean": mean, "std": std}
    stats["count"] = np.array([array.shape[0]])
    if array.shape[0] < 2:  # LeRobot's basic stats: every quantile is the mean
        quantiles = {f"q{round(q * 100):02d}": mean.copy() for q in QUANTILES}
    else:
        quantiles = {
            f"q{round(q * 100):02d}": np.array(
                [histogram_quantile(array[:, d], q) for d in range(array.shape[1])]
            )
            for q in QUANTILES
        }
    return stats | quantiles


def pooled_stats(episodes: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The dataset's statistics of a feature from its episodes' (LeRobot's aggregation)."""
    counts = np.stack([s["count"] for s in episodes]).astype(np.float64)
    means = np.stack([s["mean"] for s in episodes])
    weights = counts.reshape(counts.shape + (1,) * (means.ndim - counts.ndim))
    total = counts.sum(axis=0)
    mean = (means * weights).sum(axis=0) / total
    variance = ((np.stack([s["std"] for s in episodes]) ** 2 + (means - mean) ** 2) * weights).sum(
        axis=0
    ) / total
    out = {
        "min": np.min(np.stack([s["min"] for s in episodes]), axis=0),
        "max": np.max(np.stack([s["max"] for s in episodes]), axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": total.astype(np.int64),
    }
    for key in (k for k in episodes[0] if k.startswith("q")):
        out[key] = (np.stack([s[key] for s in episodes]) * weights).sum(axis=0) / total
    return out


def image_stats(pngs: Sequence[bytes]) -> dict[str, np.ndarray]:
    """One episode's statistics of a camera, as LeRobot samples them: up to ~n^0.75 frames
    (100 at least, 10,000 at most) evenly spaced, each downsampled by int(side / 150) when
    its longer side is 300 pixels or more, per channel, divided by 255."""
    from PIL import Image

    n = len(pngs)
    samples = max(min(100, n), min(int(n**0.75), 10_000))
    picks = np.round(np.linspace(0, n - 1, samples)).astype(int)
    frames = []
    for i in picks:
        # channels first in memory, as LeRobot loads them: the layout decides numpy's summation
        # order, and so the float32 std's last digits (a one-frame episode reduces over a view)
        image = np.ascontiguousarray(
            np.asarray(Image.open(io.BytesIO(pngs[i])).convert("RGB")).transpose(2, 0, 1)
        )
        _, height, width = image.shape
        if max(height, width) >= 300:
            step = int(width / 150) if width > height else int(height / 150)
            image = image[:, ::step, ::step]
        frames.append(image)
    stack = np.stack(frames)  # (frames, channels, height, width)
    per_channel = stack.transpose(0, 2, 3, 1).reshape(-1, stack.shape[1])
    stats = column_stats(per_channel)
    return {k: v if k == "count" else (v / 255.0).reshape(-1, 1, 1) for k, v in stats.items()} | {
        "count": np.array([len(picks)])
    }


# ---- from a demonstrations folder ------------------------------------------------------


def read_demos(source: Path) -> tuple[pa.Table, dict[str, Any]]:
    """A `collect` folder's steps and manifest, or a usage error naming what is wrong."""
    from harness.collect import MANIFEST, STEPS

    if not (source / STEPS).is_file() or not (source / MANIFEST).is_file():
        raise UsageError(
            f"{source} is not a demonstrations folder: it needs {STEPS} and {MANIFEST} "
            "(written by `dvla-harness collect`, docs/demonstrations.md)"
        )
    try:
        manifest = json.loads((source / MANIFEST).read_text())
        table = pq.read_table(source / STEPS)
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise UsageError(f"cannot read the demonstrations in {source}: {exc}") from None
    missing = {"episode_id", "instruction", "step", "observation", "action"} - set(table.column_names)
    if missing:
        raise UsageError(f"{source / STEPS} lacks the columns {', '.join(sorted(missing))}")
    if table.num_rows == 0:
        raise UsageError(f"{source / STEPS} holds no steps: nothing to export")
    return table, manifest


def _matrix(column: pa.ChunkedArray, name: str) -> np.ndarray:
    """A list<float32> column as a (rows, dim) array; the rows must be of one length."""
    lists = column.combine_chunks()
    lengths = np.unique(pc_list_lengths(lists))
    if lengths.size != 1:
        raise UsageError(
            f"{name} vectors have different lengths ({', '.join(map(str, lengths))}); a LeRobot "
            "feature has one shape: export one task at a time (collect --tasks)"
        )
    return (
        lists.flatten().to_numpy(zero_copy_only=False).astype(np.float32).reshape(len(lists), int(lengths[0]))
    )


def pc_list_lengths(lists: pa.Array) -> np.ndarray:
    import pyarrow.compute as pc

    return pc.list_value_length(lists).to_numpy(zero_copy_only=False)


def proprio_dim(manifest: Mapping[str, Any], state_dim: int) -> int:
    """How many leading state entries are the robot's own: one figure for all tasks, from
    the manifest (`proprio_dims`); the whole state where the suite does not say."""
    dims = set((manifest.get("proprio_dims") or {}).values())
    if len(dims) == 1:
        return min(int(dims.pop()), state_dim)
    return state_dim


def frames_from_demos(table: pa.Table, manifest: Mapping[str, Any], fps: int, video: bool = False) -> Frames:
    """The export's columns from a demonstrations table, episodes in their folder order;
    with `video`, the cameras as video features."""
    episode_ids = table.column("episode_id").to_numpy()
    order = np.argsort(episode_ids, kind="stable")  # rows are in order; keep that if so
    table = table.take(pa.array(order))
    episode_ids = episode_ids[order]
    _, episode_index = np.unique(episode_ids, return_inverse=True)
    starts = np.r_[0, np.flatnonzero(np.diff(episode_index)) + 1]
    frame_index = np.arange(table.num_rows) - np.repeat(starts, np.diff(np.r_[starts, table.num_rows]))
    state = _matrix(table.column("observation"), "observation")
    action = _matrix(table.column("action"), "action")
    instructions = table.column("instruction").to_pylist()
    tasks = list(dict.fromkeys(instructions))
    task_of = {text: i for i, text in enumerate(tasks)}
    proprio = proprio_dim(manifest, state.shape[1])
    cameras = {c: _image_shape(table, c) for c in manifest.get("cameras") or []}
    columns: dict[str, Any] = {STATE: state[:, :proprio], ENV_STATE: state}
    for camera in cameras:
        columns[IMAGE_PREFIX + camera] = table.column(f"image_{camera}").to_pylist()
    columns[ACTION] = action
    for name, source in zip(EXTRA, ("seed", "init_state_id", "episode_index"), strict=True):
        # -1 where the folder has none (LIBERO's fresh initial states have no id)
        column = table.column(source).fill_null(-1) if source in table.column_names else None
        values = np.full(table.num_rows, -1) if column is None else column.to_numpy()
        columns[name] = values.astype(np.int64)
    # float64 here, float32 in the file: LeRobot's statistics see the timestamps it computed
    columns["timestamp"] = frame_index / fps
    columns["frame_index"] = frame_index.astype(np.int64)
    columns["episode_index"] = episode_index.astype(np.int64)
    columns["index"] = np.arange(table.num_rows, dtype=np.int64)
    columns["task_index"] = np.array([task_of[t] for t in instructions], dtype=np.int64)
    features = features_of(state.shape[1], proprio, action.shape[1], cameras) | DEFAULT_FEATURES
    if video:
        features = video_features(features, fps)
    return Frames(features, columns, episode_index.astype(np.int64), tasks, fps)


def _image_shape(table: pa.Table, camera: str) -> tuple[int, int, int]:
    from PIL import Image

    column = f"image_{camera}"
    if column not in table.column_names:
        raise UsageError(f"the manifest names camera {camera!r} but steps.parquet has no {column} column")
    first = Image.open(io.BytesIO(table.column(column)[0].as_py()))
    return first.height, first.width, len(first.getbands())


# ---- writing ----------------------------------------------------------------------------


def _arrow_column(name: str, feature: Mapping[str, Any], values: Any) -> pa.Array:
    """One feature as LeRobot's parquet holds it: shape [1] as a scalar column, a vector as
    a fixed-size list, an image as {bytes, path}."""
    if feature["dtype"] == "image":
        return pa.array([{"bytes": b, "path": None} for b in values], IMAGE_TYPE)
    kind = pa.float32() if feature["dtype"] == "float32" else pa.int64()
    array = np.asarray(values)
    if list(feature["shape"]) == [1]:
        return pa.array(array.reshape(-1), kind)
    flat = pa.array(array.reshape(-1), kind)
    return pa.FixedSizeListArray.from_arrays(flat, int(feature["shape"][0]))


IMAGE_TYPE = pa.struct([("bytes", pa.binary()), ("path", pa.string())])


def _hf_feature(feature: Mapping[str, Any]) -> dict[str, Any]:
    """The feature as Hugging Face `datasets` describes it in the parquet's metadata, as
    LeRobot's writer leaves it (its reader casts to the same)."""
    if feature["dtype"] == "image":
        return {"_type": "Image"}
    value = {"dtype": feature["dtype"], "_type": "Value"}
    if list(feature["shape"]) == [1]:
        return value
    return {"feature": value, "length": int(feature["shape"][0]), "_type": "List"}


def episode_stats(frames: Frames, rows: slice) -> dict[str, dict[str, np.ndarray]]:
    out = {}
    for name, feature in frames.features.items():
        values = frames.columns[name][rows]
        if feature["dtype"] in ("image", "video"):  # video: the frames before encoding, as LeRobot
            out[name] = image_stats(values)
        else:
            out[name] = column_stats(np.asarray(values).reshape(len(values), -1))
    return out


def write(frames: Frames, out: Path, sidecar: Mapping[str, Any], robot_type: str | None = None) -> None:
    """The dataset into `out` (which must not exist), through a staging folder and a
    rename: an error leaves nothing half-written."""
    if out.exists():
        raise UsageError(f"{out} exists; give a new folder (LeRobot's own writer refuses one too)")
    staging = out.with_name(out.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        _write_into(frames, staging, sidecar, robot_type)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def _write_into(frames: Frames, root: Path, sidecar: Mapping[str, Any], robot_type: str | None) -> None:
    episodes = np.flatnonzero(np.diff(np.r_[-1, frames.episode_index]))  # first row of each
    bounds = list(zip(episodes, np.r_[episodes[1:], len(frames.episode_index)], strict=True))
    names = [n for n, f in frames.features.items() if f["dtype"] != "video"]  # the parquet's columns
    hf_features = {n: _hf_feature(frames.features[n]) for n in names}
    per_episode: list[dict[str, Any]] = []
    # data files: episodes in order, a new file once one passes DATA_FILE_MB (LeRobot's rule)
    file_index, chunk_index, batch_start, batch_bytes = 0, 0, 0, 0
    files: list[tuple[int, int, int, int]] = []  # (chunk, file, first episode, end episode)
    for e, (start, end) in enumerate(bounds):
        batch_bytes += _row_bytes(frames, names, slice(start, end))
        if batch_bytes >= DATA_FILE_MB * 1024 * 1024 and e + 1 < len(bounds):
            files.append((chunk_index, file_index, batch_start, e + 1))
            batch_start, batch_bytes = e + 1, 0
            file_index += 1
            if file_index >= CHUNKS_SIZE:
                chunk_index, file_index = chunk_index + 1, 0
    files.append((chunk_index, file_index, batch_start, len(bounds)))
    for chunk, file, first, last in files:
        rows = slice(int(bounds[first][0]), int(bounds[last - 1][1]))
        table = pa.table({n: _arrow_column(n, frames.features[n], frames.columns[n][rows]) for n in names})
        table = table.replace_schema_metadata(
            {"huggingface": json.dumps({"info": {"features": hf_features}})}
        )
        path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        for e in range(first, last):
            start, end = (int(b) for b in bounds[e])
            task = frames.tasks[int(frames.columns["task_index"][start])]
            stats = episode_stats(frames, slice(start, end))
            per_episode.append(
                {
                    "episode_index": e,
                    "tasks": [task],
                    "length": end - start,
                    "data/chunk_index": chunk,
                    "data/file_index": file,
                    "dataset_from_index": start,
                    "dataset_to_index": end,
                    "meta/episodes/chunk_index": 0,
                    "meta/episodes/file_index": 0,
                    "stats": stats,
                }
            )
    videos = [n for n, f in frames.features.items() if f["dtype"] == "video"]
    for record, placed in zip(
        per_episode, write_videos(root, videos, frames.columns, bounds, frames.fps), strict=True
    ):
        record.update(placed)
    _write_meta(frames, root, per_episode, robot_type)
    (root / SIDECAR).write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")


def _row_bytes(frames: Frames, names: Sequence[str], rows: slice) -> int:
    total = 0
    for name in names:
        values = frames.columns[name][rows]
        total += sum(map(len, values)) if isinstance(values, list) else np.asarray(values).nbytes
    return total


def _write_meta(
    frames: Frames, root: Path, per_episode: list[dict[str, Any]], robot_type: str | None
) -> None:
    meta = root / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
    import pandas as pd

    # LeRobot keeps its tasks as a pandas frame indexed by the task's text
    tasks = pd.DataFrame(
        {"task_index": np.arange(len(frames.tasks))}, index=pd.Index(frames.tasks, name="task")
    )
    pq.write_table(pa.Table.from_pandas(tasks), meta / "tasks.parquet")
    columns: dict[str, list[Any]] = {}
    for record in per_episode:
        flat = {k: v for k, v in record.items() if k != "stats"}
        for feature, values in record["stats"].items():
            for key, value in values.items():
                flat[f"stats/{feature}/{key}"] = np.asarray(value).tolist()
        for key, value in flat.items():
            columns.setdefault(key, []).append(value)
    pq.write_table(pa.table(columns), root / EPISODES_PATH.format(chunk_index=0, file_index=0))
    stats = {
        name: {
            k: np.asarray(v).tolist()
            for k, v in pooled_stats([r["stats"][name] for r in per_episode]).items()
        }
        for name in frames.features
    }
    (meta / "stats.json").write_text(json.dumps(stats, indent=4) + "\n")
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": len(per_episode),
        "total_frames": len(frames.episode_index),
        "total_tasks": len(frames.tasks),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_MB,
        "video_files_size_in_mb": VIDEO_FILE_MB,
        "fps": frames.fps,
        "splits": {"train": f"0:{len(per_episode)}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if any(f["dtype"] == "video" for f in frames.features.values()) else None,
        "features": frames.features,
    }
    (meta / "info.json").write_text(json.dumps(info, indent=4) + "\n")


def export_demos(source: Path, out: Path, repo_id: str, video: bool = False) -> dict[str, Any]:
    """`dvla-harness export lerobot SOURCE --out OUT [--video]`: returns info.json's counts."""
    from adapters.registry import load_suite
    from harness.episode.latency import control_hz

    table, manifest = read_demos(source)
    suite_name = manifest.get("suite")
    try:
        hz = control_hz(load_suite(str(suite_name)))
    except (LookupError, ValueError) as exc:
        raise UsageError(
            f"{source}: the manifest's suite {suite_name!r} gives no control rate: {exc}"
        ) from None
    if hz != int(hz):
        raise UsageError(f"{suite_name} runs at {hz} Hz; LeRobot's fps is an integer")
    if video:
        check_video_source(source, manifest)
    frames = frames_from_demos(table, manifest, int(hz), video)
    sidecar = {
        "format": "dvla-harness-lerobot/1",
        "repo_id": repo_id,
        "source": {k: manifest.get(k) for k in SIDECAR_KEYS},
        "features": {
            STATE: f"the first {frames.features[STATE]['shape'][0]} entries of the state (the robot's own)",
            ENV_STATE: "the whole state vector (the harness's observation)",
            ACTION: "the demonstrator's action, clipped to the action space (as executed without noise)",
            "harness.seed": "the episode spec's seed (Meta-World: the layout seed)",
            "harness.init_state_id": "the episode spec's initial state / layout id",
            "harness.episode_index": "the episode spec's index within its task",
        },
        "fps_from": f"the suite's control rate, {hz:g} Hz",
    }
    if video:
        sidecar["videos"] = (
            "AV1 MP4 (libsvtav1 via imageio-ffmpeg's ffmpeg) with LeRobot's default encoder settings"
        )
    write(frames, out, sidecar)
    info = json.loads((out / "meta" / "info.json").read_text())
    return {k: info[k] for k in ("codebase_version", "total_episodes", "total_frames", "total_tasks", "fps")}


# The manifest's entries the sidecar keeps: where the data came from and its hash.
SIDECAR_KEYS = (
    "format",
    "suite",
    "suite_version",
    "split",
    "policy",
    "policy_params",
    "action_noise",
    "episodes_attempted",
    "episodes_kept",
    "steps_sha256",
    "proprio_dims",
    "state_positions",
    "cameras",
    "created_at",
    "environment",
)
