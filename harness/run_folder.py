"""Opening a run folder for writing: every reason to refuse the output path or folder
(raised before anything is written), its writer lock, what resuming it must match, and
what a killed writer left behind.

`harness.runner.run` calls `check_path`, then `open_run` under the lock; a folder that
cannot be written gives a `UsageError` (exit 2), a failed write a `HarnessError` (exit 3).
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd

from harness.config import ResolvedRun, build_config
from harness.errors import HarnessError, UsageError
from harness.manifest import build_manifest, now
from harness.resume import (
    adopt_moved_checkpoints,
    adopt_recorded_params,
    changed_checkpoints,
    config_changes,
    config_data,
)
from results.lock import RunLock, RunLockedError
from results.manifest_check import RESUME_FIELDS
from results.store import ResultsFileError, RunDir


def _writable_ancestor(path: Path) -> Path:
    probe = path.absolute()
    while not probe.exists():
        probe = probe.parent
    return probe


def check_output(out: Path, resume: bool, overwrite: bool) -> None:
    """Every reason to refuse the output folder, raised before anything is written."""
    check_path(out, resume, overwrite)
    run_dir = RunDir(out)
    if resume:
        if not run_dir.is_run():
            raise UsageError(f"--resume: {str(out)!r} is not a dvla-harness run folder (no manifest.json)")
    elif not run_dir.is_empty():
        if not overwrite:
            raise UsageError(
                f"output folder {str(out)!r} exists and is not empty; pass --resume to "
                "continue it or --overwrite to replace it"
            )
        foreign = run_dir.foreign_files()
        if foreign:
            more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
            raise UsageError(
                f"--overwrite: {str(out)!r} holds files dvla-harness did not write "
                f"({', '.join(foreign[:5])}{more}); refusing to delete it"
            )
        if not run_dir.is_run():
            raise UsageError(
                f"--overwrite: {str(out)!r} is not a dvla-harness run folder; refusing to delete it"
            )


def check_path(out: Path, resume: bool, overwrite: bool) -> None:
    """The reasons to refuse the output path that do not depend on what the folder holds
    (checked before its writer lock is taken; the rest, under it)."""
    if resume and overwrite:
        raise UsageError("--resume and --overwrite contradict each other; pick one")
    if overwrite and out.is_symlink():
        raise UsageError(
            f"--overwrite: {str(out)!r} is a symbolic link (to {os.readlink(out)!r}); refusing to "
            "delete through it; pass the folder itself"
        )
    if out.exists() and not out.is_dir():
        raise UsageError(f"output path {str(out)!r} exists and is not a folder")
    ancestor = _writable_ancestor(out)
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"output folder {str(out)!r} is not writable (no write access to {str(ancestor)!r})")


def io_error(folder: Path, doing: str, exc: OSError) -> HarnessError:
    """One line for a failed write to the run folder; a full disk says so, with the free space."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        what = "the disk is full" if exc.errno == errno.ENOSPC else "the disk quota is exceeded"
        try:
            free = f"{shutil.disk_usage(folder).free / 1e6:.1f} MB free"
        except OSError:
            free = "free space unknown"
        return HarnessError(
            f"{folder}: {what} ({free}) while {doing}; rows recorded before are kept; "
            "free some space, then continue with --resume"
        )
    return HarnessError(f"{folder}: I/O error while {doing}: {exc}; rows recorded before are kept")


def acquire(lock: RunLock) -> None:
    """Take the run folder's writer lock, or refuse (exit 2) naming the process that holds it."""
    try:
        lock.acquire()
    except RunLockedError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot lock {str(lock.folder)!r}: {exc}") from None


