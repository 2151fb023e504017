"""One process a folder: an exclusive lock on a run folder, a population folder or a sweep's ``--out``.

Two processes that train into one folder (two ``ablate --resume`` of it, a resume while the original still runs,
two ``ablate-sweep`` drivers on one ``--out``) would interleave their metrics lines and set each other's live lines
aside. :class:`FolderLock` takes ``fcntl.flock`` on ``<folder>/.lock``, which the kernel releases when the holder
dies (a killed process leaves no stale lock to clear by hand); the holder's pid, host and start time are written
into the file only so that the refusal can name it. The file is removed when the lock is released, so that the
folder cleanups that ``rmdir`` an empty folder still find it empty, and its name starts with a dot, so that a sweep
packing a folder for transfer leaves it behind (``ablations.sweep.transfer``).
"""

from __future__ import annotations

import datetime
import errno
import fcntl
import os
import socket
import sys
from collections.abc import Iterable
from pathlib import Path

__all__ = ["LOCK", "FolderBusy", "FolderLock", "FolderLocks"]

#: The lock file's name inside the folder it locks.
LOCK = ".lock"


class FolderBusy(ValueError):
    """Another live process holds the folder's lock (the message: one line naming the folder and the holder)."""


class FolderLock:
    """The exclusive lock of one folder, held from :meth:`acquire` to :meth:`release` (or this process's end)."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self.path = self.folder / LOCK
        self._fd: int | None = None

    def __repr__(self) -> str:
        return f"FolderLock({str(self.folder)!r}, held={self.held})"

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, what: str = "folder") -> FolderLock:
        """Take the lock (the folder must exist); FolderBusy naming the holder when another process has it.
        ``what`` names the folder in the refusal ("run folder", "sweep folder", ...)."""
        if self._fd is not None:
            return self
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                holder = _read(fd)
                os.close(fd)
                if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise FolderBusy(f"{what} {self.folder} is in use by another process ({holder}): wait for it to "
                                     f"end or stop it; one process at a time trains into a folder") from None
                print(f"warning: {self.path}: cannot lock the folder ({e}); nothing keeps a second process out of "
                      f"it", file=sys.stderr)
                return self
            # the holder before us may have removed the file between our open and our lock: then this lock is on
            # a file no one else will find, and the folder's lock file has to be opened again
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on host {socket.gethostname()}, since {started}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Give the lock up and remove its file (idempotent)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.unlink(self.path)  # while still held: a process waiting on this file then opens a new one
        except OSError:
            pass
        os.close(fd)

    def __del__(self) -> None:  # a lock dropped unreleased (an error between acquire and its owner's release)
        self.release()

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


class FolderLocks:
    """The locks of several folders (a population's folder and its members'), taken in order and given up together;
    a refusal of any releases those already taken."""

    def __init__(self) -> None:
        self.locks: list[FolderLock] = []

    def acquire(self, folders: Iterable[str | os.PathLike], what: str = "run folder") -> FolderLocks:
        for folder in folders:
            if any(lock.folder == Path(folder) for lock in self.locks):
                continue
            lock = FolderLock(folder)
            try:
                lock.acquire(what)
            except BaseException:
                self.release()
                raise
            self.locks.append(lock)
        return self

    def release(self) -> None:
        while self.locks:
            self.locks.pop().release()


def _read(fd: int) -> str:
    """The holder's line of a lock file (for the refusal)."""
    try:
        text = os.pread(fd, 200, 0).decode("utf-8", errors="replace").strip()
    except OSError:
        text = ""
    return text or "holder unknown"
