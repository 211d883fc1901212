"""`dstereo calibrate` end to end with the subset solver replaced by a fast stand-in: peak memory of everything
around the solves (plan, table, steps, statistics, figures, subsets.csv, JAX and the full-set solve) at a C
whose real solves would take hours. The real solver's own memory per block is measured separately (run the
real command for a few minutes and sample its RSS: it is flat). Stand-in values: the full-set solution plus
Student-t noise of about the subsets' spread.

    /usr/bin/time -v .venv/bin/python experiments/huge_run_fake_solve.py IMAGES OUT --per-set 20 --max-subsets N ...
"""

import sys

import numpy as np

import dstereo.calib.mono as mono
from dstereo.cli import main


RNG = np.random.default_rng(0)  # one stream for all blocks (a seed per block would repeat the same noise)


def fake_solve_subsets(obj, obs, plan, start, progress=None, **_):
    n, rng = len(plan), RNG
    values = start.values + np.abs(start.values) * 2e-4 * rng.standard_t(5, size=(n, len(start.values)))
    if progress is not None:
        progress(n, n)
    return mono.SubsetSolutions(plan=plan, names=start.names, values=values, std=np.zeros_like(values),
                                rms=start.rms * (1 + 0.1 * np.abs(rng.standard_t(5, n))), iterations=np.full(n, 3),
                                status=np.ones(n, np.int32), timings={"solve_s": 0.0})


if __name__ == "__main__":
    mono.solve_subsets = fake_solve_subsets
    images, out, *flags = sys.argv[1:]
    sys.argv = ["dstereo", "calibrate", "--images", images, "--out", out, *flags]
    main()