def open_run(
    resolved: ResolvedRun, out: Path, resume: bool, overwrite: bool, lock: RunLock
) -> tuple[RunDir, str, pd.DataFrame]:
    """Create or reopen the run folder under its writer lock (taken here if the folder is
    new); returns it, the run id and the rows recorded so far."""
    check_output(out, resume, overwrite)
    run_dir = RunDir(out)
    if not lock.held:
        try:
            run_dir.create()
        except OSError as exc:
            raise UsageError(f"cannot create output folder {str(out)!r}: {exc}") from None
        acquire(lock)
        check_output(out, resume, overwrite)  # another process may have written it meanwhile
    if resume:
        try:
            manifest = run_dir.read_manifest(required=RESUME_FIELDS)
            recorded = run_dir.read_episodes()
        except ResultsFileError as exc:
            raise UsageError(f"--resume: {exc}") from None
        changes, extended = config_changes(manifest, resolved)
        if changes:
            raise UsageError(
                f"--resume: {str(out)!r} belongs to a different config ({'; '.join(changes)}); "
                "use another --out, or --overwrite to replace it"
            )
        suites = sorted(set(recorded["suite"]) - {resolved.suite.name}) if len(recorded) else []
        if suites:
            raise UsageError(
                f"--resume: {str(out)!r} holds rows of suite {suites[0]!r}, this config now resolves to "
                f"{resolved.suite.name!r} (a changed default, e.g. LIBERO's seeding); resuming would "
                "mix the two. Name the old one in --suite, or use another --out"
            )
        notices = adopt_recorded_params(manifest, recorded, resolved)
        moved = adopt_moved_checkpoints(manifest, recorded, resolved)
        changed = changed_checkpoints(manifest, recorded, resolved)
        if changed:
            raise UsageError(
                f"--resume: {'; '.join(changed)}; the run's rows came from the old file, so "
                "restore it, or use another --out"
            )
    _take_over(run_dir, lock)
    if resume:
        manifest["resumed_at"].append(now())
        manifest["status"] = "running"
        if extended is not None:
            _extend(run_dir, manifest, extended)
        run_dir.write_manifest(manifest)
        run_dir.log_event("run_resumed", recorded=len(recorded))
        for notice in notices:
            _say(notice)
            run_dir.log_event("policy_params_matched_at_defaults", notice=notice)
        for notice in moved:
            _say(notice)
            run_dir.log_event("checkpoint_matched_at_another_path", notice=notice)
        return run_dir, manifest["run_id"], recorded
    if overwrite and not run_dir.is_empty():
        run_dir.remove_recorded()  # only what the harness wrote: check_output refused others
    run_id = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]
    run_dir.create()
    run_dir.write_manifest(build_manifest(resolved, run_id))
    run_dir.log_event("run_started", run_id=run_id)
    return run_dir, run_id, pd.DataFrame()


def _extend(run_dir: RunDir, manifest: dict[str, Any], counts: tuple[int | None, int | None]) -> None:
    """Record that a resumed run now covers more episodes per task (harness.resume says
    why that is safe): the manifest's config says the new count, and the change is kept."""
    before, after = counts
    config = build_config(config_data(manifest["config"]))
    manifest["config"]["episodes_per_task"] = after
    manifest["config_fingerprint"] = dataclasses.replace(config, episodes_per_task=after).fingerprint()
    manifest.setdefault("extended", []).append({"at": now(), "episodes_per_task": [before, after]})
    run_dir.log_event("run_extended", episodes_per_task=[before, after])
    shown = "the whole protocol" if after is None else f"{after} episodes per task"
    _say(
        f"--resume: extending the run from {before} to {shown}; the recorded episodes are kept "
        "(an episode is fixed by its index in the protocol) and only the new ones run"
    )


def _say(line: str) -> None:
    from harness.console import err_console

    err_console.print(line, markup=False, highlight=False, soft_wrap=True)


def _take_over(run_dir: RunDir, lock: RunLock) -> None:
    """What a killed writer left behind, cleared before this one writes: a stale lock
    (said in one line), temporary files, a last line cut off mid-write (see RunDir.repair)."""
    from harness.console import err_console

    stale = lock.stale_message()
    if stale:
        err_console.print(stale, markup=False, highlight=False, soft_wrap=True)
    removed = run_dir.remove_temporaries()
    if run_dir.is_run():
        if stale:
            run_dir.log_event("stale_lock_taken_over", holder=lock.stale)
        if removed:
            run_dir.log_event("temporaries_removed", files=removed)
        run_dir.repair()
