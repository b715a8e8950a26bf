"""What a loopback round trip costs before any policy code: raw TCP against websockets.

benchmarks/remote.py measures the remote policy's transport per call (the call's time
minus the server's own policy time). This script finds the floor under it: an echo
server that answers a remote-policy-sized message with a reply of the same size as the
decoder's, after spinning for `--compute-ms` (the policy's compute, during which the
client waits), over raw TCP and over websockets with its sync and asyncio servers and
clients, and the remote policy's own client (policies/wsclient.py, `raw` below) against
both servers. Each server runs in its own process, as `dvla-harness serve` does.

    python benchmarks/transport_floor.py [--compute-ms 0,23] [--calls 80] [--rounds 5]

The table gives the median overhead per round trip (total minus the compute), per
combination and compute time, the median over rounds; the JSON keeps every round.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from policies.wire import pack, unpack  # noqa: E402

MESSAGE = pack({"prompt": "reach the goal", "state": np.zeros(39, np.float32)})
REPLY = pack({"actions": np.zeros((8, 4), np.float32), "dvla/nfe": 10, "dvla/policy_time_s": 0.02})


def spin(seconds: float) -> None:
    """Busy compute, as a decoder's forward passes are (a sleep would add its own wake-up)."""
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        pass


def serve(kind: str, port: int, compute: float) -> None:
    if kind == "tcp":
        listener = socket.create_server(("127.0.0.1", port))
        conn, _ = listener.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        while conn.recv(65536):
            spin(compute)
            conn.sendall(REPLY)
    elif kind == "sync":
        from websockets.sync.server import serve as sync_serve

        def handle(ws) -> None:
            for message in ws:
                unpack(message)
                spin(compute)
                ws.send(REPLY)

        with sync_serve(handle, "127.0.0.1", port, compression=None) as server:
            server.serve_forever()
    else:
        from websockets.asyncio.server import serve as async_serve

        async def handle(ws) -> None:
            async for message in ws:
                unpack(message)
                spin(compute)
                await ws.send(REPLY)

        async def main() -> None:
            async with async_serve(handle, "127.0.0.1", port, compression=None) as server:
                await server.serve_forever()

        asyncio.run(main())


def round_trips(kind: str, port: int, calls: int) -> list[float]:
    """Seconds per call (compute included), after 10 warm-up calls."""
    times: list[float] = []
    if kind == "tcp":
        conn = socket.create_connection(("127.0.0.1", port))
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for _ in range(calls + 10):
            start = time.perf_counter()
            conn.sendall(MESSAGE)
            conn.recv(65536)
            times.append(time.perf_counter() - start)
        conn.close()
    elif kind == "sync":
        from websockets.sync.client import connect

        with connect(f"ws://127.0.0.1:{port}", compression=None) as ws:
            for _ in range(calls + 10):
                start = time.perf_counter()
                ws.send(MESSAGE)
                unpack(ws.recv())
                times.append(time.perf_counter() - start)
    elif kind == "raw":  # the remote policy's own client (policies/wsclient.py)
        from policies.wsclient import WebSocket

        with WebSocket(f"ws://127.0.0.1:{port}") as ws:
            for _ in range(calls + 10):
                start = time.perf_counter()
                ws.send(MESSAGE)
                unpack(ws.recv())
                times.append(time.perf_counter() - start)
    else:
        from websockets.asyncio.client import connect as async_connect

        loop = asyncio.new_event_loop()
        ws = loop.run_until_complete(async_connect(f"ws://127.0.0.1:{port}", compression=None))

        async def call() -> None:
            await ws.send(MESSAGE)
            unpack(await ws.recv())

        for _ in range(calls + 10):
            start = time.perf_counter()
            loop.run_until_complete(call())
            times.append(time.perf_counter() - start)
        loop.run_until_complete(ws.close())
        loop.close()
    return times[10:]


COMBINATIONS = [
    ("tcp", "tcp"),
    ("sync", "sync"),
    ("sync", "async"),
    ("sync", "raw"),
    ("async", "sync"),
    ("async", "async"),
    ("async", "raw"),
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--compute-ms", default="0,23", help="server compute per call, ms (default 0,23)")
    parser.add_argument("--calls", type=int, default=80, help="timed calls per round (default 80)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds, interleaved (default 5)")
    parser.add_argument("--json", default="benchmarks/results/transport_floor.json")
    args = parser.parse_args()
    results: dict[str, list[float]] = {}
    for compute_ms in [float(x) for x in args.compute_ms.split(",")]:
        servers = {}
        for server_kind in ("sync", "async"):
            port = free_port()
            servers[server_kind] = (
                port,
                subprocess.Popen(
                    [sys.executable, __file__, "--serve", server_kind, str(port), str(compute_ms)]
                ),
            )
        time.sleep(1.5)
        try:
            for _ in range(args.rounds):
                for server_kind, client_kind in COMBINATIONS:
                    if server_kind == "tcp":  # a fresh raw server per round: it serves one connection
                        port = free_port()
                        proc = subprocess.Popen(
                            [sys.executable, __file__, "--serve", "tcp", str(port), str(compute_ms)]
                        )
                        time.sleep(0.5)
                    else:
                        port, proc = servers[server_kind][0], None
                    times = round_trips(client_kind, port, args.calls)
                    if proc is not None:
                        proc.wait(timeout=10)
                    key = f"server {server_kind} / client {client_kind} / compute {compute_ms:g} ms"
                    overhead = statistics.median(times) * 1000 - compute_ms
                    results.setdefault(key, []).append(round(overhead, 3))
        finally:
            for _, proc in servers.values():
                proc.terminate()
    print(f"{'round trip':52} median overhead ms (rounds)")
    for key, rounds in results.items():
        print(f"{key:52} {statistics.median(rounds):7.3f}  {rounds}")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    machine = {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()}
    path.write_text(
        json.dumps({"benchmark": "transport_floor", "overhead_ms": results, "machine": machine}, indent=2)
        + "\n"
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--serve":
        serve(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]) / 1000)
    else:
        main()
