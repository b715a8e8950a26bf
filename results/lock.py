"""The single-writer lock of a run folder (OUT/writer.lock): one process writes a run
folder at a time, a killed writer never blocks the next, and a second writer is refused
naming the holder (pid, host, start time)."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import stat
import sys
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

LOCK = "writer.lock"


class RunLockedError(Exception):
    """Another process writes the run folder (or may: its lock cannot be checked from here)."""


def _pid_alive(pid: Any) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    except (OverflowError, OSError):
        return False
    return True


def describe_holder(holder: Mapping[str, Any] | None) -> str:
    if not holder:
        return "holder unknown (its record is empty or unreadable)"
    return f"pid {holder.get('pid')} on host {holder.get('host')}, started {holder.get('started_at')}"


class RunLock:
    """The single-writer lock of a run folder: flock() on OUT/writer.lock, plus a JSON
    record in that file of who holds it (pid, host, start time, command) for messages.

    The flock dies with the process that holds it, so a killed writer never blocks the
    next one; its record stays behind and is reported as stale when the lock is taken
    over. On release the file is removed (while still locked; a process that opened
    the old file checks that the path is still the file it locked, and retries).

    Where it does not hold: flock is per host on network filesystems whose locks are
    not shared between clients (NFS mounted with `nolock`, some FUSE filesystems). On
    such a mount two hosts writing one folder are not excluded; a record left by
    another host is never taken over here (that host's process cannot be checked), so
    the user is asked to delete it.
    """

    def __init__(self, folder: str | os.PathLike[str]):
        self.folder = Path(folder)
        self.path = self.folder / LOCK
        self._fd: int | None = None
        self.stale: dict[str, Any] | None = None  # the record of a holder that is gone
        self.unsupported = False  # the filesystem refused flock: only the record guards

    @property
    def held(self) -> bool:
        return self._fd is not None

    def _read_record(self, fd: int) -> dict[str, Any] | None:
        data = os.pread(fd, 1 << 16, 0)
        if not data.strip():
            return None
        try:
            record = json.loads(data)
        except ValueError:
            return {}
        return record if isinstance(record, dict) else {}

    def acquire(self) -> None:
        """Take the lock or raise RunLockedError naming the holder; writes this process's record."""
        if self._fd is not None:
            return
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            if not stat.S_ISREG(os.fstat(fd).st_mode):  # a FIFO put there by hand: no lock
                os.close(fd)
                raise OSError(errno.EINVAL, f"{self.path} is not a regular file")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._read_record(fd)
                os.close(fd)
                raise RunLockedError(
                    f"{self.folder} is being written by another process ({describe_holder(holder)}); "
                    "wait for it to finish, or use another --out"
                ) from None
            except OSError as exc:
                if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    os.close(fd)
                    raise
                self.unsupported = True
            try:
                current = os.stat(self.path)
                mine = os.fstat(fd)
                same = (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino)
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)  # released and removed between our open and our flock: again
        previous = self._read_record(fd)
        if previous is not None:
            host = previous.get("host")
            if host and host != socket.gethostname():
                os.close(fd)
                raise RunLockedError(
                    f"{self.folder} has a writer lock from another host ({describe_holder(previous)}); "
                    f"this host cannot tell whether that process still runs. If it does not, delete "
                    f"{self.path} and try again"
                )
            if self.unsupported and previous.get("pid") != os.getpid() and _pid_alive(previous.get("pid")):
                os.close(fd)
                raise RunLockedError(
                    f"{self.folder} is being written by another process ({describe_holder(previous)}; "
                    "this filesystem does not support locks, so only its record says so); wait for "
                    f"it to finish, or use another --out"
                )
            self.stale = previous
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started_at": datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": sys.argv,
        }
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    def stale_message(self) -> str | None:
        """One line about the dead holder this lock was taken over from, if any."""
        if self.stale is None:
            return None
        pid = self.stale.get("pid")
        gone = "no longer runs" if not _pid_alive(pid) else "no longer holds it (its pid was reused)"
        return f"{self.folder}: taking over a stale writer lock ({describe_holder(self.stale)}): that process {gone}"

    def release(self, keep_stale: bool = False) -> None:
        """keep_stale: put back the record of the dead holder this lock was taken over from,
        and leave the file, so that a process that held the lock only to tidy up (a reader
        removing temporaries) does not take from the next writer the line saying that a
        writer was killed."""
        if self._fd is None:
            return
        try:
            if keep_stale and self.stale is not None:
                os.ftruncate(self._fd, 0)
                os.pwrite(self._fd, (json.dumps(self.stale) + "\n").encode(), 0)
            else:
                self.path.unlink(missing_ok=True)  # still locked: nobody takes the old file
        finally:
            os.close(self._fd)
            self._fd = None
