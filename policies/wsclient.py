"""A small blocking WebSocket client (RFC 6455) for the remote policy.

Why not the `websockets` library's client: its sync client reads the socket on a
background thread and hands each message to the caller through a queue, so every reply
wakes two threads; after the tens of milliseconds a decoder computes, both are cold and
that hand-over alone put the loopback round trip at ~0.9 ms, against ~0.25 ms for raw TCP
(benchmarks/transport_floor.py). This client reads its reply on the calling thread, which
is all a policy call needs: one request, one reply, in order. It speaks only what the
policy protocol uses: binary and text messages (fragmented or not), ping/pong, close; no
extensions (the handshake offers none, so no server may use compression), no
subprotocols. Servers stay on `websockets`; this module needs only the standard library
and numpy.
"""

from __future__ import annotations

import base64
import hashlib
import os
import socket
import ssl
import struct
import time
from urllib.parse import urlsplit

import numpy as np

_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455 section 1.3
_CONTINUATION, _TEXT, _BINARY, _CLOSE, _PING, _PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA


class ProtocolError(ConnectionError):
    """The server broke the WebSocket protocol (or refused the handshake); the text says how."""


class ConnectionClosed(ConnectionError):
    """The server closed the connection (its close code and reason in the text)."""


class HandshakeRefused(ProtocolError):
    """The server answered the upgrade with another HTTP status (401: a wrong token)."""

    def __init__(self, status: int, text: str):
        super().__init__(text)
        self.status = status


def _mask(payload: bytes, key: bytes) -> bytes:
    """XOR with the 4-byte masking key (clients must mask, section 5.3)."""
    if not payload:
        return payload
    data = np.frombuffer(payload, np.uint8)
    keys = np.resize(np.frombuffer(key, np.uint8), data.size)
    return (data ^ keys).tobytes()


def frame(opcode: int, payload: bytes) -> bytes:
    """One final, masked client frame."""
    n = len(payload)
    if n < 126:
        header = struct.pack("!BB", 0x80 | opcode, 0x80 | n)
    elif n < 1 << 16:
        header = struct.pack("!BBH", 0x80 | opcode, 0x80 | 126, n)
    else:
        header = struct.pack("!BBQ", 0x80 | opcode, 0x80 | 127, n)
    key = os.urandom(4)
    return header + key + _mask(payload, key)


