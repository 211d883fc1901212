"""mrcal's .cameramodel (dstereo.io.cameramodel): lens model per free set, round trip bit for bit, mrcal's own
sample file, the fisheye (no mrcal twin), bad files as one-line errors, and the file in a results folder."""

import cv2
import numpy as np
import pytest

from conftest import require_data, run_cli
from dstereo.errors import DstereoError
from dstereo.io.cameramodel import NO_TWIN, lensmodel_for, read_cameramodel, write_cameramodel
from dstereo.models.distortion import PRESETS

pytestmark = pytest.mark.slow  # see pyproject.toml: `make test` leaves these out, `make test-slow` runs them

K = np.array([1766.07, 1765.89, 1944.07, 1064.52])
COEFFS = np.array([-0.21, 0.08, 1e-4, -3e-4, -0.012, 0.3, -0.05, 0.01])  # OpenCV order k1 k2 p1 p2 k3 k4 k5 k6

# mrcal's own sample (mrcal/cameramodel.py docstring): written by mrcal, not by dstereo
MRCAL_SAMPLE = """# generated with ...
{ 'lensmodel': 'LENSMODEL_OPENCV8',

  # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....
  'intrinsics': [1766.0712405930, 1765.8925266865, 1944.0664501036, 1064.5231421210, 2.1648025156,
                 -1.1851581377, -0.0000931342, 0.0007782462, -0.2351910903, 2.4460295029, -0.6697132481,
                 -0.6284355415],

  'extrinsics': [0,0,0,0,0,0],
  'imagersize': [3840,2160]
}
"""


@pytest.mark.parametrize("preset, expected", [("none", "LENSMODEL_PINHOLE"), ("k1k2", "LENSMODEL_OPENCV4"),
                                              ("k1k2p1p2", "LENSMODEL_OPENCV4"), ("default", "LENSMODEL_OPENCV5"),
                                              ("rational", "LENSMODEL_OPENCV8"), ("fisheye", None)])
def test_lens_model_per_free_set(preset, expected):
    assert lensmodel_for(PRESETS[preset])[0] == expected


@pytest.mark.parametrize("preset", ["none", "k1k2", "default", "rational"])
def test_round_trip_is_exact(tmp_path, preset):
    free = PRESETS[preset]
    coeffs = np.array([c if n in free else 0.0 for n, c in zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
                                                               COEFFS)])
    k, coeffs = K * np.pi / 3, coeffs * np.e / 2  # all 17 digits significant
    rt = np.array([0.01, -0.2, 0.003, -120.5, 0.7, 3.25]) * np.sqrt(2)
    path = tmp_path / "camera.cameramodel"
    write_cameramodel(path, free, k, coeffs, (3840, 2160), rt, note="test\nsecond line")
    back = read_cameramodel(path)
    assert back.lensmodel == lensmodel_for(free)[0] and back.image_size == (3840, 2160)
    # repr writes 17 significant digits: float64 reads back bit for bit
    assert np.array_equal(back.intrinsics, k) and np.array_equal(back.coeffs, coeffs)
    assert np.array_equal(back.rt_cam_ref, rt) and set(free) <= set(back.free)


def test_reads_mrcals_sample_in_opencv_order(tmp_path):
    path = tmp_path / "sample.cameramodel"
    path.write_text(MRCAL_SAMPLE)
    m = read_cameramodel(path)
    assert m.lensmodel == "LENSMODEL_OPENCV8" and m.image_size == (3840, 2160)
    # mrcal's k0..k7 are OpenCV's k1 k2 p1 p2 k3 k4 k5 k6: projecting with OpenCV must equal mrcal's equations
    # (doc/lensmodels.org, written out here independently)
    p = np.array([[0.3, -0.2, 1.0], [-0.5, 0.4, 2.0]])
    kmat = np.array([[m.intrinsics[0], 0, m.intrinsics[2]], [0, m.intrinsics[1], m.intrinsics[3]], [0, 0, 1]])
    q_cv = cv2.projectPoints(p, np.zeros(3), np.zeros(3), kmat, m.coeffs)[0][:, 0]
    k = m.coeffs
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    r2 = x * x + y * y
    rad = (1 + k[0] * r2 + k[1] * r2 ** 2 + k[4] * r2 ** 3) / (1 + k[5] * r2 + k[6] * r2 ** 2 + k[7] * r2 ** 3)
    xd = x * rad + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
    yd = y * rad + 2 * k[3] * x * y + k[2] * (r2 + 2 * y * y)
    q_mrcal = np.column_stack([m.intrinsics[0] * xd + m.intrinsics[2], m.intrinsics[1] * yd + m.intrinsics[3]])
    np.testing.assert_allclose(q_cv, q_mrcal, rtol=0, atol=1e-8)  # float64 rounding of ~1e3 px values


