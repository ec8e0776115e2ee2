"""An exclusive lock on an output directory, held for a whole run: ``DIR/.lock`` with ``fcntl.flock``.

The lock belongs to the open file description, so the kernel releases it when the holder exits,
however it exits (SIGKILL included): a lock is never stale. The file records the holder's host, pid
and start time for the message a refused writer gets. On NFS, Linux maps ``flock`` to POSIX byte-range
locks, which NFSv4 servers honour across hosts; on file systems without locking the store is only safe
with one writer at a time.
"""
from __future__ import annotations

import datetime
import errno
import fcntl
import json
import os
import socket
import time

LOCK_FILE = ".lock"


class Busy(RuntimeError):
    """Another process holds the directory's lock."""


class DirLock:
    """``with DirLock(dir, wait=False, what="sweep"):`` exclusive access to ``dir`` (see the module docstring).

    ``wait=False``: raise :class:`Busy` at once, naming the holder; ``wait=True``: block until it is free
    (polling every ``poll`` s, printing one line), ``timeout`` seconds at most (None: forever).
    """

    def __init__(self, directory: str, wait: bool = False, timeout: float | None = None, poll: float = 0.5,
                 what: str = "this directory"):
        self.dir = directory
        self.path = os.path.join(directory, LOCK_FILE)
        self.wait, self.timeout, self.poll, self.what = wait, timeout, poll, what
        self.fd: int | None = None

    def holder(self) -> str:
        try:
            with open(self.path) as f:
                h = json.loads(f.read() or "{}")
            return f"pid {h.get('pid', '?')} on {h.get('host', '?')} since {h.get('since', '?')}"
        except (OSError, ValueError):
            return "another process"

    def acquire(self) -> "DirLock":
        os.makedirs(self.dir, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        t0 = time.monotonic()
        told = False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as e:
                if e.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    os.close(fd)
                    raise
                if not self.wait or (self.timeout is not None and time.monotonic() - t0 > self.timeout):
                    who = self.holder()
                    os.close(fd)
                    raise Busy(f"{self.dir} is being written by {who} ({self.what}); wait for it to finish, "
                               f"add --wait to queue behind it, or use another --out directory") from None
                if not told:
                    print(f"waiting for {self.dir}: held by {self.holder()}", flush=True)
                    told = True
                time.sleep(self.poll)
        info = dict(pid=os.getpid(), host=socket.gethostname(),
                    since=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is not None:
            try:
                os.ftruncate(self.fd, 0)
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = None

    @property
    def held(self) -> bool:
        return self.fd is not None

    def __enter__(self) -> "DirLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