class WebSocket:
    """One client connection; `send` and `recv` block on the calling thread."""

    def __init__(
        self,
        url: str,
        headers: dict[str, str] | None = None,
        open_timeout: float = 10.0,
        max_size: int = 64 * 1024 * 1024,
    ):
        parts = urlsplit(url)
        if parts.scheme not in ("ws", "wss") or not parts.hostname:
            raise ValueError(f"not a ws:// or wss:// address: {url!r}")
        self.max_size = max_size
        port = parts.port or (443 if parts.scheme == "wss" else 80)
        sock = socket.create_connection((parts.hostname, port), timeout=open_timeout)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if parts.scheme == "wss":
            sock = ssl.create_default_context().wrap_socket(sock, server_hostname=parts.hostname)
        self._sock = sock
        self._reader = sock.makefile("rb")
        self._deadline: float | None = None  # when the reply being read must be whole (monotonic)
        self.closed = False
        try:
            self._handshake(parts, port, headers or {})
        except BaseException:
            self._drop()
            raise

    def _handshake(self, parts, port: int, headers: dict[str, str]) -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        host = parts.hostname if port in (80, 443) else f"{parts.hostname}:{port}"
        lines = [
            f"GET {parts.path or '/'}{'?' + parts.query if parts.query else ''} HTTP/1.1",
            f"Host: {host}",
            "Upgrade: websocket",
            "Connection: Upgrade",
            f"Sec-WebSocket-Key: {key}",
            "Sec-WebSocket-Version: 13",
            *(f"{name}: {value}" for name, value in headers.items()),
        ]
        self._sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        status_line = self._reader.readline(65536).decode("latin-1").strip()
        fields: dict[str, str] = {}
        while True:
            line = self._reader.readline(65536)
            if not line:
                raise ProtocolError("the server closed the connection during the handshake")
            if line in (b"\r\n", b"\n"):
                break
            name, _, value = line.decode("latin-1").partition(":")
            fields[name.strip().lower()] = value.strip()
        status = status_line.split(" ", 2)
        if len(status) < 2 or not status[1].isdigit():
            raise ProtocolError(f"not an HTTP reply to the upgrade: {status_line[:200]!r}")
        if status[1] != "101":
            raise HandshakeRefused(int(status[1]), f"server rejected WebSocket connection: HTTP {status[1]}")
        expected = base64.b64encode(hashlib.sha1(key.encode() + _GUID).digest()).decode()
        if fields.get("sec-websocket-accept") != expected:
            raise ProtocolError("the server's Sec-WebSocket-Accept does not match the key sent")
        if fields.get("sec-websocket-extensions"):
            raise ProtocolError(
                f"the server chose an extension none was offered: {fields['sec-websocket-extensions']}"
            )

    # --- messages --------------------------------------------------------------------

    def send(self, message: bytes | str) -> None:
        if self.closed:
            raise ConnectionClosed("the connection is closed")
        opcode = _TEXT if isinstance(message, str) else _BINARY
        payload = message.encode() if isinstance(message, str) else message
        try:
            self._sock.sendall(frame(opcode, payload))
        except OSError as exc:
            self._drop()
            raise ConnectionClosed(f"sending failed ({exc})") from None

    def recv(self, timeout: float | None = None) -> bytes | str:
        """The next data message; TimeoutError once `timeout` seconds pass without a whole
        one (the connection is then unusable: a late reply must not be read as the next
        one's)."""
        if self.closed:
            raise ConnectionClosed("the connection is closed")
        self._deadline = None if timeout is None else time.monotonic() + timeout
        parts: list[bytes] = []
        opcode_of_message = None
        size = 0
        try:
            while True:
                fin, opcode, payload = self._read_frame(self.max_size - size)
                if opcode >= _CLOSE:
                    self._control(opcode, payload)
                    continue
                if opcode == _CONTINUATION:
                    if opcode_of_message is None:
                        raise ProtocolError("a continuation frame with no message to continue")
                elif opcode in (_TEXT, _BINARY):
                    if opcode_of_message is not None:
                        raise ProtocolError("a new message began before the last one ended")
                    opcode_of_message = opcode
                else:
                    raise ProtocolError(f"unknown opcode {opcode}")
                parts.append(payload)
                size += len(payload)
                if fin:
                    data = b"".join(parts)
                    return data.decode() if opcode_of_message == _TEXT else data
        except TimeoutError:  # the socket's own ("timed out") or the deadline's
            self._drop()
            raise TimeoutError(f"no reply within {timeout} s") from None
        except (OSError, ValueError) as exc:
            if isinstance(exc, ConnectionError):
                self._drop()
                raise
            self._drop()
            raise ConnectionClosed(f"reading failed ({exc})") from None

    def _read_exactly(self, n: int) -> bytes:
        """n bytes, each read of the socket held to what is left of the reply's deadline:
        one deadline for the whole message, so a server that keeps pinging, or trickles a
        reply frame by frame or byte by byte, still times out."""
        parts: list[bytes] = []
        while n:
            if self._deadline is None:
                self._sock.settimeout(None)
            else:
                left = self._deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("the reply's deadline passed")
                self._sock.settimeout(left)
            data = self._reader.read1(n)  # what the buffer holds, else one read of the socket
            if not data:
                raise ConnectionClosed("the server closed the connection (no close frame)")
            parts.append(data)
            n -= len(data)
        return b"".join(parts)

    def _read_frame(self, room: int) -> tuple[bool, int, bytes]:
        first, second = self._read_exactly(2)
        if first & 0x70:
            raise ProtocolError("reserved bits set in a frame (no extension was agreed)")
        if second & 0x80:
            raise ProtocolError("the server masked a frame (servers must not, RFC 6455 5.1)")
        n = second & 0x7F
        if n == 126:
            (n,) = struct.unpack("!H", self._read_exactly(2))
        elif n == 127:
            (n,) = struct.unpack("!Q", self._read_exactly(8))
        opcode = first & 0x0F
        if opcode >= _CLOSE and (n > 125 or not first & 0x80):
            raise ProtocolError("a control frame longer than 125 bytes or fragmented")
        if n > room and opcode < _CLOSE:
            raise ProtocolError(f"a message over the {self.max_size}-byte limit")
        return bool(first & 0x80), opcode, self._read_exactly(n) if n else b""

    def _control(self, opcode: int, payload: bytes) -> None:
        if opcode == _PING:
            self._sock.sendall(frame(_PONG, payload))
        elif opcode == _CLOSE:
            code = struct.unpack("!H", payload[:2])[0] if len(payload) >= 2 else 1005
            reason = payload[2:].decode(errors="replace")
            try:
                self._sock.sendall(frame(_CLOSE, payload[:2]))
            except OSError:
                pass
            self._drop()
            raise ConnectionClosed(f"received {code} ({reason or 'no reason'})")
        elif opcode != _PONG:
            raise ProtocolError(f"unknown control opcode {opcode}")

    # --- closing ---------------------------------------------------------------------

    def close(self) -> None:
        """Say goodbye (close code 1000) and drop the socket; never raises."""
        if self.closed:
            return
        try:
            self._sock.settimeout(1.0)
            self._sock.sendall(frame(_CLOSE, struct.pack("!H", 1000)))
        except OSError:
            pass
        self._drop()

    def _drop(self) -> None:
        self.closed = True
        for thing in (self._reader, self._sock):
            try:
                thing.close()
            except OSError:
                pass

    def __enter__(self) -> WebSocket:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
