"""`dvla-harness serve`: a registered policy behind openpi's WebSocket policy protocol."""

from __future__ import annotations

import argparse
import signal

from harness.device import DEFAULT_DEVICE, DEVICES
from harness.errors import UsageError
from harness.plugins import install_hint

PROTOCOLS = ("openpi", "vla-eval")

EPILOG = """\
examples:
  dvla-harness serve --policy fast_dvla --suite metaworld/mt10 --port 8000
  DVLA_KEY=... dvla-harness serve --policy scripted --suite metaworld/mt1/reach-v3 --token-env DVLA_KEY
  dvla-harness serve --policy bidirectional:checkpoint=my.safetensors --suite metaworld/mt10 --host 0.0.0.0
  # one policy process for many env workers: their calls share one batched decode
  dvla-harness serve --policy fast_dvla --suite metaworld/mt10 --max-batch 8 --device cuda &
  dvla-harness run --suite metaworld/mt10 --policy remote:url=ws://127.0.0.1:8000 --workers 8
  # a vla-eval model server: `vla-eval run` evaluates the policy on its LIBERO benchmark
  dvla-harness serve --protocol vla-eval --policy MY_POLICY --suite "libero/spatial:obs=upstream,seeding=openpi"

Any openpi client can then connect (openpi-client's WebsocketClientPolicy, with
api_key=KEY when a key is set), read the server's metadata (the observation it
takes, the action it returns) and call infer({"state": ..., "prompt": ...}); each reply
holds "actions" (chunk x action dim) and the forward passes the call made ("dvla/nfe",
counted by the harness's own hooks) with the policy's time. The suite (and --task) fix
the observation and action spaces and the default episode; the simulator is built once
to read them. Binds 127.0.0.1 unless --host says otherwise. The key is read from an
environment variable (--token-env) or a file (--token-file), never from the command line
(other users of the machine see it there) and never printed.

--max-batch B (policies with act_batch: the five decoders) makes the server a shared
policy process: calls from different clients that arrive together are decoded in one
act_batch call of up to B observations, waiting at most --batch-wait-ms for more while
another active client (one that asked within 2 s) could still send one. Each reply
carries the call's passes (charged to each episode it served), its policy time and the
time the call waited in the queue. See docs/remote-policies.md.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="serve a policy over openpi's WebSocket protocol (msgpack + numpy)",
        description="Serve one registered policy to remote clients (openpi-client, dvla-harness's remote policy).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--policy", required=True, metavar="NAME[:k=v,...]", help="the policy to serve")
    p.add_argument("--suite", required=True, help="the suite whose observations and actions it serves")
    p.add_argument("--task", help="the task of the default episode (default: the suite's first)")
    p.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)"
    )
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one)")
    p.add_argument(
        "--token-env",
        metavar="NAME",
        help="require clients to send 'Authorization: Api-Key KEY', KEY read from this environment variable",
    )
    p.add_argument("--token-file", metavar="PATH", help="as --token-env, the key read from this file")
    p.add_argument("--token", help=argparse.SUPPRESS)  # refused with the reason (server_key)
    p.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default="openpi",
        help="openpi's WebSocket policy protocol (default), or vla-eval's model-server protocol "
        "(its `vla-eval run` drives the policy on its benchmarks; docs/remote-policies.md)",
    )
    p.add_argument("--state-key", default="state", help="the observation key of the state vector")
    p.add_argument(
        "--max-batch",
        type=int,
        default=1,
        metavar="B",
        help="decode concurrent clients' calls together, up to B observations a call (default 1: one at a time)",
    )
    p.add_argument(
        "--batch-wait-ms",
        type=float,
        default=5.0,
        metavar="MS",
        help="with --max-batch: longest wait for more calls once one is waiting (default 5)",
    )
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=DEFAULT_DEVICE,
        help="where a model policy decodes: cpu (default), cuda (refused without a GPU), auto (as run's --device)",
    )
    p.set_defaults(func=cmd_serve)


def server_key(args: argparse.Namespace) -> str | None:
    """The key clients must send, from --token-env or --token-file (None: no key)."""
    from policies.remote import read_api_key

    if getattr(args, "token", None) is not None:
        raise UsageError(
            "--token puts the key on the command line, where other users of the machine see it "
            "(ps) and shell history keeps it; pass --token-env NAME or --token-file PATH"
        )
    env, path = getattr(args, "token_env", None) or "", getattr(args, "token_file", None) or ""
    if env and path:
        raise UsageError("--token-env and --token-file are both given; pick one")
    try:
        return read_api_key(env, path, env_flag="--token-env", file_flag="--token-file") or None
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def build_served(args: argparse.Namespace, token: str | None = None):
    """The policy resolved as `run` resolves it (same registry, params, checkpoints), and
    the served task's spaces read from one env of the suite; `token`: the key clients
    must send (server_key)."""
    from harness.config import build_config, parse_policy_arg, resolve
    from harness.serving.server import Served

    data = {"suite": args.suite, "policy": [parse_policy_arg(args.policy)]}
    if args.task:
        data["tasks"] = [args.task]
    resolved = resolve(build_config(data))
    task = resolved.tasks[0]
    env = resolved.suite.make_env(task)
    try:
        observation_space, action_space = env.observation_space, env.action_space
    finally:
        env.close()
    p = resolved.policies[0]
    from harness.device import apply_device

    apply_device(resolved.policies, getattr(args, "device", DEFAULT_DEVICE))
    return Served(
        policy=p.policy,
        name=p.spec.name,
        params=p.params_json,
        suite=resolved.suite.name,
        task=task.name,
        instruction=task.instruction,
        max_steps=task.max_steps,
        observation_space=observation_space,
        action_space=action_space,
        state_key=args.state_key,
        token=token,
        max_batch=getattr(args, "max_batch", 1),
        batch_wait_s=getattr(args, "batch_wait_ms", 5.0) / 1000,
    )


def cmd_serve(args: argparse.Namespace) -> int:
    import importlib.util

    from harness.console import console, raise_interrupt

    if importlib.util.find_spec("websockets") is None or importlib.util.find_spec("msgpack") is None:
        raise UsageError(f"serve needs websockets and msgpack: {install_hint('remote')}")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be 0..65535, got {args.port}")
    if args.max_batch < 1:
        raise UsageError(f"--max-batch must be at least 1, got {args.max_batch}; 1 serves one call at a time")
    if not 0 <= args.batch_wait_ms <= 10_000:
        raise UsageError(f"--batch-wait-ms must be 0..10000, got {args.batch_wait_ms}")
    token = server_key(args)
    try:
        served = build_served(args, token)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    from harness.serving.server import make_server, stop_server

    dialect = None
    if getattr(args, "protocol", "openpi") == "vla-eval":
        from harness.serving import vlaeval

        try:
            vlaeval.mapping_for(served)
        except ValueError as exc:
            raise UsageError(f"--protocol vla-eval: {exc}") from None
        dialect = vlaeval.handler
    try:
        server = make_server(served, args.host, args.port, dialect, ping_interval=None if dialect else 20.0)
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}") from None
    host, port = server.socket.getsockname()[:2]
    console.print(
        f"serving {served.name} ({served.suite}, task {served.task}) on ws://{host}:{port}"
        + (" (token required)" if served.token else "")
        + (f" (batching up to {served.max_batch})" if served.max_batch > 1 else "")
        + (" (vla-eval's protocol)" if dialect is not None else "")
        + "; Ctrl-C stops",
        soft_wrap=True,  # one line, however long the task's name: scripts read the address from it
    )
    # Ctrl-C and SIGTERM (how services and CI stop a process) both stop it cleanly, also
    # where the shell that started it in the background left SIGINT ignored.
    signal.signal(signal.SIGINT, raise_interrupt)
    signal.signal(signal.SIGTERM, raise_interrupt)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        coalescer = served.coalescer
        if coalescer is not None and coalescer.calls:
            console.print(
                f"stopped: {coalescer.rows} observations in {coalescer.calls} calls "
                f"(mean batch {coalescer.rows / coalescer.calls:.2f})"
            )
        else:
            console.print("stopped")
    finally:
        stop_server(server)
    return 0
