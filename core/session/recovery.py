"""Crash recovery: the two-slot autosave of a session and which runs ended without cleaning up.

The GUI's :class:`CrashRecovery` writes the session after each edit (:meth:`CrashRecovery.write`)
and removes its files when the program closes normally (:meth:`CrashRecovery.clear`), so a
recovery file still there at the next start means that run did not exit cleanly. Each running
process autosaves into its own two files, ``recovery-<pid>-a.json`` and ``-b.json``, written in
turn (a complete one exists at every moment, and no rename replaces an existing file, which
ext4 follows with a synchronous flush), holding the session document of
:mod:`core.session.document` with the arrays packed as base64 (about 0.4 ms for 500 points).
They live in the state folder :func:`state_dir`. Two instances never overwrite each other;
:meth:`CrashRecovery.read` only offers files of processes that are no longer running, and
claims what it offers (renames it to this process's name), so it is offered once and then
kept up to date by this run's autosaves or cleared.

"No longer running" is not judged by the pid alone (a crashed run's pid may be a zombie, or
reused by another program). A writing process holds an exclusive lock on
``recovery-<pid>.lock`` (:class:`filelock.FileLock`: ``flock`` on POSIX, ``msvcrt.locking`` on
Windows, both released by the operating system when the process ends, zombie or not), so a
lock that can be taken means its writer is gone. For files without a lock file, psutil
decides: no such pid, a zombie, or a process whose creation time is not the one the writer
recorded (the pid was reused) all mean the writer has ended.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

import filelock
import platformdirs
import psutil

from core.session.document import Session, from_document, read_document, to_document

APP_NAME = "ssm-studio"
STATE_DIR_ENV = "SSM_STUDIO_STATE_DIR"
RECOVERY_PREFIX = "recovery-"
# Linux derives a process's creation time from the boot time, which the kernel may report a
# second apart over a long uptime (NTP); a pid reused within one second is not a practical case.
CREATE_TIME_TOLERANCE_S = 1.0


def state_dir() -> Path:
    """Per-user folder for recovery files and the recent-files list; not created here.

    ``$SSM_STUDIO_STATE_DIR`` if set, else the platform's per-user state folder
    (:func:`platformdirs.user_state_dir`): ``$XDG_STATE_HOME/ssm-studio`` (an absolute
    ``XDG_STATE_HOME`` only) or ``~/.local/state/ssm-studio`` on Linux,
    ``%LOCALAPPDATA%\\ssm-studio`` on Windows, ``~/Library/Application Support/ssm-studio`` on
    macOS.
    """
    override = os.environ.get(STATE_DIR_ENV)
    if override:
        return Path(override)
    return Path(platformdirs.user_state_dir(APP_NAME, appauthor=False))


def _slot_paths(folder: Path, pid: int) -> tuple[Path, Path]:
    return (folder / f"{RECOVERY_PREFIX}{pid}-a.json", folder / f"{RECOVERY_PREFIX}{pid}-b.json")


def _lock_path(folder: Path, pid: int) -> Path:
    return folder / f"{RECOVERY_PREFIX}{pid}.lock"


def _read_slot(path: Path) -> tuple[int, dict] | None:
    """(sequence, document) of a complete recovery slot, None if missing or unreadable."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        return int(doc["writer"]["sequence"]), doc
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _newest_slot(folder: Path, pid: int) -> Path | None:
    slots = [(read[0], path) for path in _slot_paths(folder, pid) if (read := _read_slot(path))]
    return max(slots)[1] if slots else None


def _pid_of(path: Path) -> int | None:
    stem = path.name[len(RECOVERY_PREFIX):].split("-")[0].split(".")[0]
    return int(stem) if stem.isdigit() else None


def _lock_says_running(folder: Path, pid: int) -> bool | None:
    """True/False from pid's lock file; None when there is none."""
    path = _lock_path(folder, pid)
    if not path.exists():
        return None
    lock = filelock.FileLock(path, thread_local=False)
    try:
        lock.acquire(blocking=False)
    except filelock.Timeout:
        return True
    except OSError:  # unreadable lock file: let the process table decide
        return None
    lock.release()
    path.unlink(missing_ok=True)  # its writer has ended
    return False


def writer_running(pid: int, created: float | None = None, folder: Path | None = None) -> bool:
    """Whether the process that wrote recovery files as ``pid`` is still running.

    Its held lock file (in ``folder``, default :func:`state_dir`) decides; else a missing
    process or a zombie has ended and, when the writer's creation time is known (seconds
    since the epoch, as :meth:`psutil.Process.create_time`), a process with that pid but
    another creation time is someone else.
    """
    if pid == os.getpid():
        return True
    if pid <= 0:
        return False
    locked = _lock_says_running(folder or state_dir(), pid)
    if locked is not None:
        return locked
    try:
        process = psutil.Process(pid)
        if process.status() in (psutil.STATUS_ZOMBIE, psutil.STATUS_DEAD):
            return False  # it has ended, nobody reaped it yet
        if created is not None and \
                abs(process.create_time() - created) > CREATE_TIME_TOLERANCE_S:
            return False  # the pid was reused by a later process
    except psutil.NoSuchProcess:  # psutil.ZombieProcess is one
        return False
    except psutil.AccessDenied:  # another user's process: it exists
        return True
    return True


