"""Issue 28's hostile walk, the reconstruction and recession side: each case gets one line `dstereo: error: ...`
and exit 1 before any work where it can be known before (SGBM settings OpenCV cannot take, a Middlebury baseline
<= 0, a worker count far above the cores, a scheduler address that is none), or a self-check after it (a noise
scale of 0, a rig without a baseline, an image size the calibration does not state). One test each."""

import errno
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import refused as _refused
from conftest import require_data, run_cli

ROOT = Path(__file__).resolve().parents[1]


def _image(path: Path, seed: int, size=(48, 64)) -> Path:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, size, dtype=np.uint8))
    return path


def _write_storage(path: Path, **mats) -> Path:
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in mats.items():
        fs.write(key, np.asarray(value, dtype=float))
    fs.release()
    return path


K = np.array([[500.0, 0, 32], [0, 500, 24], [0, 0, 1]])  # a camera of 64 x 48 images


def _teddy():
    teddy = require_data("middlebury2014q") / "Teddy"
    return teddy / "im0.png", teddy / "im1.png", teddy / "calib.txt"


def _calib_txt(tmp_path: Path, replace: dict[str, str | None]) -> Path:
    """Teddy's calib.txt with the lines of the keys in `replace` given a new value (None: line removed)."""
    lines = []
    for line in _teddy()[2].read_text().splitlines():
        key = line.partition("=")[0].strip()
        if key in replace:
            if replace[key] is None:
                continue
            line = f"{key}= {replace[key]}"
        lines.append(line)
    path = tmp_path / "calib.txt"
    path.write_text("\n".join(lines) + "\n")
    return path


# --- 1. SGBM settings OpenCV cannot take --------------------------------------------------------------------------

