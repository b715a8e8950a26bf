"""The remote policy's own WebSocket client against the `websockets` library's server (the
one `dvla-harness serve` and openpi's servers run on) and against raw sockets that break
the protocol on purpose."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import pytest

pytest.importorskip("websockets")

from websockets.sync.server import serve

from policies.wsclient import ConnectionClosed, HandshakeRefused, ProtocolError, WebSocket


@contextmanager
def server(handle: Callable, **options) -> Iterator[str]:
    with serve(handle, "127.0.0.1", 0, compression=None, **options) as srv:
        thread = threading.Thread(target=srv.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"ws://127.0.0.1:{srv.socket.getsockname()[1]}"
        finally:
            srv.shutdown()
            thread.join(timeout=5)


def echo(ws) -> None:
    for message in ws:
        ws.send(message)


@pytest.mark.parametrize("size", [0, 1, 125, 126, 65535, 65536, 300_000])
def test_binary_messages_of_every_length_encoding_round_trip(size: int) -> None:
    payload = bytes(range(256)) * (size // 256) + bytes(size % 256)
    with server(echo) as url, WebSocket(url) as ws:
        ws.send(payload)
        assert ws.recv(timeout=5) == payload


def test_text_comes_back_as_str_and_fragments_are_joined() -> None:
    def handle(ws) -> None:
        ws.recv()
        ws.send("bad request: why")
        ws.send([b"ab", b"cd", b"ef"])  # an iterable: one message in three frames

    with server(handle) as url, WebSocket(url) as ws:
        ws.send(b"go")
        assert ws.recv(timeout=5) == "bad request: why"
        assert ws.recv(timeout=5) == b"abcdef"


def test_a_ping_is_answered_while_waiting_for_the_reply() -> None:
    def handle(ws) -> None:
        ws.recv()
        pong = ws.ping(b"are you there")
        ws.send(b"after the ping")
        ws.send(b"pong arrived" if pong.wait(timeout=5) else b"no pong")

    with server(handle) as url, WebSocket(url) as ws:
        ws.send(b"go")
        assert ws.recv(timeout=5) == b"after the ping"
        assert ws.recv(timeout=5) == b"pong arrived"


def test_a_server_that_keeps_pinging_and_never_replies_still_times_out() -> None:
    """The timeout is one deadline for the reply, not per read: pings every 0.1 s must
    not keep a call waiting past it."""
    stop = threading.Event()

    def handle(ws) -> None:
        ws.recv()
        while not stop.is_set():
            try:
                ws.ping()
            except Exception:
                return
            time.sleep(0.1)

    with server(handle) as url, WebSocket(url) as ws:
        ws.send(b"go")
        started = time.monotonic()
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.5)
        assert time.monotonic() - started < 2.0
        assert ws.closed
        stop.set()


def test_headers_reach_the_server_and_a_refused_handshake_names_its_status() -> None:
    from http import HTTPStatus

    seen: list[str] = []

    def process_request(connection, request):
        seen.append(request.headers.get("Authorization", ""))
        if request.headers.get("Authorization") != "Api-Key right":
            return connection.respond(HTTPStatus.UNAUTHORIZED, "no\n")
        return None

    with server(echo, process_request=process_request) as url:
        with WebSocket(url, headers={"Authorization": "Api-Key right"}) as ws:
            ws.send(b"x")
            assert ws.recv(timeout=5) == b"x"
        with pytest.raises(HandshakeRefused, match="401") as refused:
            WebSocket(url, headers={"Authorization": "Api-Key wrong"})
        assert refused.value.status == 401
    assert seen == ["Api-Key right", "Api-Key wrong"]


def test_the_servers_close_names_its_code_and_the_connection_is_then_closed() -> None:
    def handle(ws) -> None:
        ws.recv()
        ws.close(1011, "policy crashed")

    with server(handle) as url, WebSocket(url) as ws:
        ws.send(b"go")
        with pytest.raises(ConnectionClosed, match=r"1011 \(policy crashed"):
            ws.recv(timeout=5)
        assert ws.closed
        with pytest.raises(ConnectionClosed):
            ws.send(b"again")


def test_no_reply_is_a_timeout_not_a_hang_and_the_connection_is_dropped() -> None:
    def handle(ws) -> None:
        for _ in ws:
            pass  # never answers

    with server(handle) as url, WebSocket(url) as ws:
        ws.send(b"go")
        start = time.perf_counter()
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.3)
        assert time.perf_counter() - start < 3
        assert ws.closed  # a late reply must never be read as the next call's


def test_a_message_over_max_size_is_refused() -> None:
    def handle(ws) -> None:
        ws.recv()
        ws.send(bytes(1000))

    with server(handle) as url:
        ws = WebSocket(url, max_size=999)
        ws.send(b"go")
        with pytest.raises(ProtocolError, match="999-byte limit"):
            ws.recv(timeout=5)
        assert ws.closed


@contextmanager
def raw_server(reply: Callable[[bytes], bytes], trickle: bytes = b"", gap_s: float = 0.0) -> Iterator[str]:
    """A TCP server that reads the handshake and answers whatever `reply` makes of it,
    then sends `trickle` one byte every `gap_s` seconds (until the client hangs up)."""
    listener = socket.create_server(("127.0.0.1", 0))

    def run() -> None:
        conn, _ = listener.accept()
        request = b""
        while b"\r\n\r\n" not in request:
            request += conn.recv(4096)
        conn.sendall(reply(request))
        for byte in trickle:
            time.sleep(gap_s)
            try:
                conn.sendall(bytes([byte]))
            except OSError:
                break
        time.sleep(0.5)
        conn.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield f"ws://127.0.0.1:{listener.getsockname()[1]}"
    finally:
        thread.join(timeout=5)
        listener.close()


def accept_for(request: bytes) -> str:
    import base64
    import hashlib

    key = next(
        line.split(b":", 1)[1].strip()
        for line in request.split(b"\r\n")
        if line.lower().startswith(b"sec-websocket-key")
    )
    guid = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
    return base64.b64encode(hashlib.sha1(key + guid).digest()).decode()


def upgraded(request: bytes, extra: str = "") -> bytes:
    return (
        "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Accept: {accept_for(request)}\r\n{extra}\r\n"
    ).encode()


def test_a_wrong_accept_key_is_a_protocol_error() -> None:
    bogus = b"HTTP/1.1 101 Switching Protocols\r\nSec-WebSocket-Accept: AAAA\r\n\r\n"
    with raw_server(lambda request: bogus) as url, pytest.raises(ProtocolError, match="Accept"):
        WebSocket(url)


def test_an_extension_nobody_offered_is_a_protocol_error() -> None:
    reply = lambda request: upgraded(request, "Sec-WebSocket-Extensions: permessage-deflate\r\n")  # noqa: E731
    with raw_server(reply) as url, pytest.raises(ProtocolError, match="extension"):
        WebSocket(url)


def test_a_masked_frame_from_the_server_is_a_protocol_error() -> None:
    masked = bytes([0x82, 0x80 | 2]) + b"\x01\x02\x03\x04" + b"\x00\x00"
    with raw_server(lambda request: upgraded(request) + masked) as url:
        ws = WebSocket(url)
        with pytest.raises(ProtocolError, match="masked"):
            ws.recv(timeout=5)


def test_a_server_that_drops_the_socket_without_a_close_frame() -> None:
    half = bytes([0x82, 10]) + b"only4"
    with raw_server(lambda request: upgraded(request) + half) as url:
        ws = WebSocket(url)
        with pytest.raises(ConnectionClosed, match="no close frame"):
            ws.recv(timeout=5)


def test_a_reply_trickled_inside_one_frame_still_times_out() -> None:
    """The deadline bounds the whole reply, not each read: a server that sends one byte
    of a frame every 0.1 s (each read answered well within the timeout) is cut off."""
    header = bytes([0x82, 60])  # a final binary frame of 60 bytes: 6 s at this pace
    with raw_server(lambda request: upgraded(request) + header, trickle=b"x" * 60, gap_s=0.1) as url:
        ws = WebSocket(url)
        started = time.monotonic()
        with pytest.raises(TimeoutError, match=r"no reply within 0\.8 s"):
            ws.recv(timeout=0.8)
        assert time.monotonic() - started < 2.0 and ws.closed
