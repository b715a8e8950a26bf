"""A run folder on disk, written so that a crash loses at most the episode in flight.

    RUN_DIR/
      manifest.json     resolved config + provenance (rewritten atomically)
      events.jsonl      structured log, one JSON object a line, appended as it runs
      pending.jsonl     one row per finished episode, appended and flushed before the
                        next episode starts; survives a SIGKILL of the process
      episodes.parquet  all rows, compacted from pending.jsonl when a run ends
      replay.json       after `dvla-harness bench`: per configuration, seconds per chunk of
                        each round of decoding the recorded observations (results/replay.py)
      replay_observations.npz  the observations `bench` decodes (arrays, no pickle)
      traces.jsonl      with --traces: one line per action chunk, which positions each
                        forward pass committed; an episode's lines are written (one
                        flushed write) just before its row (docs/sweeps-and-plots.md)
      writer.lock       while a process writes the folder: flock()ed, with its pid, host
                        and start time; removed when it stops (see RunLock)

Readers take episodes.parquet and pending.jsonl together, so an interrupted run can
be read and resumed; if the same episode appears twice, the later write wins. A row
is one small append (~20 us), not a Parquet file per episode (~2 ms): on fast suites
that difference alone was a 5-8% harness overhead.

A line cut short (a kill mid-write, a full disk, a hand-truncated file) is dropped on
read, and dropped from the file itself before the next append to it, so that the next
row cannot be glued onto it (the dropped text goes to events.jsonl).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import stat
import sys
import time
from collections.abc import Iterable, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from results.file_writes import atomic_write, fsync_dir, overwrite_in_place, write_table_atomically
from results.labels import with_config_labels
from results.lock import LOCK, RunLock, RunLockedError
from results.manifest_check import ManifestError, check_manifest
from results.schema import (
    COLUMN_NAMES,
    EPISODE_KEY,
    READABLE_VERSIONS,
    SCHEMA_VERSION_KEY,
    arrow_schema,
)

MANIFEST = "manifest.json"
EPISODES = "episodes.parquet"
EVENTS = "events.jsonl"
PENDING = "pending.jsonl"
TRACES = "traces.jsonl"
REPLAY = "replay.json"  # `dvla-harness bench`: the replay benchmark's figures (results/replay.py)
REPLAY_OBSERVATIONS = "replay_observations.npz"  # ... and the recorded observations it decoded
VIDEOS = "videos"  # rollout videos, one MP4 per recorded episode (harness/episode/video.py)
# Everything the harness writes into a run folder; --overwrite deletes only these (and
# their temporaries), and refuses a folder that holds anything else.
HARNESS_FILES = (MANIFEST, EPISODES, EVENTS, PENDING, TRACES, REPLAY, REPLAY_OBSERVATIONS, LOCK)
HARNESS_FOLDERS = (VIDEOS,)
# atomic_write's and write_table_atomically's temporaries (results/file_writes.py) (".NAME.PID.tmp"), left behind by a kill
_TEMPORARY = re.compile(r"^\.(" + "|".join(re.escape(n) for n in HARNESS_FILES) + r")\.\d+\.tmp$")
# Fields of every trace line besides what the policy put in its trace ("committed": a
# list, one entry per forward pass, of the action positions that pass committed).
TRACE_FIELDS = (
    "run_id", "suite", "task", "episode_index", "policy", "policy_config_id", "started_at", "chunk", "step",
)  # fmt: skip


class ResultsFileError(ValueError):
    """A results file or folder is missing, foreign, or of another schema version."""


def repair_tail(path: Path) -> tuple[str, bytes] | None:
    """Make an append-only JSON-lines file end at a line boundary before it is appended to.

    A last line without its newline (a kill mid-write, a full disk, a hand-truncated
    file) would otherwise be glued to the next line written, and the file would stop
    parsing. If that line is a complete JSON value (only the newline was lost), the
    newline is added and it stays, as readers already counted it; otherwise it is
    truncated away. Returns ("completed" | "dropped", the line's bytes), or None if the
    file was whole.
    """
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return None
    if size == 0:
        return None
    with open(path, "rb+") as fh:
        fh.seek(size - 1)
        if fh.read(1) == b"\n":
            return None
        cut, end = 0, size
        while end > 0:  # the last newline, read backwards a block at a time
            start = max(0, end - (1 << 16))
            fh.seek(start)
            i = fh.read(end - start).rfind(b"\n")
            if i >= 0:
                cut = start + i + 1
                break
            end = start
        fh.seek(cut)
        tail = fh.read()
        try:
            json.loads(tail)
            action = "completed"
            fh.seek(size)
            fh.write(b"\n")
        except ValueError:  # JSONDecodeError and UnicodeDecodeError
            action = "dropped"
            fh.truncate(cut)
        fh.flush()
        os.fsync(fh.fileno())
    return action, tail


def strict_json(value: Any) -> Any:
    """`value` with every non-finite number as null: strict JSON (RFC 8259, and most
    readers outside Python) has no NaN or Infinity, so a file holding one cannot be read
    by them. Numpy scalars become Python numbers first, so theirs are caught too."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # a numpy scalar
        return strict_json(value.item())
    return value


def _json_default(value: Any) -> Any:
    if isinstance(value, datetime):
        return value.isoformat()
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in a row")


def rows_to_table(rows: Iterable[Mapping[str, Any]]) -> pa.Table:
    return pa.Table.from_pylist([dict(r) for r in rows], schema=arrow_schema())


def _widen(path: Path, table: pa.Table, field: pa.Field) -> pa.Table:
    """A column of an older table in its current type: a struct that has gained fields
    since (the chain `subtasks` records) reads with them null, so old and new rows concat.
    A cast that changes a value is refused, naming the column and row: a `success` of
    NaN, cast to bool, would read as a success."""
    before = table.column(field.name)
    try:
        column = before.cast(field.type)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise ResultsFileError(
            f"{path}: column {field.name!r} is {before.type}, which this "
            f"dvla-harness cannot read as {field.type} ({exc})"
        ) from None
    if not pa.types.is_nested(field.type):
        _refuse_changed_values(path, field, before, column)
    return table.set_column(table.column_names.index(field.name), field, column)


def _refuse_changed_values(
    path: Path, field: pa.Field, before: pa.ChunkedArray, after: pa.ChunkedArray
) -> None:
    """ResultsFileError when reading `before` as `field.type` changed a value (it does not
    come back as itself: NaN or 0.5 read as True)."""
    try:
        same = pc.equal(after.cast(before.type), before)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        return  # no way back to compare: the cast itself was allowed
    changed = pc.and_(pc.is_valid(before), pc.invert(pc.fill_null(same, False)))
    if pc.any(changed).as_py():
        row = pc.index(changed, True).as_py()
        raise ResultsFileError(
            f"{path}: column {field.name!r} holds {before[row].as_py()!r} in row {row}, which is not "
            f"a {field.type} value (it would read as {after[row].as_py()!r}); the file was not written "
            "by dvla-harness as it is"
        )


def read_table(path: Path) -> pa.Table:
    """Read one episode Parquet file, refusing files of another schema or version."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as exc:
        raise ResultsFileError(f"{path}: not a readable Parquet file ({exc})") from None
    meta = table.schema.metadata or {}
    version = meta.get(SCHEMA_VERSION_KEY)
    if version is None:
        raise ResultsFileError(f"{path}: not a dvla-harness episode table (no schema version)")
    if version.decode() not in READABLE_VERSIONS:
        raise ResultsFileError(
            f"{path}: schema version {version.decode()}, but this dvla-harness reads versions "
            f"{', '.join(READABLE_VERSIONS)}: upgrade dvla-harness to read it"
        )
    for field in arrow_schema():  # nullable columns added since the file was written: null
        if field.nullable and field.name not in table.column_names:
            table = table.append_column(field, pa.nulls(len(table), field.type))
        elif field.name in table.column_names and table.schema.field(field.name).type != field.type:
            table = _widen(path, table, field)
    return table.select([n for n in COLUMN_NAMES if n in table.column_names])


_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def not_regular(path: Path) -> str:
    """What `path` is when it exists and is not a regular file ('a FIFO (named pipe)',
    'a folder', ...); '' for a regular file (a link to one included) or nothing at all.

    Opening a FIFO blocks until another process opens its other end, and a folder reads
    as no file at all: either would hang a run or make a reader count 0 episodes."""
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return ""
    if stat.S_ISREG(mode):
        return ""
    return next((kind for test, kind in _KINDS if test(mode)), "not a regular file")


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of an append-only JSON-lines file; a last line cut short by a kill
    (that episode was in flight) is dropped, any other bad line is an error."""
    if not path.is_file():
        return []
    lines = path.read_text().splitlines()
    records = []
    for i, line in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                break
            raise ResultsFileError(f"{path}: line {i + 1} is not valid JSON") from None
    return records


class RunDir:
    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        self._pending: Any = None  # open append handle, kept across episodes
        self._traces: Any = None  # the same for traces.jsonl
        self._repaired: set[str] = set()  # JSON-lines files whose tail was checked

    @property
    def manifest_path(self) -> Path:
        return self.path / MANIFEST

    def is_run(self) -> bool:
        return self.manifest_path.is_file()

    def check_files(self) -> None:
        """Refuse a folder where a file the harness writes is something else (a FIFO, a
        folder, a device), before anything opens it; ResultsFileError names it."""
        for name in HARNESS_FILES:
            kind = not_regular(self.path / name)
            if kind:
                raise ResultsFileError(
                    f"{self.path / name}: is {kind}, not a regular file; dvla-harness writes only "
                    "regular files there, so this folder was changed by hand: move it away"
                )

    def is_empty(self) -> bool:
        """Nothing recorded: no entries but a leftover lock or temporary file."""
        if not self.path.exists():
            return True
        return all(p.name == LOCK or _TEMPORARY.match(p.name) for p in self.path.iterdir())

    def foreign_files(self) -> list[str]:
        """Entries the harness did not write (sorted names): --overwrite leaves such a folder alone."""
        if not self.path.is_dir():
            return []
        return sorted(
            p.name + ("/" if p.is_dir() else "")
            for p in self.path.iterdir()
            if not ((p.name in HARNESS_FILES or _TEMPORARY.match(p.name)) and not p.is_dir())
            and not (p.name in HARNESS_FOLDERS and p.is_dir() and not p.is_symlink())
        )

    def temporaries(self) -> list[Path]:
        if not self.path.is_dir():
            return []
        return sorted(p for p in self.path.iterdir() if _TEMPORARY.match(p.name) and not p.is_dir())

    def remove_temporaries(self) -> list[str]:
        """Delete the temporary files a killed writer left (call with the lock held)."""
        removed = []
        for p in self.temporaries():
            p.unlink(missing_ok=True)
            removed.append(p.name)
        return removed

    def remove_temporaries_unless_locked(self) -> list[str]:
        """For the commands that only read a folder (show, leaderboard, gate, report, plot):
        what a writer killed mid-compaction left is removed by whichever command opens the
        folder next, not only by a writer. A live writer's temporary is the file it is about
        to rename into place, so this takes the writer lock first and leaves everything alone
        while another process holds it (or when the folder cannot be locked: read-only)."""
        if not self.is_run() or not self.temporaries():
            return []
        lock = RunLock(self.path)
        try:
            lock.acquire()
        except (RunLockedError, OSError):
            return []
        try:
            removed = self.remove_temporaries()
            if removed:
                with contextlib.suppress(OSError):
                    self.log_event("temporaries_removed", files=removed, command=sys.argv)
        except OSError:
            removed = []  # tidying up is not what the reader was asked for
        finally:
            with contextlib.suppress(OSError):
                lock.release(keep_stale=True)  # the next writer still says one was killed
        return removed

    def remove_recorded(self) -> None:
        """Delete what the harness wrote (for --overwrite, with the lock held; the lock stays)."""
        for name in HARNESS_FILES:
            if name != LOCK:
                (self.path / name).unlink(missing_ok=True)
        for name in HARNESS_FOLDERS:
            folder = self.path / name
            if folder.is_dir() and not folder.is_symlink():
                shutil.rmtree(folder)
        self.remove_temporaries()
        fsync_dir(self.path)

    def write_video(self, relative: str, data: bytes) -> None:
        """An episode's MP4 at `relative` (under videos/), written atomically."""
        path = self.path / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, data)

    def lock(self) -> RunLock:
        return RunLock(self.path)

    def create(self) -> None:
        self.path.mkdir(parents=True, exist_ok=True)

    def _open_append(self, name: str) -> Any:
        """An append handle to a JSON-lines file whose cut-off last line (if any) is gone."""
        self._repair(name)
        return open(self.path / name, "a")

    def _repair(self, name: str) -> None:
        if name in self._repaired:
            return
        self._repaired.add(name)
        fixed = repair_tail(self.path / name)
        if fixed is not None:
            action, tail = fixed
            self.log_event(
                "partial_line_" + action,
                file=name,
                bytes=len(tail),
                text=tail[:4000].decode("utf-8", "replace"),
            )

    def repair(self) -> None:
        """Check every JSON-lines file's tail now (see repair_tail); with the lock held."""
        for name in (EVENTS, PENDING, TRACES):
            self._repair(name)

    def write_manifest(self, manifest: Mapping[str, Any]) -> None:
        text = json.dumps(strict_json(manifest), indent=2, allow_nan=False)
        atomic_write(self.manifest_path, (text + "\n").encode())

    def overwrite_manifest(self, manifest: Mapping[str, Any], ending: Mapping[str, Any]) -> None:
        """The manifest written over the file's own bytes, for a full disk, where the atomic
        write has no room for its second copy (results/file_writes.py overwrite_in_place):
        `manifest` indented or compact, else the file's own manifest with only `ending`
        (status, finished_at) changed; only for saying how a run stopped by a full disk ended."""
        on_disk = json.loads(self.manifest_path.read_bytes())
        versions = ((manifest, 2), (manifest, None), ({**on_disk, **ending}, None))
        overwrite_in_place(
            self.manifest_path,
            [
                json.dumps(strict_json(data), indent=indent, separators=None if indent else (",", ":")) + "\n"
                for data, indent in versions
            ],
        )

    def read_manifest(self, required: tuple[str, ...] = ()) -> dict[str, Any]:
        """The manifest, checked (results.manifest_check); `required`: fields it must have."""
        self.check_files()
        if not self.is_run():
            raise ResultsFileError(f"{self.path}: not a run folder (no {MANIFEST})")
        try:
            data = json.loads(self.manifest_path.read_bytes())
            return check_manifest(data, self.manifest_path, required)
        except (ValueError, RecursionError) as exc:  # JSON, UTF-8, ManifestError
            detail = (
                str(exc) if isinstance(exc, ManifestError) else f"{self.manifest_path}: invalid JSON ({exc})"
            )
            raise ResultsFileError(detail) from None

    def log_event(self, event: str, **fields: Any) -> None:
        record = {"time": time.time(), "event": event, **fields}
        with self._open_append(EVENTS) as fh:
            fh.write(json.dumps(strict_json(record), default=str, allow_nan=False) + "\n")
            fh.flush()

    def append_episode(self, row: Mapping[str, Any]) -> None:
        """Record one finished episode: one flushed line, complete or absent after a kill."""
        line = json.dumps(dict(row), default=_json_default, allow_nan=False) + "\n"
        if self._pending is None:
            self._pending = self._open_append(PENDING)  # closed in compact()
        self._pending.write(line)
        self._pending.flush()  # in the kernel now: a killed process cannot lose it

    def append_traces(self, lines: Iterable[Mapping[str, Any]]) -> None:
        """One episode's chunk traces in one flushed write, made before its row is appended:
        a recorded row always has its traces; an episode killed in between runs again on
        --resume and its newer lines win on read."""
        text = "".join(
            json.dumps(strict_json(dict(t)), default=_json_default, separators=(",", ":"), allow_nan=False)
            + "\n"
            for t in lines
        )
        if not text:
            return
        if self._traces is None:
            self._traces = self._open_append(TRACES)  # closed in compact()
        self._traces.write(text)
        self._traces.flush()

    def has_traces(self) -> bool:
        return (self.path / TRACES).is_file()

    def read_traces(self) -> pd.DataFrame:
        """Every recorded chunk trace, one row each; of an episode traced twice (run again
        after a kill, or by --retry-failed), only the latest attempt."""
        records = _read_jsonl(self.path / TRACES)
        if not records:
            return pd.DataFrame(columns=[*TRACE_FIELDS, "committed"])
        df = pd.DataFrame(records)
        latest = df.groupby(["policy_config_id", "task", "episode_index"])["started_at"].transform("max")
        return df[df["started_at"] == latest].reset_index(drop=True)

    def pending_rows(self) -> list[dict[str, Any]]:
        rows = _read_jsonl(self.path / PENDING)
        for row in rows:
            if row.get("started_at"):
                row["started_at"] = datetime.fromisoformat(row["started_at"])
        return rows

    def read_episodes(self) -> pd.DataFrame:
        """Every recorded episode, one row each (the latest write of a repeated episode)."""
        self.check_files()
        tables = [read_table(self.path / EPISODES)] if (self.path / EPISODES).is_file() else []
        pending = self.pending_rows()
        if pending:
            try:
                tables.append(rows_to_table(pending))
            except (pa.ArrowInvalid, pa.ArrowTypeError, KeyError) as exc:
                raise ResultsFileError(
                    f"{self.path / PENDING}: rows do not match the schema ({exc})"
                ) from None
        if not tables:
            return arrow_schema().empty_table().to_pandas()
        df = pa.concat_tables(tables).to_pandas()
        df = df.drop_duplicates(subset=list(EPISODE_KEY), keep="last")
        return with_config_labels(df.reset_index(drop=True)[list(COLUMN_NAMES)])

    def compact(self, stamp: Mapping[str, Any] | None = None) -> None:
        """Fold pending rows into episodes.parquet (atomically), then drop pending.jsonl.

        stamp: columns to set in every row as the file is written, a verdict on the whole
        run known only at its end (calibration drift: speed_reliable); with a stamp the
        file is written even when no row is pending."""
        handles, self._pending, self._traces = (self._pending, self._traces), None, None
        failed: OSError | None = None
        for handle in handles:
            if handle is not None:
                try:
                    handle.close()  # the file is closed even when its last flush fails
                except OSError as exc:
                    failed = failed or exc
        if failed is not None:
            raise failed
        pending = self.path / PENDING
        if not pending.is_file() and not (stamp and (self.path / EPISODES).is_file()):
            return
        df = self.read_episodes()
        for column, value in (stamp or {}).items():
            df[column] = [value] * len(df)
        df = df.sort_values(["policy_config_id", "task_index", "episode_index"], kind="stable")
        table = pa.Table.from_pandas(df, schema=arrow_schema(), preserve_index=False)
        write_table_atomically(self.path / EPISODES, table.replace_schema_metadata(arrow_schema().metadata))
        pending.unlink(missing_ok=True)
        fsync_dir(self.path)
