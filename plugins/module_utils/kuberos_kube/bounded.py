"""Remote reads with bounds: an overall deadline over a whole request (connect, headers, body), not only a timeout per
socket read, and a size cap on the answer. Used by the Kubernetes layer for clusters it does not run (a third-party
cluster, the metrics API) and by the registry client (``kuberos_deploy/registry_api.py``).

A ``Deadline`` is a watchdog: when its time is up it shuts down the sockets registered with it, which ends any read
blocked on them at once (an answer that trickles one byte a minute ends there), and marks itself expired so the
caller says why. ``read_capped`` reads an answer in pieces and stops at the cap. Both fail with ``ReadBoundExceeded``,
whose message is one sentence naming the host and the limit.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time

CHUNK = 64 * 1024


class ReadBoundExceeded(RuntimeError):
    """A remote answer exceeded its size cap or its deadline; the message names the host and the limit."""


def mib(size: int) -> str:
    return f"{size / (1024 * 1024):g} MiB" if size >= 1024 * 1024 else f"{size // 1024} KiB"


class Deadline:
    """A watchdog over one request to ``host``: ``remaining()`` seconds, sockets shut down when time is up."""

    def __init__(self, host: str, seconds: float, clock=time.monotonic):
        self.host = host
        self.seconds = float(seconds)
        self._clock = clock
        self._end = clock() + self.seconds
        self._sockets: list = []
        self._lock = threading.Lock()
        self.expired = False
        self._timer = threading.Timer(max(0.0, self.seconds), self._expire)
        self._timer.daemon = True

    def __enter__(self) -> Deadline:
        self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self._timer.cancel()

    def remaining(self) -> float:
        """Seconds left (at least a sliver, so a socket timeout is never 0, which would mean non-blocking)."""
        left = self._end - self._clock()
        if left <= 0:
            self._expire()
            raise self.error()
        return max(left, 0.001)

    def watch(self, sock) -> None:
        """Shut ``sock`` down when time is up (at once if it is already)."""
        with self._lock:
            self._sockets.append(sock)
            expired = self.expired
        if expired:
            _shut(sock)

    def _expire(self) -> None:
        with self._lock:
            self.expired = True
            sockets, self._sockets = self._sockets, []
        for sock in sockets:
            _shut(sock)

    def error(self) -> ReadBoundExceeded:
        return ReadBoundExceeded(f"{self.host} gave no complete answer within {self.seconds:g} s (the deadline of one request)")

    def check(self) -> None:
        """Raise the deadline's error when it expired (after a read that a shut-down socket ended)."""
        if self.expired:
            raise self.error()


def _shut(sock) -> None:
    with contextlib.suppress(OSError, AttributeError):
        sock.shutdown(socket.SHUT_RDWR)


def too_large(host: str, cap: int) -> ReadBoundExceeded:
    return ReadBoundExceeded(f"{host} answered with more than {mib(cap)} (the size limit of one answer)")


def exchange(connection, deadline: Deadline, method: str, target: str, where: str, cap: int, body=None,
             headers: dict | None = None) -> tuple:  # fmt: skip
    """One request on an ``http.client`` connection under ``deadline``: connected, its socket watched, the answer
    read up to ``cap`` (none for a HEAD: its Content-Length is what a GET would send, a blob's size). (status,
    headers, body bytes)."""
    connection.connect()
    deadline.watch(connection.sock)
    connection.request(method, target, body=body, headers=headers or {})
    response = connection.getresponse()
    data = b"" if method == "HEAD" else read_capped(response, where, cap, deadline)
    return response.status, response.headers, data


def read_capped(response, host: str, cap: int, deadline: Deadline | None = None) -> bytes:
    """The whole body of ``response`` (an http.client or urllib3 response), at most ``cap`` bytes: a declared
    Content-Length over the cap is refused before reading; else it is read in pieces up to the cap."""
    headers = getattr(response, "headers", None) or {}
    with contextlib.suppress(TypeError, ValueError):
        if int(headers.get("Content-Length") or 0) > cap:
            raise too_large(host, cap)
    if not hasattr(response, "read1"):  # a response already read whole (a test's stand-in)
        data = response.data
        if len(data) > cap:
            raise too_large(host, cap)
        return data
    pieces, size = [], 0
    while True:
        if deadline is not None:
            deadline.remaining()
        try:
            piece = response.read1(CHUNK)
        except Exception:
            if deadline is not None:
                deadline.check()
            raise
        if not piece:
            if deadline is not None:
                deadline.check()
            return b"".join(pieces)
        size += len(piece)
        if size > cap:
            raise too_large(host, cap)
        pieces.append(piece)
