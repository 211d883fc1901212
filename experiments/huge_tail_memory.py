"""Peak memory of a huge run's tail (steps, statistics, figures, subsets.csv) without its ~2 h of solves.

A C-row table of synthetic subset values (normal around a camera's, heavy-tailed outliers) goes to disk as
the solve blocks would write it; then the robust steps, the stats files, the ten parameter figures and the
CSV run on it, as `fill_camera_folder` runs them. Prints peak RSS (getrusage) after each stage.

    .venv/bin/python experiments/huge_tail_memory.py 10000000 /tmp/somewhere [--no-csv]
"""

import resource
import sys
import time
from pathlib import Path

import numpy as np

from dstereo.calib.robust_steps import run_steps
from dstereo.calib.subset_table import SubsetTable
from dstereo.calib.subsets import plan_subsets
from dstereo.config.calibration import Step
from dstereo.io import plots
from dstereo.io.results import write_stats_files, write_subsets_csv

COLUMNS = ("re", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
CENTRE = np.array([0.04, 800.3, 800.7, 321.9, 237.8, -0.18, 0.92, 3e-4, -4e-4, -0.07])
SPREAD = np.array([0.005, 0.13, 0.12, 0.09, 0.12, 9e-4, 0.011, 5e-5, 5e-5, 0.04])


def peak(stage: str, t0: float) -> None:
    mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{stage:<28} peak RSS {mb:7.0f} MB   {time.perf_counter() - t0:6.1f} s", flush=True)


def main(count: int, folder: Path, csv: bool) -> None:
    t0 = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    plan = plan_subsets(29, 20, cap=count, seed=0)
    table = SubsetTable(COLUMNS, count, folder=folder)
    rng = np.random.default_rng(0)
    for a in range(0, count, 500_000):
        k = min(500_000, count - a)
        rows = CENTRE + SPREAD * rng.standard_t(5, size=(k, len(COLUMNS)))
        table.put(a, rows, np.ones(k))
    peak(f"table of {count} written", t0)
    steps = (Step(("re",), (0.06,)), Step(("fx", "fy"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5, 1.5, 1.5)))
    f = run_steps(table, COLUMNS, steps, table.status > 0)
    peak("steps", t0)
    write_stats_files(folder / "stats", f)
    peak("stats files", t0)
    for name in COLUMNS:
        plots.parameter_figure(name, f.values(name, 0), f.values(name, len(f.steps)), folder / f"{name}.png", "px")
    peak("10 parameter figures", t0)
    if csv:
        write_subsets_csv(folder / "subsets.csv", plan, f, table.status)
        peak("subsets.csv", t0)
    table.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), Path(sys.argv[2]), "--no-csv" not in sys.argv)
