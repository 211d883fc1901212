"""`dstereo serve`: keep dstereo loaded so that each `dstereo` command skips the ~1-2 s of start-up.

The machinery is in serve_server.py (the server) and dstereo/serve_client.py (the entry point's client).
"""

from __future__ import annotations

import json
import time

import typer

STOP_WAIT_S = 600.0  # --stop waits for the running command to end, at most this long


def serve(
    stop: bool = typer.Option(False, "--stop", help="Stop the running server (after its current command)."),
    status: bool = typer.Option(False, "--status", help="Say whether a server runs, and what it has done."),
    idle_timeout: float = typer.Option(0.0, "--idle-timeout", min=0.0,
                                       help="Stop after this many seconds without a command (0: never)."),
    started_by: int = typer.Option(0, "--started-by", hidden=True, min=0),  # serve_autostart.py: the client's pid
) -> None:
    """Run a resident server in the foreground: JAX, the commands and the figure workers load once, then every
    `dstereo` command (but serve and demo) started by this user from this installation with the same dstereo code
    and start-up settings runs in it, one at a time, with the same output, files and exit code. Without a server,
    the first such command starts one in the background that stops after 15 min without a command
    (DSTEREO_SERVE_IDLE seconds). DSTEREO_SERVE=0 runs a command in its own process and starts none;
    DSTEREO_SERVE=manual starts none. The socket is in $DSTEREO_SERVE_DIR, else $XDG_RUNTIME_DIR/dstereo, else
    ~/.cache/dstereo/serve."""
    from dstereo import serve_client as wire
    from dstereo.errors import DstereoError

    if stop and status:
        raise DstereoError("--stop and --status: give one of them")
    path = wire.socket_path()
    if stop or status:
        state = ask(path, "stop" if stop else "status")
        if state is None:
            typer.echo(f"dstereo serve: no server at {path}")
            if status:
                raise typer.Exit(1)
            return
        if status:
            same = "the same as" if state["key"] == wire.code_key() else \
                "NOT the same as (commands run in their own process)"
            typer.echo(f"dstereo serve: running at {path}, pid {state['pid']}, up "
                       f"{time.time() - state['since']:.0f} s, {state['served']} command(s) served, "
                       f"{'busy' if state['busy'] else 'idle'}; its code and start-up settings are {same} this "
                       "dstereo's")
            return
        _wait_gone(path)
        typer.echo(f"dstereo serve: stopped the server at {path} (pid {state['pid']})")
        return
    from dstereo.commands.serve_server import Server

    Server(path, idle_timeout, started_by).run()


def ask(path: str, op: str) -> dict | None:
    from dstereo import serve_client as wire

    try:
        with wire.connect(path) as sock:
            wire.send(sock, b"q", json.dumps({"op": op}).encode())
            frame = wire.receive(sock)
    except OSError:
        return None
    return json.loads(frame[1]) if frame is not None and frame[0] == b"s" else None


def _wait_gone(path: str) -> None:
    import os

    deadline = time.monotonic() + STOP_WAIT_S
    while os.path.exists(path) and time.monotonic() < deadline:
        time.sleep(0.05)
