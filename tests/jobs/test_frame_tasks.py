"""Frames in parallel (`dstereo.runtime.tasks`): a local Dask cluster of 2 workers gives the serial results, a worker
that dies has its frame retried (or reported failed), and an interrupted run resumed from OUT.partial gives the
uninterrupted run's summary.json.

One small rendered sequence (6 frames, 320 x 240, as tests/recession/test_analysis.py renders them) serves every test.
"""

import json
import os

import numpy as np
import pytest

from conftest import release_compiled_programs, run_cli

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them

N_FRAMES = 6
ARGS = ("--grid", "1", "--z-min", "550", "--z-max", "650")


def _before_a_cluster() -> None:
    """This process's compiled programs freed before it starts two Dask workers (~0.4-0.5 GB each): the suite's
    two test processes and these workers must stay under 3 GB together (measured: 0.9 GB here beside them, 2.98 GB
    in all)."""
    release_compiled_programs()


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from dstereo.jobs.synthetic_recession import write_synthetic_sequence

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
    return (*_numbers(out), out)


def test_report_html_with_the_face_in_3d_in_a_browser(serial):
    from conftest import assert_reports_render

    page, = assert_reports_render([serial[3]])
    assert len(page["views3d"]) == 1


def _assert_same_maps(a, b):
    assert a.keys() == b.keys()
    for k in a:
        # bitwise: each frame is the same computation on the same inputs wherever it runs (the workers' XLA
        # runs single-threaded, and these functions give the same bits either way: measured, and so asserted)
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


def test_two_workers_give_the_serial_results(sequence, serial, tmp_path):
    _before_a_cluster()
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
            with open(self.marker + ".always", "a") as fh:  # one line per death
                fh.write("died\n")
            os._exit(1)
        if on_worker and frame.key.endswith(f"{self.once:03d}") and not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(1)
        out = self.inner(frame)
        self.log = self.inner.log
        return out


def test_a_killed_worker_has_its_frame_retried_then_reported(sequence, serial, tmp_path):
    _before_a_cluster()
    import sys

    import cloudpickle

    from dstereo.runtime.tasks import FrameRunner
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.recession import RecessionConfig
    from dstereo.io.sequence_files import discover
    from dstereo.jobs.recession import run_recession
    from dstereo.jobs.recession import FrameReconstructor

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    frames = discover(sequence)
    calib = read_stereo_calibration(sequence / "stereo.yml")
    from dstereo.config import reconstruction as settings

    # the configuration the CLI builds from ARGS, so that frame 2 can be compared with the serial run bit for bit
    recon = settings.build(settings.flag_layer({"z_min": 550, "z_max": 650}))
    config = RecessionConfig(grid_mm=1.0)
    dying = DyingReconstructor(FrameReconstructor(calib, recon, config.refine_subpixel), tmp_path / "died", 2, 4)
    result = run_recession(frames, calib, config, recon, reconstruct=dying, runner=FrameRunner(2, retries=1))
    assert (tmp_path / "died").exists()  # frame 2's worker did die once
    status = [f.status for f in result.frames]
    assert status == ["ok", "ok", "ok", "ok", "failed", "ok"], [f.reason for f in result.frames]
    assert "died 2 time(s)" in result.frames[4].reason
    # bounded: run at most 1 + retries times (Dask charges a death to every task the dying worker held, so a
    # frame can also be given up after fewer runs of its own)
    assert 1 <= (tmp_path / "died.always").read_text().count("died") <= 2
    assert any("1 frame(s) failed" in w for w in result.warnings)
    # the retried frame is measured exactly as in the serial run
    np.testing.assert_array_equal(result.heights[2], serial[1]["heights_mm"][2])
    assert np.isnan(result.heights[4]).all()


def test_interrupted_run_resumes_to_the_same_summary(sequence, serial, tmp_path, monkeypatch):
    from dstereo.jobs import recession as analysis

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


# --- dstereo reconstruct with several pairs ---------------------------------------------------------------

PAIRS = 3


