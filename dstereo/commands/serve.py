"""`dstereo serve`: keep dstereo loaded so that each `dstereo` command skips the ~1-2 s of start-up.

The machinery is in runtime/server.py (the server) and dstereo/runtime/client.py (the entry point's client).
"""

from __future__ import annotations

import json
import time

import typer

STOP_WAIT_S = 600.0  # --stop waits for the running command to end, at most this long
STARTING_WAIT_S = 300.0  # --stop waits this long for a starting server to listen (a loaded 2-core machine)


def serve(
    stop: bool = typer.Option(False, "--stop", help="Stop the running server (after its current command)."),
    status: bool = typer.Option(False, "--status", help="Say whether a server runs, and what it has done."),
    idle_timeout: float = typer.Option(0.0, "--idle-timeout", min=0.0,
                                       help="Stop after this many seconds without a command (0: never)."),
    started_by: int = typer.Option(0, "--started-by", hidden=True, min=0),  # runtime/autostart.py: the client's pid
) -> None:
    """Run a resident server in the foreground: JAX, the commands and the figure workers load once, then every
    `dstereo` command (but serve and demo) started by this user from this installation with the same dstereo code
    and start-up settings runs in it, one at a time, with the same output, files and exit code. Without a server,
    the first such command starts one in the background that stops after 15 min without a command
    (DSTEREO_SERVE_IDLE seconds). DSTEREO_SERVE=0 runs a command in its own process and starts none;
    DSTEREO_SERVE=manual starts none. The socket is in $DSTEREO_SERVE_DIR, else $XDG_RUNTIME_DIR/dstereo, else
    ~/.cache/dstereo/serve."""
    from dstereo.runtime import client as wire
    from dstereo.errors import DstereoError

    if stop and status:
        raise DstereoError("--stop and --status: give one of them")
    path = wire.socket_path()
    if stop or status:
        state = ask(path, "stop" if stop else "status")
        if state is None and stop:
            state = _stop_starting(path)
        if state is None:
            typer.echo(f"dstereo serve: no server at {path}")
            if status:
                raise typer.Exit(1)
            return
        if status:
            typer.echo(describe(path, state))
            return
        _wait_gone(path)
        typer.echo(f"dstereo serve: stopped the server at {path} (pid {state['pid']})")
        return
    from dstereo.runtime.server import Server

    Server(path, idle_timeout, started_by).run()


def _stop_starting(path: str) -> dict | None:
    """`--stop` while a server is starting (it holds the installation's lock but does not listen yet: JAX and the
    figure workers are loading): wait until it answers, then stop it, rather than report "no server" and leave it
    running for its idle time. None where no server holds the lock, or none answered within STARTING_WAIT_S."""
    from dstereo.runtime import autostart
    from dstereo.runtime import client as wire

    deadline = time.monotonic() + STARTING_WAIT_S
    said = False
    while autostart.lock_taken(wire.sibling(path, ".lock")) and time.monotonic() < deadline:
        state = ask(path, "stop")
        if state is not None:
            return state
        if not said:
            typer.echo("dstereo serve: a server is starting; waiting to stop it", err=True)
            said = True
        time.sleep(0.2)
    return None


def describe(path: str, state: dict) -> str:
    """`serve --status`: where, its memory, age and commands, and whether (else why not) it serves this dstereo."""
    from dstereo.runtime import client as wire

    age = time.time() - state["since"]
    mib = (state.get("rss", 0) + state.get("children_rss", 0)) / 2**20
    lines = [f"dstereo serve: running at {path}, pid {state['pid']}, up {_duration(age)}, "
             f"{'busy' if state['busy'] else 'idle'}, memory {mib:.0f} MiB (RSS with its figure workers)"]
    if state.get("idle_timeout"):
        lines.append(f"  stops after {_duration(state['idle_timeout'])} without a command")
    history = state.get("history") or []
    lines.append(f"  {state['served']} command(s) served" + (":" if history else ""))
    for item in history:
        lines.append(f"    {time.strftime('%H:%M:%S', time.localtime(item['at']))}  {item['command']}  exit "
                     f"{item['code']}  {item['seconds']:.2f} s")
    if state["key"] == wire.code_key():
        lines.append("  its code, start-up settings and libraries are the same as this dstereo's")
    else:
        why = wire.differences(wire.key_parts(), state["parts"]) if "parts" in state else "an older server"
        lines.append(f"  its code, start-up settings or libraries are NOT the same as this dstereo's ({why}): "
                     "commands run in their own process")
    return "\n".join(lines)


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    if seconds < 120:
        return f"{seconds} s"
    if seconds < 7200:
        return f"{seconds // 60} min"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"


def ask(path: str, op: str) -> dict | None:
    from dstereo.runtime import client as wire

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