def test_uniqueness_ratio_100_is_refused_not_a_crash_in_opencv(tmp_path):
    """Before: SIGFPE inside OpenCV's 3-way SGBM (it divides by 100 - uniquenessRatio), exit 136 and no message.
    Run as a process: without the check the crash would take pytest down with it."""
    left, right, calib = _teddy()
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT), DSTEREO_SERVE="0")
    done = subprocess.run([sys.executable, "-m", "dstereo.cli", "reconstruct", "--left", str(left), "--right",
                           str(right), "--calib", str(calib), "--out", str(out), "--sgbm", "uniqueness_ratio=100"],
                          capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("dstereo: error: --sgbm uniqueness_ratio=100"), done.stderr
    assert "0..99" in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("setting, allowed", [
    ("block_size=1001", "odd 1..31 on these 450x375 images"),  # before: accepted, noise check 0 px, sigmas x 0.00
    ("num_disparities=464", "16..448"),
    ("pre_filter_cap=300", "1..127"),
    ("disp12_max_diff=-5", "-1 (off)"),
    ("P2=40000", "0..32767"),
    ("speckle_window_size=1000000", "0..168749"),
])
def test_sgbm_settings_opencv_cannot_take_are_refused_first(tmp_path, setting, allowed):
    # before: each ran to exit 0 (OpenCV silently clips, wraps or saturates them) with a poorer or empty map
    left, right, calib = _teddy()
    out = tmp_path / "out"
    _refused(("reconstruct", "--left", left, "--right", right, "--calib", calib, "--out", out, "--sgbm", setting),
             out, f"--sgbm {setting}", allowed)


def test_a_noise_scale_of_zero_is_not_applied():
    """A disparity map flat within its tiles (what block_size=1001 gave) has 0 px scatter about local fits: the
    sigmas were multiplied by 0.00. Now they stay the model's, with a warning."""
    from dstereo.stereo.disparity_noise import disparity_sigma_map

    rng = np.random.default_rng(3)
    left = rng.normal(128, 40, (160, 192)).clip(0, 255)
    right = np.roll(left, -8, axis=1)
    disparity = np.full(left.shape, 8.0, np.float32)
    disparity[:, -12:] = np.nan
    sigma, info, warnings = disparity_sigma_map((left, right), (left, right), disparity, False, 5,
                                                report_image_noise=False)
    assert info["scaled_by"] == 1.0
    assert info["plane_check"]["ratio"] is None and info["plane_check"]["ratio_refused"] == 0.0
    ok = np.isfinite(disparity)
    assert np.all(sigma[ok] > 0)
    assert any("no measure of the noise" in w and "not scaled" in w for w in warnings), warnings


# --- 2. Middlebury baseline <= 0, and an empty cloud ---------------------------------------------------------------

@pytest.mark.parametrize("baseline", ["-160", "0"])
def test_a_middlebury_baseline_that_is_not_positive_is_refused(tmp_path, baseline):
    # before: -160 ran to exit 0 (0.4 % valid, depths 1.2-2.9x wrong); 0 was a traceback in trimesh's PLY export
    left, right, _ = _teddy()
    calib = _calib_txt(tmp_path, {"baseline": baseline})
    out = tmp_path / "out"
    _refused(("reconstruct", "--left", left, "--right", right, "--calib", calib, "--out", out), out,
             str(calib), "baseline = ", "must be a positive number")


def test_an_empty_cloud_writes_a_valid_empty_mesh(tmp_path):
    """trimesh's exporter raised on a cloud without a point (ValueError: broadcast (0,5) into (0,4))."""
    import trimesh

    from dstereo.io.pointcloud import write_mesh_ply, write_ply_points

    points = np.full((6, 8, 3), np.nan)
    colors = np.zeros((6, 8, 3), np.uint8)
    assert write_mesh_ply(tmp_path / "mesh.ply", points, colors) == (0, 0)
    assert write_ply_points(tmp_path / "points.ply", points, colors) == 0
    mesh = trimesh.load(tmp_path / "mesh.ply", process=False)
    cloud = trimesh.load(tmp_path / "points.ply", process=False)
    assert len(getattr(mesh, "vertices", [])) == 0 and len(getattr(cloud, "vertices", [])) == 0


def test_a_pair_whose_every_point_is_removed_writes_its_folder_whole_with_a_warning(tmp_path):
    """The results folder of a pair without a point (here every matched pixel lies outside the ROI): written whole,
    points.ply and mesh.ply valid and empty, and a warning saying so, not a traceback."""
    import trimesh

    from dstereo.io.reconstruction_files import write_pair
    from dstereo.stereo.points_from_disparity import points_and_summary
    from dstereo.config.reconstruction_config import ReconstructionConfig

    h, w = 40, 64
    disparity = np.full((h, w), np.nan, np.float32)
    disparity[:, :20] = 10.0  # matched on the left only
    Q = np.array([[1.0, 0, 0, -32], [0, 1, 0, -20], [0, 0, 0, 500], [0, 0, 0.01, 0]])
    config = ReconstructionConfig(roi=(40, 0, 24, 40), uncertainty=False)
    image = np.random.default_rng(0).integers(0, 255, (h, w, 3), dtype=np.uint8)
    matrices = {k: np.eye(3) for k in ("R1", "R2")} | {"P1": np.eye(3, 4), "P2": np.eye(3, 4), "Q": Q,
                                                       "roi1": np.zeros(4), "roi2": np.zeros(4)}
    summary = {"units": "mm", "refine": {"enabled": False}, "sgbm": {"min_disparity": 0, "num_disparities": 16}}
    result = points_and_summary("pair", image, image, disparity, Q, np.eye(3), config, matrices, summary, {}, [])
    assert result.summary["valid_points"] == 0
    assert any("no pixel has a point" in x and "written empty" in x for x in result.warnings), result.warnings
    write_pair(tmp_path, result, config)
    for name in ("points.ply", "mesh.ply"):
        assert len(getattr(trimesh.load(tmp_path / name, process=False), "vertices", [])) == 0
    assert (tmp_path / "summary.json").is_file()


# --- 3. a calibration that does not state its image size ---------------------------------------------------------

def test_a_calibration_without_its_image_size_says_it_could_not_be_checked(tmp_path):
    # before: exit 0 and no word that the size was never compared
    left, right, _ = _teddy()
    calib = _calib_txt(tmp_path, {"width": None, "height": None})
    out = tmp_path / "out"
    code, _, err = run_cli("reconstruct", "--left", left, "--right", right, "--calib", calib, "--out", out)
    assert code == 0, err
    unchecked = [line for line in err.splitlines() if "does not state its image size" in line]
    assert len(unchecked) == 1 and unchecked[0].startswith("dstereo: warning: ") and "450x375" in unchecked[0], err
    assert "could not check" in unchecked[0]


@pytest.mark.parametrize("cx, cy, why", [(320.0, 240.0, "outside these 64x48 images"),
                                         (16.0, 12.0, "evidently for images of about 32x24 px")])
def test_a_calibration_without_its_size_for_other_images_is_refused(tmp_path, cx, cy, why):
    # before: exit 0 and a meaningless cloud (a 640 x 480 calibration applied to 64 x 48 images)
    Kc = np.array([[500.0, 0, cx], [0, 500, cy], [0, 0, 1]])
    calib = _write_storage(tmp_path / "stereo.yml", M1=Kc, D1=np.zeros(5), M2=Kc, D2=np.zeros(5), R=np.eye(3),
                           T=[-100.0, 0, 0])  # no imageSize
    left, right = _image(tmp_path / "l.png", 1), _image(tmp_path / "r.png", 2)
    out = tmp_path / "out"
    _refused(("reconstruct", "--left", left, "--right", right, "--calib", calib, "--out", out), out,
             "does not state its image size", why)


# --- 4. recession: --workers, --scheduler, and "Too many open files" ---------------------------------------------

def _sequence(tmp_path: Path) -> Path:
    seq = tmp_path / "seq"
    for t in (0, 1):
        _image(seq / "left" / f"left_t={t}s.png", 10 + t)
        _image(seq / "right" / f"right_t={t}s.png", 20 + t)
    return seq


def test_recession_refuses_a_worker_count_far_above_the_cores_before_any_work(tmp_path):
    """Before: --workers 100000 started nannies for minutes (19,999 open files) and hung. The calibration here is
    broken on purpose: the worker count is refused before the calibration is even read (and without the check
    the run stops at the calibration, never starting a cluster)."""
    (tmp_path / "broken.yml").write_text("")
    out = tmp_path / "out"
    most = 4 * (os.cpu_count() or 1)
    _refused(("recession", _sequence(tmp_path), "--calib", tmp_path / "broken.yml", "--out", out, "--workers",
              "100000"), out, "--workers 100000", f"at most {most}", "cores")


def test_a_worker_count_the_open_file_limit_cannot_hold_is_refused(monkeypatch):
    import resource

    from dstereo.errors import DstereoError
    from dstereo.runtime.tasks import FrameRunner

    monkeypatch.setattr(resource, "getrlimit", lambda _: (100, 100))
    with pytest.raises(DstereoError, match="open-file limit .100"):
        FrameRunner(workers=min(4, 4 * (os.cpu_count() or 1)))
    FrameRunner(workers=1)  # one worker runs here: no cluster, nothing to hold


@pytest.mark.parametrize("address", ["not a url", "http://10.0.0.5:8786", "tcp://host:99999"])
def test_a_scheduler_address_that_is_none_is_refused_and_nothing_written(tmp_path, address):
    # before: "not a url" was a traceback from Dask and left OUT.partial behind
    calib = _write_storage(tmp_path / "stereo.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3),
                           T=[-100.0, 0, 0])
    out = tmp_path / "out"
    _refused(("recession", _sequence(tmp_path), "--calib", calib, "--out", out, "--scheduler", address), out,
             f"--scheduler {address!r}", "tcp://HOST:PORT")


def test_running_out_of_file_descriptors_does_not_blame_the_file(monkeypatch):
    """Before: "dstereo: error: stereo.yml: Too many open files; check the path, ...": the file was not at fault."""
    def out_of_descriptors(*_):
        raise OSError(errno.EMFILE, "Too many open files", "stereo.yml")

    monkeypatch.setattr("dstereo.optics.calculator.compute_optics", out_of_descriptors)
    line = _refused(("optics", "--focus-distance", "1000", "--focal-length", "50", "--crop-factor", "1.5",
                     "--f-number", "8"), None, "Too many open files", "run out of open files", "not at fault")
    assert not line.startswith("dstereo: error: stereo.yml"), line


# --- 5. a rig without a baseline -------------------------------------------------------------------------------

@pytest.mark.parametrize("board_depths", [True, False])
def test_a_rig_without_a_baseline_is_refused(tmp_path, board_depths):
    """A right folder holding copies of the left images calibrates to |T| = 2.2e-9 mm; reconstruct then blamed a
    "vertical baseline"."""
    calib = _write_storage(tmp_path / "stereo.yml", M1=K, D1=np.zeros(5), M2=K, D2=np.zeros(5), R=np.eye(3),
                           T=[1.2e-9, 1.8e-9, 0.3e-9], imageSize=np.array([[64, 48]]))
    if board_depths:  # dstereo's stereo.yml carries them (`append_board_depths`)
        with calib.open("a") as fh:
            fh.write("board_depth_min: 250.0\nboard_depth_max: 600.0\n")
    left, right = _image(tmp_path / "l.png", 1), _image(tmp_path / "r.png", 2)
    out = tmp_path / "out"
    line = _refused(("reconstruct", "--left", left, "--right", right, "--calib", calib, "--out", out), out,
                    "stereo.yml", "the rig has no baseline", "may be the same pictures")
    assert "vertical" not in line
    if board_depths:
        assert "nearest calibration board, at 250" in line