def _reconstruct(sequence, out, *extra):
    images = []
    for i in range(PAIRS):
        images += ["--left", sequence / "images_left" / f"left_{i:03d}.png",
                   "--right", sequence / "images_right" / f"right_{i:03d}.png"]
    return run_cli("reconstruct", *images, "--calib", sequence / "stereo.yml", "--out", out, "--z-min", "550",
                   "--z-max", "650", "--no-uncertainty", *extra)


def _pairs_index(out):
    """The index summary.json, without the timings (how long each step took is no result)."""
    index = json.loads((out / "summary.json").read_text())
    for s in index["pairs"]:
        s.pop("timings_s", None)
    return index


def test_reconstruct_pairs_in_parallel_and_resumed_equal_serial(sequence, tmp_path, monkeypatch):
    """Three pairs serially; the same run interrupted after its first pair and resumed on a 2-worker cluster, which
    computes the two remaining pairs at once: the index and every pair's arrays equal the serial run's bit for bit.
    The resumed run is the parallel run too (its two pairs ran on the workers, --workers 2 sends every task there:
    `FrameRunner.map`), so one cluster checks both; a separate uninterrupted parallel run repeated it."""
    _before_a_cluster()
    from dstereo.jobs import reconstruct_pairs as pairs

    serial = tmp_path / "serial"
    code, _, err = _reconstruct(sequence, serial, "--workers", "1")
    assert code == 0, err
    names = [f"left_{i:03d}" for i in range(PAIRS)]
    assert sorted(p.name for p in serial.iterdir() if p.is_dir()) == names
    from conftest import assert_reports_render

    assert_reports_render([serial])  # the index: one row per pair, each linking the pair's report.html
    assert all(f"]({n}/report.html)" in (serial / "report.md").read_text() for n in names)
    assert all((serial / n / "report.html").is_file() for n in names)

    real = pairs.reconstruct_pair
    ran = []

    def interrupt_at_pair_1(job, *args, **kwargs):
        if job[0] == "left_001":
            raise KeyboardInterrupt
        ran.append(job[0])
        return real(job, *args, **kwargs)

    out = tmp_path / "out"
    monkeypatch.setattr(pairs, "reconstruct_pair", interrupt_at_pair_1)
    code, _, err = _reconstruct(sequence, out, "--workers", "1")
    assert code == 130 and "1 finished pair(s)" in err and not out.exists() and ran == ["left_000"]
    monkeypatch.setattr(pairs, "reconstruct_pair", real)
    code, _, err = _reconstruct(sequence, out, "--workers", "2", "--resume")  # the last two pairs on the cluster
    assert code == 0, err
    assert not (tmp_path / "out.partial").exists()
    index = _pairs_index(out)
    assert index == _pairs_index(serial)
    for name in names:
        for f in ("points.npy", "disparity.npy", "depth.npy"):
            a, b = np.load(serial / name / f), np.load(out / name / f)
            assert np.array_equal(a, b, equal_nan=True), (name, f)  # same computation: bitwise
        assert not (out / name / "pair_done.json").exists()


def test_default_runner_stays_serial_when_a_cluster_would_not_pay(monkeypatch):
    """workers=None: the first task is timed here; a short remainder runs here too (no cluster started), a long
    one would start a cluster (checked by the decision alone, the cluster itself replaced)."""
    from dstereo.runtime import tasks as runner_mod

    done = []
    r = runner_mod.FrameRunner()
    if r.workers < 2:
        r.workers = 2  # the rule is about a machine with cores to spare
    r.map(lambda x: x * 2, [(i, i) for i in range(4)], lambda t: done.append(t.value))
    assert sorted(done) == [0, 2, 4, 6] and r.workers == 1 and r.decision.startswith("auto: serial")

    started = []
    slow = runner_mod.FrameRunner()
    slow.workers = 2
    monkeypatch.setattr(runner_mod, "_timed", lambda fn, arg: (fn(arg), runner_mod.PAYOFF_S, 0.0, "here", 0.0))
    monkeypatch.setattr(runner_mod.FrameRunner, "_map_dask", lambda self, fn, items, on_done, ticker:
                        started.append(len(items)))
    slow.map(lambda x: x, [(i, i) for i in range(3)], lambda t: None)
    assert started == [2] and slow.decision.startswith("auto: local cluster of 2")
