"""A compiled call that stops making progress ends the command with one line and exit 1, never a silent wait.

Why: a compiled XLA call cannot be cancelled from Python, and the one hang we met (two concurrent calls into
jaxlib's batched LAPACK kernels, each waiting on the other's threads: dstereo/solver/cholesky.py) sat at 0 % CPU
forever. The solver no longer calls those kernels, but a run must end even where the next such hang is not known.

How: every compiled solver call runs inside `watched(key, what)`. A daemon thread looks at the calls in flight
once a second; a call still running after `allowance(key)` — FACTOR times the longest call of the same `key`
(program and shapes) already finished in this process, at least FLOOR_S, or FIRST_S for a key with none finished
yet (its first call compiles or loads the program) — is abandoned: the command's staging folders are removed,
every child process is killed, the line below is written, and the process exits 1 (`interrupts.abandon`: a thread
stuck in native code never returns, so nothing can unwind it). A served command's line goes to its client first
(`reporter`, set by the server per command).

DSTEREO_WATCHDOG="FLOOR_S,FACTOR[,FIRST_S]" changes the allowances (tests; a user whose calls are legitimately
slow); DSTEREO_WATCHDOG=0 turns it off.
"""

from __future__ import annotations

import os
import threading
import time
from contextlib import contextmanager

FLOOR_S = 120.0  # no call is abandoned sooner: a loaded machine can stall a healthy call for tens of seconds
FACTOR = 30.0  # times the longest finished call of the same program and shapes (the calls of a run vary ~2-3x)
FIRST_S = 1800.0  # a program's first call: compiling the largest model here took ~60 s on a loaded 2-core machine
POLL_S = 1.0

_lock = threading.Lock()
_longest: dict = {}  # key -> the longest finished call (s)
_running: dict[int, tuple[float, float, str, object]] = {}  # token -> (start, allowance, what, key)
_token = 0
_monitor: threading.Thread | None = None
reporter = None  # callable(line) -> None: where a served command's line goes before the process ends


def settings(env=None) -> tuple[float, float, float] | None:
    """(floor, factor, first) from DSTEREO_WATCHDOG, else the defaults; None: turned off."""
    value = (os.environ if env is None else env).get("DSTEREO_WATCHDOG", "").strip()
    if value == "0":
        return None
    if not value:
        return FLOOR_S, FACTOR, FIRST_S
    try:
        numbers = [float(v) for v in value.split(",")]
        floor, factor = numbers[0], numbers[1]
        first = numbers[2] if len(numbers) > 2 else FIRST_S
    except (ValueError, IndexError):
        from dstereo.errors import DstereoError

        raise DstereoError(f"DSTEREO_WATCHDOG={value!r}: give FLOOR_S,FACTOR[,FIRST_S] (for example 120,30) or 0 "
                           "to turn the watchdog off") from None
    return floor, factor, first


def allowance(key, chosen=None) -> float:
    floor, factor, first = chosen or settings() or (FLOOR_S, FACTOR, FIRST_S)
    longest = _longest.get(key)
    return first if longest is None else max(floor, factor * longest)


@contextmanager
def watched(key, what: str):
    """Run the block (one compiled call and its results' transfer) under the watchdog (module docstring)."""
    global _token, _monitor
    chosen = settings()
    if chosen is None:
        yield
        return
    start = time.monotonic()
    with _lock:
        _token += 1
        token = _token
        _running[token] = (start, allowance(key, chosen), what, key)
        if _monitor is None or not _monitor.is_alive():
            _monitor = threading.Thread(target=_watch, name="dstereo-watchdog", daemon=True)
            _monitor.start()
    try:
        yield
    finally:
        took = time.monotonic() - start
        with _lock:
            _running.pop(token, None)
            _longest[key] = max(_longest.get(key, 0.0), took)


def _watch() -> None:
    while True:
        time.sleep(POLL_S)
        now = time.monotonic()
        with _lock:
            stuck = [(now - start, limit, what, key) for start, limit, what, key in _running.values()
                     if now - start > limit]
        if stuck:
            _give_up(*stuck[0])


def _give_up(waited: float, limit: float, what: str, key) -> None:
    longest = _longest.get(key)
    expected = "its first call" if longest is None else f"the longest earlier call of it took {longest:.1f} s"
    line = (f"the compiled solver made no progress on {what} for {waited:.0f} s ({expected}; allowed {limit:.0f} s); "
            "the run was abandoned and nothing was written. Run it again; if it stops again, run it with "
            "DSTEREO_THREADS=1 and report it (DSTEREO_WATCHDOG sets the allowance)")
    if reporter is not None:
        try:
            reporter(f"dstereo: error: {line}\n")
        except Exception:  # noqa: BLE001 - the process ends either way
            pass
    from dstereo.runtime import interrupts

    interrupts.abandon(line, 1)
