"""Building programs ahead of need (runtime/prebuild.py, jobs/prebuild.py): what a calibration ran is recorded and
built for other view buckets, so that a later data set of another size loads its executable instead of compiling."""

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them


@pytest.fixture
def executables(tmp_path, monkeypatch):
    """A compilation cache of this test's own, executables built in this process (DSTEREO_AOT=1)."""
    import jax

    from dstereo.calib import problem

    monkeypatch.setenv("DSTEREO_AOT", "1")
    monkeypatch.setenv("DSTEREO_SHAPE_BUCKETS", "1")
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "jax"))
    problem._compiled_solver.cache_clear()
    yield tmp_path / "jax" / "dstereo-aot"
    problem._compiled_solver.cache_clear()
    jax.config.update("jax_compilation_cache_dir", before)


def test_a_size_built_ahead_is_loaded_not_compiled(executables):
    """A one-camera solve at 11 views (bucket 11) records its solver; built ahead at bucket 14, a solve of 13 views
    (another bucket, never run) loads that executable from disk."""
    from dstereo.calib import problem
    from dstereo.calib.mono import calibrate_full
    from dstereo.jobs.prebuild import build
    from dstereo.runtime import buckets
    from dstereo.synth import board_views

    buckets.clear_noted()
    cam, _, obj, corners = board_views.scene(11, seed=2)
    calibrate_full(obj, corners, board_views.SIZE, board_warp=True, alone=True)
    records = [r for r in buckets.noted() if r[0] == "solver"]
    assert len(records) == 1
    assert build(records, (buckets.views(13),)) == 1
    problem._compiled_solver.cache_clear()  # a new process's view: nothing in memory
    cam, _, obj, corners = board_views.scene(13, seed=3)
    sol = calibrate_full(obj, corners, board_views.SIZE, board_warp=True, alone=True)
    assert sol.converged and sol.rms < 1e-6
    events = [e for f in [problem.compiled_solver(*records[0][1][:2])] for e in f.events]
    assert events == ["loaded"], events
    assert build(records, (buckets.views(13),)) == 0  # marked built: not again
