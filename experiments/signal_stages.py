"""By hand (not the suite): send SIGINT/SIGTERM/SIGHUP to a `dstereo calibrate` at several moments, served and not
served, and record how long it took to end, its exit code, the child processes left and the folders left.

    .venv/bin/python -m experiments.signal_stages [--served RUN_DIR]

The signal is sent at the first appearance of a progress text on stderr (TRIGGERS): a stage's start, or the end of
the stage before it. Served: start `DSTEREO_SERVE_DIR=RUN_DIR dstereo serve` first and run one calibration
through it (so nothing compiles). Results go to docs/validation.md by hand (section "Signals").
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dstereo.runtime.interrupts import children
from tests.test_signals import SUBSET_FLAGS, alive, render_views

# (stage, the progress text whose first appearance on stderr triggers the signal, extra delay s)
TRIGGERS = (("detection", b"detect:", 0.0), ("full-set solve", b"detect: 16/16 done", 0.0),
            ("subsets", b"full-set solve: 1/1 done", 0.5),
            ("final solve and figures", b"subsets: 12870/12870 done", 0.0),
            # "writing results:" is printed once the folder is in place: 0.8 s after the subsets is the writing
            ("final solve, figures, writing", b"subsets: 12870/12870 done", 0.8),
            ("results in place, process ending", b"writing results:", 0.0))


def one(views: Path, folder: Path, sig: int, trigger: bytes, delay: float, env: dict) -> dict:
    folder.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "dstereo.runtime.client", "calibrate", "--images", str(views),
                             *SUBSET_FLAGS, "--out", "results"], cwd=folder, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    os.set_blocking(proc.stderr.fileno(), False)
    seen, t0 = b"", time.monotonic()
    while trigger not in seen and proc.poll() is None and time.monotonic() - t0 < 300:
        seen += proc.stderr.read() or b""
        time.sleep(0.005)
    time.sleep(delay)
    kids = children(proc.pid)
    sent = time.monotonic()
    proc.send_signal(sig)
    os.set_blocking(proc.stderr.fileno(), True)
    out, err = proc.communicate(timeout=60)  # returns once every holder of the pipes has closed them
    ended = time.monotonic() - sent
    text = (seen + err).decode()
    return {"signal": signal.Signals(sig).name, "end_s": round(ended, 2), "code": proc.returncode,
            "left": [k for k in kids if alive(k)], "children": len(kids), "folder": sorted(os.listdir(folder)),
            "last": text.strip().splitlines()[-1] if text.strip() else ""}


def main() -> None:
    served = "--served" in sys.argv
    env = dict(os.environ, DSTEREO_SERVE="1" if served else "0")
    if served:
        env["DSTEREO_SERVE_DIR"] = sys.argv[sys.argv.index("--served") + 1]
    root = Path(tempfile.mkdtemp(prefix="signal-stages-"))
    views = render_views(root / "images", 16)
    i = 0
    for stage, trigger, delay in TRIGGERS:
        for sig in (signal.SIGINT, signal.SIGTERM):
            print({"stage": stage, "served": served, **one(views, root / f"run{i}", sig, trigger, delay, env)},
                  flush=True)
            i += 1


if __name__ == "__main__":
    main()
