"""The figure workers write the same files as drawing in the calling process (the results folder must not depend
on where its figures were drawn), and a job's error reaches the caller."""

import numpy as np
import pytest

from dstereo.io import figure_pool, plots


@pytest.fixture(scope="module")
def pool():
    import os

    old = os.environ.get("DSTEREO_FIGURE_WORKERS")
    os.environ["DSTEREO_FIGURE_WORKERS"] = "1"
    figure_pool.start()
    assert figure_pool._POOL is not None, "the worker did not start"
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
