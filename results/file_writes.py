"""How results files are written, so that a kill or a full disk never leaves half a file
where a reader looks: a temporary file beside the target (`.NAME.PID.tmp`, removed on
failure so a full disk does not stay full of it), fsynced, renamed into place, the folder
fsynced. And the one write that cannot work that way: on a full disk there is no room for
the second copy a rename needs, so how a run ended is written over the file's own bytes.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Sequence
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def temporary(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def atomic_write(path: Path, data: bytes) -> None:
    """Write via a temporary file and rename, so readers never see half a file."""
    tmp = temporary(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)  # a full disk must not stay full of half a file
        raise
    fsync_dir(path.parent)


def write_table_atomically(path: Path, table: pa.Table) -> None:
    """A Parquet file written as atomic_write writes bytes."""
    tmp = temporary(path)
    try:
        pq.write_table(table, tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)


def overwrite_in_place(path: Path, texts: Sequence[str]) -> None:
    """Write the first of `texts` that is no longer than the file at `path` over the file's
    own bytes: the blocks it already holds suffice, so this works on a full disk (a
    copy-on-write filesystem aside). OSError(ENOSPC) when none fits, the file untouched.
    Not atomic: a crash in the write leaves the file cut short, which readers refuse."""
    size = path.stat().st_size
    fitting = [encoded for encoded in (t.encode() for t in texts) if len(encoded) <= size]
    if not fitting:
        raise OSError(errno.ENOSPC, f"no room to write {path.name} over itself")
    with open(path, "r+b") as fh:
        fh.write(fitting[0])
        fh.truncate()
        fh.flush()
        os.fsync(fh.fileno())
