"""Raw byte access to a bus port without any SDK: tests and tools check packets byte for byte."""

from __future__ import annotations

import os
import select
import time
import tty


class RawPort:
    """The host side of the pty without any SDK: write bytes, read replies."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.fd)

    def close(self) -> None:
        os.close(self.fd)

    def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    def receive(self, n: int, timeout: float = 2.0) -> bytes:
        """Up to `n` bytes, waiting (in select) at most `timeout` seconds for them."""
        out = b""
        deadline = time.monotonic() + timeout
        while len(out) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            ready, _, _ = select.select([self.fd], [], [], remaining)
            if ready:
                out += os.read(self.fd, n - len(out))
        return out

    def exchange(self, data: bytes, n: int, timeout: float = 2.0) -> bytes:
        self.send(data)
        return self.receive(n, timeout)
