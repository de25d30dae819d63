"""Slow clients on loopback: connections that send a request head one byte at a time and
never finish it (a slowloris). Used by tests/backend/test_slow_clients.py and
benchmarks/slow_clients.py.

One thread sends a byte on each connection every `every_s`; a connection the service
closed (the socket reads EOF or errors) is counted in `dropped` and, with `reconnect`,
replaced, as an attacker who wants to keep `count` connections would do.
"""

from __future__ import annotations

import select
import socket
import threading
from collections.abc import Callable
from types import TracebackType

# A head that never ends: a header value the service keeps reading byte by byte.
HEAD_START = b"GET /v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "


class Dribblers:
    """`count` connections to (host, port), each sending a never-ending request head."""

    def __init__(self, host: str, port: int, count: int, every_s: float = 0.05,
                 reconnect: bool = True) -> None:
        self.address, self.count, self.every_s = (host, port), count, every_s
        self.reconnect = reconnect
        self.dropped = 0  # connections the service closed
        self.sent = 0  # bytes sent over all connections
        self._sockets: list[socket.socket] = []
        self._stop = threading.Event()
        self._round = threading.Condition()  # notified after every round of sends
        self._thread = threading.Thread(target=self._loop, name="dribblers", daemon=True)

    def __enter__(self) -> Dribblers:
        self._sockets = [self._connect() for _ in range(self.count)]
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join(timeout=30)
        for sock in self._sockets:
            sock.close()

    @property
    def open(self) -> int:
        """Connections now held (neither dropped nor closed)."""
        return sum(sock.fileno() >= 0 for sock in self._sockets)

    def wait_until(self, done: Callable[[Dribblers], bool], timeout: float) -> bool:
        """Whether `done(self)` held after some round within `timeout` seconds."""
        with self._round:
            return self._round.wait_for(lambda: done(self), timeout)

    def _connect(self) -> socket.socket:
        sock = socket.create_connection(self.address, timeout=10)
        sock.setblocking(False)
        sock.send(HEAD_START[:1])
        self.sent += 1
        return sock

    def _closed_by_peer(self) -> set[socket.socket]:
        live = [s for s in self._sockets if s.fileno() >= 0]
        readable, _, _ = select.select(live, [], [], 0) if live else ([], [], [])
        closed = set()
        for sock in readable:
            try:
                if not sock.recv(4096):
                    closed.add(sock)
            except OSError:
                closed.add(sock)
        return closed

    def _loop(self) -> None:
        offsets = [1] * len(self._sockets)  # bytes of the head each connection has sent
        while not self._stop.wait(self.every_s):
            for sock in self._closed_by_peer():
                self.dropped += 1
                sock.close()
            for k, sock in enumerate(self._sockets):
                if sock.fileno() < 0:
                    if not self.reconnect:
                        continue
                    try:
                        sock = self._sockets[k] = self._connect()
                    except OSError:
                        continue
                    offsets[k] = 1
                try:
                    sock.send(HEAD_START[offsets[k]:offsets[k] + 1] or b"a")
                except OSError:  # reset: seen as closed on the next round
                    continue
                offsets[k] += 1
                self.sent += 1
            with self._round:
                self._round.notify_all()
