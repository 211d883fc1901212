"""Frames in parallel (`dstereo.frames`): a local Dask cluster of 2 workers gives the serial results, a worker
that dies has its frame retried (or reported failed), and an interrupted run resumed from OUT.partial gives the
uninterrupted run's summary.json.

One small rendered sequence (6 frames, 320 x 240, as tests/test_recession.py renders them) serves every test.
"""

import json
import os

import numpy as np
import pytest

from conftest import run_cli

N_FRAMES = 6
ARGS = ("--grid", "1", "--z-min", "550", "--z-max", "650")


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from dstereo.recession.synthetic import write_synthetic_sequence

    folder = tmp_path_factory.mktemp("frames") / "seq"
    write_synthetic_sequence(folder, n_frames=N_FRAMES, duration_s=20.0, total_mm=1.0, image_size=(320, 240))
    return folder


def _run(sequence, out, *extra):
    code, stdout, stderr = run_cli("recession", sequence, "--calib", sequence / "stereo.yml", "--out", out, *ARGS,
                                   *extra)
    return code, stdout, stderr


def _numbers(out):
    """summary.json without its 'run' section (where and how fast it ran) and the maps."""
    summary = json.loads((out / "summary.json").read_text())
    run = summary.pop("run")
    with np.load(out / "recession_maps.npz") as maps:
        return summary, {k: maps[k] for k in maps.files}, run


@pytest.fixture(scope="module")
def serial(sequence, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "out"
    code, _, err = _run(sequence, out, "--workers", "1")
    assert code == 0, err
    return _numbers(out)


def _assert_same_maps(a, b):
    assert a.keys() == b.keys()
    for k in a:
        # bitwise: each frame is the same computation on the same inputs wherever it runs (the workers' XLA
        # runs single-threaded, and these functions give the same bits either way: measured, and so asserted)
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


def test_two_workers_give_the_serial_results(sequence, serial, tmp_path):
    out = tmp_path / "out"
    code, _, err = _run(sequence, out, "--workers", "2")
    assert code == 0, err
    summary, maps, run = _numbers(out)
    assert run["mode"] == "local dask cluster" and run["workers"] == 2
    assert run["frames_timed"] == N_FRAMES - 1  # the reference ran here; the others on the workers
    assert len(run["worker_peak_rss_mb"]) >= 1 and all(v > 50 for v in run["worker_peak_rss_mb"].values())
    assert summary == serial[0]
    _assert_same_maps(maps, serial[1])
    assert summary["frames_used"] == N_FRAMES
    assert not (tmp_path / "out.partial").exists()  # removed once the results folder is in place
    assert "s per frame on a worker" in err


class DyingReconstructor:
    """The real reconstructor, except that on a worker process it kills that process: at frame `once` the first
    time only (a marker file remembers), at frame `always` every time."""

    def __init__(self, inner, marker, once, always):
        self.inner, self.marker, self.once, self.always = inner, str(marker), once, always
        self.home = os.getpid()
        self.log = inner.log

    def __call__(self, frame):
        on_worker = os.getpid() != self.home
        if on_worker and frame.key.endswith(f"{self.always:03d}"):
            os._exit(1)
        if on_worker and frame.key.endswith(f"{self.once:03d}") and not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(1)
        out = self.inner(frame)
        self.log = self.inner.log
        return out


def test_a_killed_worker_has_its_frame_retried_then_reported(sequence, serial, tmp_path):
    import sys

    import cloudpickle

    from dstereo.frames import FrameRunner
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.recession import RecessionConfig, discover, run_recession
    from dstereo.recession.analysis import FrameReconstructor
    from dstereo.reconstruction import ReconstructionConfig

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    frames = discover(sequence)
    calib = read_stereo_calibration(sequence / "stereo.yml")
    from dataclasses import replace

    from dstereo.commands.matching_options import matching_changes

    # the configuration the CLI builds from ARGS, so that frame 2 can be compared with the serial run bit for bit
    recon = replace(ReconstructionConfig(), **matching_changes(ReconstructionConfig().sgbm, None, [], 550, 650, None))
    config = RecessionConfig(grid_mm=1.0)
    dying = DyingReconstructor(FrameReconstructor(calib, recon, config.refine_subpixel), tmp_path / "died", 2, 4)
    result = run_recession(frames, calib, config, recon, reconstruct=dying, runner=FrameRunner(2, retries=1))
    assert (tmp_path / "died").exists()  # frame 2's worker did die once
    status = [f.status for f in result.frames]
    assert status == ["ok", "ok", "ok", "ok", "failed", "ok"], [f.reason for f in result.frames]
    assert "died 2 time(s)" in result.frames[4].reason
    assert any("1 frame(s) failed" in w for w in result.warnings)
    # the retried frame is measured exactly as in the serial run
    np.testing.assert_array_equal(result.heights[2], serial[1]["heights_mm"][2])
    assert np.isnan(result.heights[4]).all()


def test_interrupted_run_resumes_to_the_same_summary(sequence, serial, tmp_path, monkeypatch):
    from dstereo.recession import analysis

    out = tmp_path / "out"
    real = analysis.FrameReconstructor.__call__

    def interrupt_at_frame_3(self, frame):
        if frame.key.endswith("003"):
            raise KeyboardInterrupt  # Ctrl-C while frame 3 runs
        return real(self, frame)

    monkeypatch.setattr(analysis.FrameReconstructor, "__call__", interrupt_at_frame_3)
    code, _, err = _run(sequence, out, "--workers", "1")
    assert code == 130 and "--resume" in err and not out.exists()
    kept = sorted(p.name for p in (tmp_path / "out.partial" / "frames").glob("*.json"))
    assert kept == ["000001.json", "000002.json"]  # frames 1 and 2 (0 is the reference, recomputed on resume)
    monkeypatch.setattr(analysis.FrameReconstructor, "__call__", real)

    code, _, err = _run(sequence, out, "--workers", "1")  # without --resume: refused, nothing deleted
    assert code == 1 and "--resume" in err and len(kept) == 2 and (tmp_path / "out.partial").exists()
    code, _, err = _run(sequence, out, "--workers", "1", "--resume", "--min-points", "9")  # other settings: refused
    assert code == 1 and "other inputs or settings" in err

    code, _, err = _run(sequence, out, "--workers", "1", "--resume")
    assert code == 0, err
    summary, maps, run = _numbers(out)
    assert run["frames_timed"] == N_FRAMES - 3  # frames 3, 4, 5 computed; 1 and 2 reused
    assert summary == serial[0]
    _assert_same_maps(maps, serial[1])
    assert not (tmp_path / "out.partial").exists()