def _writer_created(folder: Path, pid: int) -> float | None:
    """The creation time the newest complete recovery slot of ``pid`` recorded, if any.

    Files written before psutil (their ``started`` in clock ticks) have none: the pid and
    the lock decide for them."""
    slot = _newest_slot(folder, pid)
    read = _read_slot(slot) if slot is not None else None
    writer = read[1]["writer"] if read and isinstance(read[1].get("writer"), dict) else {}
    created = writer.get("created")
    if writer.get("pid") != pid:  # the file was not written by that pid: its time says nothing
        return None
    return float(created) if isinstance(created, (int, float)) and \
        not isinstance(created, bool) else None


def _orphan_pids(folder: Path) -> list[int]:
    """Processes that left recovery files in ``folder`` and no longer run, newest files first."""
    if not folder.is_dir():
        return []
    newest: dict[int, float] = {}
    for path in folder.glob(f"{RECOVERY_PREFIX}*.json*"):
        pid = _pid_of(path)
        if pid is None or pid == os.getpid():
            continue
        try:
            newest[pid] = max(newest.get(pid, 0.0), path.stat().st_mtime)
        except FileNotFoundError:  # claimed meanwhile by another instance
            continue
    return sorted((pid for pid in newest
                   if not writer_running(pid, _writer_created(folder, pid), folder)),
                  key=lambda pid: newest[pid], reverse=True)


def orphaned_recovery_files(folder: Path | None = None) -> list[Path]:
    """Recovery files left by runs that did not exit cleanly (not those of running ones)."""
    folder = folder or state_dir()
    return sorted(p for pid in _orphan_pids(folder)
                  for p in folder.glob(f"{RECOVERY_PREFIX}{pid}-*.json*"))


def previous_run_crashed(folder: Path | None = None) -> bool:
    """True when a run that has ended left a recovery file, i.e. it did not exit cleanly."""
    return bool(_orphan_pids(folder or state_dir()))


class CrashRecovery:
    """This process's autosave for crash recovery, in ``folder`` (default :func:`state_dir`,
    read when constructed). Holds the liveness lock from the first write to :meth:`clear`."""

    def __init__(self, folder: str | os.PathLike | None = None):
        self.folder = Path(folder) if folder is not None else state_dir()
        self.pid = os.getpid()
        self.created = psutil.Process(self.pid).create_time()  # recorded against pid reuse
        self._next_slot = 0  # which of the two slots the next autosave replaces
        self._lock = filelock.FileLock(_lock_path(self.folder, self.pid), thread_local=False)

    @property
    def path(self) -> Path:
        """This process's current recovery file (the newest of its two autosave slots)."""
        return _newest_slot(self.folder, self.pid) or _slot_paths(self.folder, self.pid)[0]

    def write(self, session: Session) -> Path:
        """Autosave ``session``; returns the file written.

        Two slots are written in turn: the new text goes to a temporary file, the older slot
        is removed and the temporary file takes its name, so a complete recovery file exists
        at every moment. (This avoids renaming over an existing file, which ext4 follows with
        a synchronous data flush of several ms; durability against power loss is not the
        point here, surviving a crash of the program is.) Paths are stored absolute.
        """
        doc = to_document(session, None, packed=True)
        doc["writer"] = {"pid": self.pid, "host": socket.gethostname(),
                         "sequence": time.time_ns(),
                         "created": self.created}
        text = json.dumps(doc, separators=(",", ":"))
        target = _slot_paths(self.folder, self.pid)[self._next_slot]
        target.parent.mkdir(parents=True, exist_ok=True)
        self._hold_lock()
        tmp = target.with_name(target.name + ".tmp")
        try:
            tmp.write_text(text, encoding="utf-8")
            target.unlink(missing_ok=True)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        self._next_slot = 1 - self._next_slot
        return target

    def _hold_lock(self) -> None:
        if self._lock.is_locked:
            return
        try:
            self._lock.acquire(blocking=False)
        except (filelock.Timeout, OSError):  # e.g. held by another object of this process:
            pass                             # the pid check covers this process

    def read(self) -> Session | None:
        """The newest session left by a run that did not exit cleanly, or None.

        Call it at start-up, before the first autosave. The left-over files are claimed
        (renamed to this process's slots), so they are offered only once; :meth:`clear`
        removes them (after a refusal, or at the next clean exit) and this run's autosaves
        replace them. Several crashed runs are offered one per start, newest first.

        Raises
        ------
        DataFileError
            The recovery file exists but cannot be read (it is claimed all the same, so that
            :meth:`clear` discards it).
        """
        own = _slot_paths(self.folder, self.pid)[0]
        for pid in _orphan_pids(self.folder):
            files = sorted(self.folder.glob(f"{RECOVERY_PREFIX}{pid}-*.json*"))
            keep = _newest_slot(self.folder, pid)
            if keep is None:  # only damaged files: claim one all the same, to report and clear it
                keep = next((f for f in files if f.suffix == ".json"), None)
            if keep is None:
                for path in files:
                    path.unlink(missing_ok=True)
                continue
            try:
                os.replace(keep, own)
            except FileNotFoundError:  # another instance claimed it first
                continue
            for path in files:
                if path != keep:
                    path.unlink(missing_ok=True)  # the older slot, or a half-written temporary
            self._next_slot = 1
            return from_document(read_document(own), own, None)
        return None

    def clear(self) -> None:
        """Remove this process's recovery files: on a clean exit, or after refusing recovery."""
        for path in _slot_paths(self.folder, self.pid):
            path.unlink(missing_ok=True)
            path.with_name(path.name + ".tmp").unlink(missing_ok=True)
        if self._lock.is_locked:
            self._lock.release()
            Path(self._lock.lock_file).unlink(missing_ok=True)