def test_fisheye_has_no_twin_and_nothing_is_written(tmp_path):
    what = write_cameramodel(tmp_path / "camera.cameramodel", PRESETS["fisheye"], K, np.zeros(8), (640, 640))
    assert what == NO_TWIN and "no mrcal twin" in what and not (tmp_path / "camera.cameramodel").exists()


@pytest.mark.parametrize("text, message", [
    ("{'lensmodel': 'LENSMODEL_OPENCV4'", "not a readable"),
    ("[1, 2]", "holds a dict"),
    ("{'lensmodel': 'LENSMODEL_OPENCV4', 'intrinsics': [1, 2, 3, 4, 0, 0, 0, 0]}", "lacks imagersize"),
    ("{'lensmodel': 'LENSMODEL_CAHVOR', 'intrinsics': [1, 1, 1, 1, 1, 1, 1, 1, 1], 'imagersize': [4, 4]}",
     "no dstereo twin"),
    ("{'lensmodel': 'LENSMODEL_OPENCV5', 'intrinsics': [1, 2, 3, 4, 0], 'imagersize': [4, 4]}", "expected 9"),
    ("{'lensmodel': 'LENSMODEL_PINHOLE', 'intrinsics': [1, 2, 3, 4], 'imagersize': [4.5, 4]}", "whole numbers"),
])
def test_bad_files_are_one_line_errors(tmp_path, text, message):
    path = tmp_path / "bad.cameramodel"
    path.write_text(text)
    with pytest.raises(DstereoError, match=message) as err:
        read_cameramodel(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


@pytest.fixture(scope="module")
def left_results(tmp_path_factory):
    """OpenCV's left sample images calibrated by the CLI: full set, 5 coefficients, the board's sag solved."""
    images = require_data("opencv_stereo")
    out = tmp_path_factory.mktemp("left") / "out"
    code, _, err = run_cli("calibrate", "--images", images, "--glob", "left*.jpg", "--pattern", "9x6", "--model",
                           "default", "--out", out, "-q")
    assert code == 0, err
    return out


def test_results_folder_holds_the_camera_of_camera_yml(left_results):
    """camera.cameramodel holds camera.yml's numbers."""
    out = left_results
    fs = cv2.FileStorage(str(out / "camera.yml"), cv2.FILE_STORAGE_READ)
    kmat, d = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    m = read_cameramodel(out / "camera.cameramodel")
    assert m.lensmodel == "LENSMODEL_OPENCV5" and m.image_size == (640, 480)
    np.testing.assert_array_equal(m.intrinsics, kmat[[0, 1, 0, 1], [0, 1, 2, 2]])
    np.testing.assert_array_equal(m.coeffs[:5], d)
    assert "camera.cameramodel" in (out / "report.md").read_text()


def test_rig_files_put_the_right_camera_at_opencvs_r_t(tmp_path):
    from dstereo.io.cameramodel import write_rig_cameramodels

    rvec, t = np.array([0.02, -0.15, 0.01]), np.array([-120.3, 1.2, 0.8])
    R = cv2.Rodrigues(rvec)[0]
    cams = [(np.array([[800.0, 0, 320], [0, 801, 240], [0, 0, 1]]), COEFFS * (np.arange(8) < 5), PRESETS["default"],
             (640, 480)), (np.array([[805.0, 0, 318], [0, 806, 242], [0, 0, 1]]), COEFFS, PRESETS["rational"],
                           (640, 480))]
    write_rig_cameramodels(tmp_path, cams, R, t)
    left, right = read_cameramodel(tmp_path / "left.cameramodel"), read_cameramodel(tmp_path / "right.cameramodel")
    assert (left.lensmodel, right.lensmodel) == ("LENSMODEL_OPENCV5", "LENSMODEL_OPENCV8")
    assert np.array_equal(left.rt_cam_ref, np.zeros(6))
    p_left = np.array([10.0, -5.0, 900.0])
    # mrcal: x_cam = R(r) x_ref + t with the left camera as reference; OpenCV: x_right = R x_left + T
    p_right = cv2.Rodrigues(right.rt_cam_ref[:3])[0] @ p_left + right.rt_cam_ref[3:]
    np.testing.assert_allclose(p_right, R @ p_left + t, rtol=0, atol=1e-9)  # Rodrigues round trip, float64


# Run by Debian's python3 (mrcal is a system package, never a dependency): mrcal reads the file, evaluates the
# stored solve, re-solves it from a start moved off the optimum, and gives its projection uncertainty.
MRCAL_CHECK = """
import copy, json, sys
import mrcal, numpy as np
m = mrcal.cameramodel(sys.argv[1])
oi = m.optimization_inputs()
x = mrcal.optimizer_callback(**oi, no_jacobian=True, no_factorization=True)[1]
obs = oi['observations_board']
nv, H, W = obs.shape[:3]
r = x[:nv * H * W * 2].reshape(nv, H * W, 2)
ok = obs[..., 2].reshape(nv, H * W) > 0
again = copy.deepcopy(oi)
mrcal.optimize(**again)
start = copy.deepcopy(oi)
start['intrinsics'][0, :4] += [4.0, -4.0, 2.0, -2.0]
start['frames_rt_toref'][:, 3:] *= 1.002
start['calobject_warp'] = start['calobject_warp'] * 0.5
mrcal.optimize(**start)
print(json.dumps({'n_measurements': int(x.size), 'n_board': nv * H * W * 2, 'rejected': int((~ok).sum()),
                  'rms': float(np.sqrt(np.mean(np.sum(r[ok] ** 2, -1)))),
                  'again': again['intrinsics'][0].tolist(), 'again_warp': again['calobject_warp'].tolist(),
                  'intrinsics': start['intrinsics'][0].tolist(), 'warp': start['calobject_warp'].tolist(),
                  'region': m.valid_intrinsics_region().tolist(),
                  'uncertainty_px': float(mrcal.projection_uncertainty(np.array([0.0, 0.0, 1000.0]), m,
                                                                       what='worstdirection-stdev'))}))
"""
SYSTEM_PYTHON = "/usr/bin/python3"
# mrcal re-evaluates the residuals with its own projection code: each differs from dstereo's by rounding of a pixel
# coordinate (< 800 px: a few dozen roundings, ~1e-12 px), not of the residual (~0.15 px), so the two RMS values
# agree to ~1e-11 relative at worst (measured 1e-15 to 9e-15: the rounding errors average out over the corners)
RMS_RTOL = 1e-10


def _mrcal_or_skip() -> None:
    import subprocess

    try:
        found = subprocess.run([SYSTEM_PYTHON, "-c", "import mrcal"], capture_output=True, timeout=60).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        found = False
    if not found:
        pytest.skip(f"mrcal is not installed for {SYSTEM_PYTHON} (Debian's python3-mrcal): it is a reference for "
                    "checks, never a dependency of dstereo")


def test_mrcal_reevaluates_and_resolves_the_solve_the_file_holds(left_results):
    """Issue 35: the file's optimization inputs are dstereo's solve in mrcal's layout: mrcal evaluates them to
    dstereo's RMS over the same corners (the rejected ones marked as mrcal's outliers), its own solver comes back
    from a start moved off to dstereo's intrinsics and sag, and its projection_uncertainty runs on the file."""
    import json
    import subprocess

    _mrcal_or_skip()
    out = left_results
    done = subprocess.run([SYSTEM_PYTHON, "-c", MRCAL_CHECK, str(out / "camera.cameramodel")], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout)
    summary = json.loads((out / "summary.json").read_text())
    full = summary["full_set"]
    # regularization off: the measurements are the board corners' residuals only
    assert got["n_measurements"] == got["n_board"]
    assert got["rejected"] == len(summary["outliers"]["corners"]) > 0 and not summary["outliers"]["views"]
    # the same residuals at the same parameters, computed by mrcal: rounding only (RMS_RTOL)
    assert abs(got["rms"] / full["rms"] - 1) < RMS_RTOL, (got["rms"], full["rms"])
    cam = read_cameramodel(out / "camera.cameramodel")
    values = np.concatenate([cam.intrinsics, cam.coeffs[:5]])
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    sigma = np.array([full["std"][n] for n in names])
    sag = np.array([full["board_sag_x"], full["board_sag_y"]])
    sag_sigma = np.array([full["std"]["board_sag_x"], full["std"]["board_sag_y"]])
    # re-solved from the file's own state, mrcal finds it at its optimum: issue 35 asks no parameter moved by more
    # than 1e-6 of its sigma (measured: none moved)
    assert np.all(np.abs(np.array(got["again"]) - values) < 1e-6 * sigma), (got["again"], values)
    assert np.all(np.abs(np.array(got["again_warp"]) - sag) < 1e-6 * sag_sigma), (got["again_warp"], sag)
    # from a start moved off it (4 px, 0.2 % of range, half the sag), mrcal's solver comes back to it within its
    # own stopping rule (measured 1.4e-5 sigma on cy): 1e-4 sigma, far below anything a user reads
    assert np.all(np.abs(np.array(got["intrinsics"]) - values) < 1e-4 * sigma), (got["intrinsics"], values)
    assert np.all(np.abs(np.array(got["warp"]) - sag) < 1e-4 * sag_sigma), (got["warp"], sag)
    assert np.isfinite(got["uncertainty_px"]) and got["uncertainty_px"] > 0
    # the valid-intrinsics region mrcal reads is the one dstereo wrote: a closed outline inside the image
    region = np.array(got["region"])
    assert region.shape[0] >= 4 and np.array_equal(region[0], region[-1])
    assert np.all((region >= 0) & (region <= np.array([639.0, 479.0])))


def test_a_free_set_mrcal_cannot_hold_fixed_is_said_in_the_file(tmp_path):
    """k1 alone lives in OPENCV4 with k2, p1, p2 held at 0, which mrcal's solve would free: no optimization
    inputs, and the file's comment says why."""
    from dstereo.io.cameramodel import BoardSolve

    solve = BoardSolve.one_camera(("k1",), K, np.zeros(8), (640, 480), np.zeros((3, 6)), np.zeros((3, 54, 2)), None,
                                  (9, 6), 1.0, None)
    done = write_cameramodel(tmp_path / "c.cameramodel", ("k1",), K, np.zeros(8), (640, 480), solve=solve)
    text = (tmp_path / "c.cameramodel").read_text()
    assert "optimization_inputs" not in text and "mrcal frees every coefficient" in text and "held" in done
    read_cameramodel(tmp_path / "c.cameramodel")  # still a plain camera file


# mrcal's worst-direction projection std of each camera file at pixels q and range r (one Debian python for
# several files: its start and mrcal's import, ~0.7 s, paid once)
MRCAL_UNCERTAINTIES = """
import json, sys, numpy as np, mrcal
out = []
for path, q, r in json.loads(sys.argv[1]):
    m = mrcal.cameramodel(path)
    p = mrcal.unproject(np.array(q), *m.intrinsics(), normalize=True) * r
    c = mrcal.projection_uncertainty(p, model=m, atinfinity=False, what='covariance')
    out.append(np.sqrt(np.linalg.eigvalsh(c)[:, -1]).tolist())
print(json.dumps(out))
"""


def _mrcal_stds(jobs) -> list[np.ndarray]:
    """mrcal's worst-direction projection std at pixels q of each camera file, for `jobs` = [(path, q, range)]:
    every file in one process (MRCAL_UNCERTAINTIES)."""
    import json
    import subprocess

    arg = json.dumps([[str(path), np.asarray(q).tolist(), float(range_)] for path, q, range_ in jobs])
    done = subprocess.run([SYSTEM_PYTHON, "-c", MRCAL_UNCERTAINTIES, arg], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return [np.array(x) for x in json.loads(done.stdout)]


@pytest.mark.numerics
def test_mrcals_projection_uncertainty_of_the_file_is_dstereos_jacobian_map_in_mrcals_noise_convention(
        left_results):
    """mrcal's projection_uncertainty on the written file against dstereo's pose-compensated map of the same solve
    from the Jacobian covariance (mrcal's premise: independent corner noise; the map dstereo reports carries the
    views' effects besides), at the map's range: mrcal's noise is sqrt(SSE / N), dstereo's sqrt(SSE / (N - p)),
    so every pixel's ratio is sqrt(N / (N - p)) (3.4 % here; measured equal to 3e-7)."""
    import ast
    import base64
    import io
    import json

    from dstereo.calib.mono import calibrate_full
    from dstereo.models.board import Board
    from dstereo.uncertainty.covariance import joint_covariance
    from dstereo.uncertainty.projection import projection_uncertainty_map
    from dstereo.uncertainty.view_scatter import inliers_of, sse_of

    _mrcal_or_skip()
    out = left_results
    text = (out / "camera.cameramodel").read_text()
    stored = ast.literal_eval(text[text.index("{"):])
    inputs = np.load(io.BytesIO(base64.b85decode(stored["optimization_inputs"])), allow_pickle=False)
    board = inputs["observations_board"]
    views, rows, cols = board.shape[:3]
    inliers = board[..., 2].reshape(views, rows * cols) > 0
    obj = Board(cols, rows, float(inputs["calibration_object_spacing"])).object_points()
    size = tuple(int(x) for x in inputs["imagersizes"][0])
    # the file's solve again, from the corners and the inliers it names (the CLI's outlier rounds are not re-run)
    sol = calibrate_full(obj, board[..., :2].reshape(views, rows * cols, 2), size, PRESETS["default"],
                         inliers=inliers, board_warp=True)
    lens = np.array([i for i, n in enumerate(sol.names) if not n.startswith("board_sag")])
    joint = joint_covariance(sol.normal, len(sol.values), sse_of(sol), 2 * inliers_of(sol).sum())
    keep = np.r_[lens, np.arange(len(sol.values), len(joint))]
    range_ = json.loads((out / "summary.json").read_text())["projection_uncertainty"]["range"]
    ours = projection_uncertainty_map(sol.values[:4], sol.camera().coeffs(), tuple(sol.names[i] for i in lens),
                                      joint[np.ix_(keep, keep)], size, range_, (8, 6), poses=sol.poses,
                                      method="pose-compensated")
    q = np.stack(np.meshgrid(ours.u, ours.v), axis=-1).reshape(-1, 2)
    (theirs,) = _mrcal_stds([(out / "camera.cameramodel", q, range_)])
    n, p = 2 * int(inliers.sum()), len(sol.values) + 6 * views
    # both at one optimum (the re-solve stops within ~1e-6 px of the file's): the linearisation moves the ratio by
    # ~1e-7; 1e-4 holds that and fails any change of the propagation far below the 3.4 % convention it tests
    np.testing.assert_allclose(np.asarray(ours.std).ravel() / theirs, np.sqrt(n / (n - p)), rtol=1e-4, atol=0)


def test_mrcal_show_projection_diff_runs_on_two_calibrations_with_their_uncertainties(tmp_path, left_results):
    """mrcal's own comparison tool on two dstereo calibrations of one camera (OpenCV's left samples: every view,
    the module's `left_results`, and every other view, calibrated here): it fits the implied transform and weighs
    it by both files' uncertainties (their optimization inputs), and draws both valid-intrinsics regions."""
    import shutil
    import subprocess

    _mrcal_or_skip()
    tool = shutil.which("mrcal-show-projection-diff")
    if tool is None:
        pytest.skip("mrcal-show-projection-diff (Debian's mrcal package) is not installed")
    images = sorted(require_data("opencv_stereo").glob("left*.jpg"))
    folder = tmp_path / "half"
    folder.mkdir()
    for image in images[1::2]:
        (folder / image.name).symlink_to(image)  # the shared data are read in place, never copied
    code, _, err = run_cli("calibrate", "--images", folder, "--pattern", "9x6", "--model", "default", "--out",
                           tmp_path / "out", "-q")
    assert code == 0, err
    models = [str(left_results / "camera.cameramodel"), str(tmp_path / "out" / "camera.cameramodel")]
    figure = tmp_path / "diff.png"
    done = subprocess.run([tool, "--distance", "300", "--valid-intrinsics-region", "--hardcopy", str(figure), *models],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    said = done.stdout + done.stderr
    assert "Transformation cam1 <-- cam0" in said
    # the fit used both files' uncertainties: without optimization inputs mrcal warns and falls back on its
    # region-only fit ("... asked to use uncertainties, but they aren't available")
    assert "uncertainties, but they aren't available" not in said and "Uncertainty cannot be computed" not in said
    assert figure.stat().st_size > 10_000


MRCAL_RIG_CHECK = """
import copy, json, sys
import mrcal, numpy as np
out = []
for path in sys.argv[1:]:
    m = mrcal.cameramodel(path)
    oi = m.optimization_inputs()
    x = mrcal.optimizer_callback(**oi, no_jacobian=True, no_factorization=True)[1]
    again = copy.deepcopy(oi)
    mrcal.optimize(**again)
    out.append({'icam': m.icam_intrinsics(), 'cameras': int(oi['intrinsics'].shape[0]),
                'observations': int(oi['observations_board'].shape[0]), 'n_measurements': int(x.size),
                'rms': float(np.sqrt(np.sum(x ** 2) / np.sum(oi['observations_board'][..., 2] > 0))),
                'n_inlier_measurements': 2 * int(np.sum(oi['observations_board'][..., 2] > 0)),
                'intrinsics': again['intrinsics'].tolist(), 'extrinsics': again['extrinsics_rt_fromref'].tolist(),
                'warp': again['calobject_warp'].tolist(), 'file_intrinsics': m.intrinsics()[1].tolist(),
                'file_extrinsics': m.extrinsics_rt_fromref().tolist()})
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def ring_rig_files(tmp_path_factory):
    """A ring rig of three cameras (synth.ring_rig) over 14 frames, 0.1 px corner noise, a sagging board, one
    camera's view read in reversed corner order, solved jointly once for the module (the solve is the costly part:
    ~15 s of tracing), and its rig files as `calibrate --cameras` (io.cameras_files) writes them: each holds the
    joint solve as mrcal's optimization inputs, camera k its intrinsics k. Both tests below read this one solve:
    the reversed view is re-read by `as_solved` before anything is written, so the files and the covariance are
    those of an ordinary solve (measured: the uncertainty ratio below holds to 4e-10 with it, as without it)."""
    from types import SimpleNamespace

    from dstereo.calib.multiview import as_solved, calibrate_views
    from dstereo.io.cameramodel import write_cameramodels_of_rig
    from dstereo.io.cameras_files import _rig_solve
    from dstereo.models.board import Board
    from dstereo.synth import multiview_corners, multiview_poses, ring_rig
    from dstereo.synth.multiview import MULTIVIEW_BOARD

    _mrcal_or_skip()
    rig = ring_rig(3)
    poses, visible, _ = multiview_poses(rig, MULTIVIEW_BOARD, 14, 5)
    board = Board(*MULTIVIEW_BOARD.pattern, MULTIVIEW_BOARD.square)
    obj = board.object_points()
    obs = multiview_corners(rig, MULTIVIEW_BOARD, poses, visible, sag=(0.3, -0.2), noise_px=0.1, seed=5)
    seen = np.flatnonzero(visible[:, 2])[0]
    obs[seen, 2] = obs[seen, 2][::-1]  # a detection that numbered the corners from the other end
    sizes = [c.image_size for c in rig.cameras]
    sol = calibrate_views(obj, obs, visible, sizes, mode="joint", board_warp=True)
    solved_obs, solved_inliers = as_solved(obs, None, sol.flipped)  # as calibrate --cameras keeps them
    job = SimpleNamespace(solution=sol, solved_observations=solved_obs, solved_inliers=solved_inliers,
                          cameras=[SimpleNamespace(detection=SimpleNamespace(board=board))])
    solve, why = _rig_solve(job)
    assert solve is not None, why
    folder = tmp_path_factory.mktemp("ring")
    names = ["rig_a", "rig_b", "rig_c"]
    write_cameramodels_of_rig(folder, [(c.matrix(), c.coeffs(), c.dist.free, c.image_size) for c in sol.cameras],
                              names, np.concatenate([sol.rvecs, sol.T], axis=1), solve)
    return SimpleNamespace(sol=sol, obj=obj, visible=visible, seen=seen, solved=solved_obs, inliers=solved_inliers,
                           files=[folder / f"{n}.cameramodel" for n in names])


def test_every_file_of_a_three_camera_rig_carries_the_joint_solve_mrcal_reevaluates(ring_rig_files):
    """The ring rig's files (`ring_rig_files`): mrcal evaluates them to dstereo's RMS and, re-solving from them,
    moves no parameter by 1e-6 of its sigma; the reversed view was found and re-read."""
    import json
    import subprocess

    from dstereo.calib.multiview import EXTRINSIC_NAMES

    sol, visible = ring_rig_files.sol, ring_rig_files.visible
    assert (ring_rig_files.seen, 2) in sol.flipped
    files = [str(f) for f in ring_rig_files.files]
    done = subprocess.run([SYSTEM_PYTHON, "-c", MRCAL_RIG_CHECK, *files], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout)
    assert [g["icam"] for g in got] == [0, 1, 2] and all(g["cameras"] == 3 for g in got)
    assert all(g["observations"] == int(visible.sum()) for g in got)
    # the same residuals at the same parameters, computed by mrcal: rounding only (RMS_RTOL)
    assert abs(got[0]["rms"] / sol.rms - 1) < RMS_RTOL, (got[0]["rms"], sol.rms)
    sigma = dict(zip(sol.names, sol.std_jacobian if sol.std_jacobian is not None else sol.std))
    for k, cam in enumerate(sol.cameras):
        values = np.concatenate([np.asarray(cam.k), cam.coeffs()[:5]])
        np.testing.assert_array_equal(got[k]["file_intrinsics"], values)  # the file's camera is the solve's
        s = np.array([sigma[f"{sol.labels[k]}.{n}"] for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")])
        assert np.all(np.abs(np.array(got[0]["intrinsics"][k]) - values) < 1e-6 * s), k
    ext = np.concatenate([sol.rvecs, sol.T], axis=1)[1:]
    # the file holds the solve's numbers written with repr (17 digits): read back exactly, so 1e-12 mm / rad only
    # allows the Rodrigues vector's round trip through mrcal's reader, not any computation
    assert np.allclose(got[1]["file_extrinsics"], ext[0], rtol=0, atol=1e-12)
    sag_sigma = np.array([sigma["board_sag_x"], sigma["board_sag_y"]])
    assert np.all(np.abs(np.array(got[0]["warp"]) - sol.board_sag) < 1e-6 * sag_sigma)
    ext_sigma = np.array([[sigma[f"{sol.labels[k]}.{n}"] for n in EXTRINSIC_NAMES] for k in (1, 2)])
    moved = np.abs(np.array(got[0]["extrinsics"]) - ext) / ext_sigma
    assert moved.max() < 1e-6, moved.max()


@pytest.mark.parametrize("rig", ["opencv_stereo", "rig640"])
def test_a_real_stereo_rigs_files_carry_the_joint_solve_mrcal_reevaluates(tmp_path, rig):
    """Issue 35 on the shared real rigs: `calibrate --left/--right` (the K-camera job, defaults: outlier rejection,
    the board's sag) writes rig_left/rig_right.cameramodel with the joint solve stereo.yml holds as mrcal's
    optimization inputs; mrcal evaluates them to dstereo's RMS (the rejected corners marked as its outliers) and,
    re-solving from them, moves no parameter by 1e-6 of its sigma."""
    import json
    import subprocess

    from dstereo.calib.multiview import EXTRINSIC_NAMES

    _mrcal_or_skip()
    data = require_data(rig)
    out = tmp_path / "r"
    code, _, err = run_cli("calibrate", "--left", data / "left*.jpg", "--right", data / "right*.jpg", "--pattern",
                           "9x6", "--square", "25", "--out", out, "-q")
    assert code == 0, err
    joint = json.loads((out / "cameras.json").read_text())["joint"]
    files = [str(out / f"rig_{side}.cameramodel") for side in ("left", "right")]
    done = subprocess.run([SYSTEM_PYTHON, "-c", MRCAL_RIG_CHECK, *files], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout)
    assert [g["icam"] for g in got] == [0, 1] and all(g["cameras"] == 2 for g in got)
    # the same residuals at the same parameters, computed by mrcal: rounding only (RMS_RTOL)
    assert abs(got[0]["rms"] / joint["rms"] - 1) < RMS_RTOL, (got[0]["rms"], joint["rms"])
    value, sigma = joint["parameters"], joint["std_jacobian"]
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    for k, side in enumerate(("left", "right")):
        v = np.array([value[f"{side}.{n}"] for n in names])
        s = np.array([sigma[f"{side}.{n}"] for n in names])
        np.testing.assert_array_equal(got[k]["file_intrinsics"], v)  # the file's camera is the solve's
        moved = np.abs(np.array(got[0]["intrinsics"][k]) - v) / s
        assert moved.max() < 1e-6, (side, moved)
    ext = np.array([value[f"right.{n}"] for n in EXTRINSIC_NAMES])
    ext_sigma = np.array([sigma[f"right.{n}"] for n in EXTRINSIC_NAMES])
    moved = np.abs(np.array(got[0]["extrinsics"][0]) - ext) / ext_sigma
    assert moved.max() < 1e-6, moved
    sag = np.array([value["board_sag_x"], value["board_sag_y"]])
    sag_sigma = np.array([sigma["board_sag_x"], sigma["board_sag_y"]])
    assert np.all(np.abs(np.array(got[0]["warp"]) - sag) < 1e-6 * sag_sigma), (got[0]["warp"], sag)
    # each camera's written projection uncertainty (the joint solve's, calib/rig_projection.py) is mrcal's in
    # mrcal's noise convention: sqrt(N / (N - p)), N the inlier measurements, p the shared vector and the poses
    frames = json.loads((out / "cameras.json").read_text())["frames"]
    n, p = got[0]["n_inlier_measurements"], len(value) + 6 * frames
    ours, jobs = [], []
    for side, path in zip(("left", "right"), files):
        with np.load(out / f"rig_{side}_projection_uncertainty.npz") as z:
            u, v, std, range_ = z["u"], z["v"], z["std"], float(z["range"])
        pick = (slice(None, None, 4), slice(None, None, 4))  # every 4th grid pixel: 48 of the 768
        ours.append(std[pick].ravel())
        jobs.append((path, np.stack(np.meshgrid(u[pick[1]], v[pick[0]]), axis=-1).reshape(-1, 2), range_))
    for mine, theirs in zip(ours, _mrcal_stds(jobs), strict=True):
        np.testing.assert_allclose(mine / theirs, np.sqrt(n / (n - p)), rtol=1e-5, atol=0)


@pytest.mark.numerics
def test_mrcals_projection_uncertainty_of_each_rig_camera_is_dstereos_in_mrcals_noise_convention(ring_rig_files):
    """Issue 35 for rigs: the ring rig of three cameras (`ring_rig_files`: 14 frames, 0.1 px, a sagging board):
    mrcal's projection_uncertainty of each rig_<camera>.cameramodel against dstereo's map of that camera in the
    joint solve (`calib/rig_projection.py`: pose-compensated over every frame). mrcal's noise is sqrt(SSE / N),
    dstereo's sqrt(SSE / (N - p)) with p = the shared vector and every frame's pose, so every pixel of every camera
    reads sqrt(N / (N - p)) (2.1 % here; measured equal to 4e-10)."""
    from dstereo.calib.rig_projection import frames_covariance, rig_camera_map

    r = ring_rig_files
    sol, obj, solved, inliers = r.sol, r.obj, r.solved, r.inliers
    cov, n, p = frames_covariance(sol, obj, solved, inliers)
    assert n == 2 * int(r.visible.sum()) * len(obj) and p == len(sol.values) + 6 * len(sol.poses)
    maps = [rig_camera_map(sol, obj, solved, inliers, k, 900.0, grid=(8, 6), cov=cov) for k in range(len(r.files))]
    jobs = [(path, np.stack(np.meshgrid(m.u, m.v), axis=-1).reshape(-1, 2), 900.0) for path, m in zip(r.files, maps)]
    for ours, theirs in zip(maps, _mrcal_stds(jobs), strict=True):
        # one optimum, one linearisation: float rounding of two inversions; 1e-6 fails any change of the
        # propagation far below the 2 % convention it tests
        np.testing.assert_allclose(np.asarray(ours.std).ravel() / theirs, np.sqrt(n / (n - p)), rtol=1e-6, atol=0)
