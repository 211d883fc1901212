"""By hand (not the suite): send SIGINT/SIGTERM/SIGHUP to a `dstereo calibrate` at several moments, served and not
served, and record how long it took to end, its exit code, the child processes left and the folders left.

    .venv/bin/python -m experiments.signal_stages [--served RUN_DIR]

The stage a signal hit is read from the progress lines seen before it (`detect: ... done`, `full-set solve: ...
done`, `subsets: ... done`, `writing results: ... done`): the first stage not yet reported done. Served: start
`DSTEREO_SERVE_DIR=RUN_DIR dstereo serve` first and run one calibration through it (so nothing compiles).
Results go to docs/validation.md by hand (section "Signals").
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dstereo.interrupts import children
from tests.test_signals import SUBSET_FLAGS, alive, render_views

STAGES = (("detect:", "detection"), ("full-set solve:", "full-set solve"), ("subsets:", "subsets"),
          ("writing results:", "writing"))
DELAYS = (1.0, 3.0, 6.0, 12.0, 16.0)


def one(views: Path, folder: Path, sig: int, delay: float, env: dict) -> dict:
    folder.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "dstereo.serve_client", "calibrate", "--images", str(views),
                             *SUBSET_FLAGS, "--out", "results"], cwd=folder, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    os.set_blocking(proc.stderr.fileno(), False)
    seen, t0 = b"", time.monotonic()
    while time.monotonic() - t0 < delay and proc.poll() is None:
        seen += proc.stderr.read() or b""
        time.sleep(0.02)
    kids = children(proc.pid)
    sent = time.monotonic()
    proc.send_signal(sig)
    os.set_blocking(proc.stderr.fileno(), True)
    out, err = proc.communicate(timeout=60)  # returns once every holder of the pipes has closed them
    ended = time.monotonic() - sent
    text = (seen + err).decode()
    stage = next((name for key, name in STAGES if f"{key}" not in (seen.decode())), "done")
    return {"signal": signal.Signals(sig).name, "stage": stage, "end_s": round(ended, 2), "code": proc.returncode,
            "left": [k for k in kids if alive(k)], "children": len(kids), "folder": sorted(os.listdir(folder)),
            "last": text.strip().splitlines()[-1] if text.strip() else ""}


def main() -> None:
    served = "--served" in sys.argv
    env = dict(os.environ, DSTEREO_SERVE="1" if served else "0")
    if served:
        env["DSTEREO_SERVE_DIR"] = sys.argv[sys.argv.index("--served") + 1]
    root = Path(tempfile.mkdtemp(prefix="signal-stages-"))
    views = render_views(root / "images", 16)
    for i, (sig, delay) in enumerate((s, d) for d in DELAYS for s in (signal.SIGINT, signal.SIGTERM)):
        print(one(views, root / f"run{i}", sig, delay, env), flush=True)


if __name__ == "__main__":
    main()
