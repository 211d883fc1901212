"""The figure workers write the same files as drawing in the calling process (the results folder must not depend
on where its figures were drawn), and a job's error reaches the caller."""

import numpy as np
import pytest

from dstereo.io import plots
from dstereo.runtime import figure_pool


@pytest.fixture(scope="module")
def pool():
    import os

    old = os.environ.get("DSTEREO_FIGURE_WORKERS")
    os.environ["DSTEREO_FIGURE_WORKERS"] = "1"
    figure_pool.stop()  # workers an in-process command of an earlier test started
    figure_pool.start()
    assert figure_pool.started() == 1, "the worker did not start"
    yield
    figure_pool.stop()
    if old is None:
        del os.environ["DSTEREO_FIGURE_WORKERS"]
    else:
        os.environ["DSTEREO_FIGURE_WORKERS"] = old


def test_worker_figure_equals_inline(pool, tmp_path):
    x = np.random.default_rng(3).normal(800.0, 1.0, 900)
    data = plots.parameter_figure_data("fx", x, x[np.abs(x - 800) < 1], "px", 800.0)
    figures = figure_pool.Figures()
    figures.draw(plots.draw_parameter_figure, data, tmp_path / "worker.png")
    figures.wait()
    assert figures.jobs == [] and (tmp_path / "worker.png").exists()
    plots.draw_parameter_figure(data, tmp_path / "inline.png")
    # Same matplotlib, same data, same Agg backend: byte-identical PNGs.
    assert (tmp_path / "worker.png").read_bytes() == (tmp_path / "inline.png").read_bytes()


def test_worker_error_reaches_caller(pool, tmp_path):
    figures = figure_pool.Figures()
    figures.draw(plots.per_image_rms, ["a.png"], np.array([0.1]), tmp_path / "missing" / "r.png")
    with pytest.raises(FileNotFoundError):
        figures.wait()


MAIN = r'''
import os, sys
from pathlib import Path
if __name__ != "__main__":  # a spawned worker importing this main module (as __mp_main__): what start() avoids
    Path(os.environ["MARKER"]).write_text(__name__)
else:
    from dstereo.runtime import figure_pool
    figure_pool.start(now=1)
    figure_pool.start_rest()
    print(figure_pool.started())  # every worker started, each under the stand-in main module
    figure_pool.stop()
'''


def test_every_worker_starts_without_importing_the_main_module(tmp_path):
    import os
    import subprocess
    import sys

    script, marker = tmp_path / "main.py", tmp_path / "imported"
    script.write_text(MAIN)
    env = dict(os.environ, DSTEREO_FIGURE_WORKERS="2", MARKER=str(marker))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["2"] and not marker.exists()


def test_jobs_go_to_the_least_busy_worker():
    """One single-worker pool per worker (`figure_pool.start`): jobs handed out together reach both workers."""
    import os
    import time

    old = os.environ.get("DSTEREO_FIGURE_WORKERS")
    os.environ["DSTEREO_FIGURE_WORKERS"] = "2"
    try:
        figure_pool.stop()  # the module's single worker, or an earlier test's
        figure_pool.start(now=1)
        assert figure_pool.started() == 1
        figure_pool.start_rest()
        assert figure_pool.started() == 2
        futures = [figure_pool._submit(time.sleep, 0.2) for _ in range(4)]
        pids = [figure_pool._submit(os.getpid) for _ in range(2)]
        for f in futures:
            f.result()
        assert len({f.result() for f in pids}) == 2  # each worker had two sleeps queued: one getpid each
    finally:
        figure_pool.stop()
        if old is None:
            del os.environ["DSTEREO_FIGURE_WORKERS"]
        else:
            os.environ["DSTEREO_FIGURE_WORKERS"] = old
