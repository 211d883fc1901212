"""The reconstruction pipeline: file formats, Middlebury and synthetic truth, the results folder, bad input, CLI."""

import json
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from conftest import require_data
from dstereo.config.reconstruction import load_config
from dstereo.errors import DstereoError
from dstereo.io.calib_files import (
    StereoCalibration,
    read_middlebury_calib,
    read_pfm,
    read_stereo_calibration,
    write_opencv_stereo,
    write_pfm,
)
from dstereo.io.pointcloud import grid_faces
from dstereo.models.camera import Camera
from dstereo.stereo.disparity import PRESETS, SGBMParams, parse_overrides
from dstereo.io.images import read_image
from dstereo.jobs.reconstruct import run_reconstruction
from dstereo.stereo.reconstruct import (
    ReconstructionConfig,
    reconstruct_calibrated,
    reconstruct_uncalibrated,
    rectifying_maps,
)
from dstereo.stereo.point_outliers import remove_statistical_outliers
from dstereo.synth.objects import Sample, Sphere
from dstereo.synth.poses import look_at, pose_matrix
from dstereo.synth.render import render_object
from dstereo.synth.sensor import RenderOptions
from dstereo.synth.texture import Speckle

SCENES = ["Adirondack", "Motorcycle", "Piano", "Pipes", "Teddy"]
SUPERSAMPLE = 2
MIDDLEBURY_SGBM = SGBMParams(num_disparities=80, block_size=5, mode="hh")
RMS_RATIO = 0.85  # refined / SGBM surface RMS on the thesis-geometry pair: measured 0.0357 / 0.0461 = 0.78


# --- files ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", SCENES)
def test_middlebury_calib_is_parsed_tolerantly(scene):
    folder = require_data("middlebury2014q") / scene
    c = read_middlebury_calib(folder / "calib.txt")
    text = (folder / "calib.txt").read_text()
    assert c.rectified and c.image_size == read_image(folder / "im0.png").shape[1::-1]
    assert c.extras["doffs"] == pytest.approx(c.K2[0, 2] - c.K1[0, 2], abs=1e-3)
    assert f"{c.baseline:g}" in text.replace(" ", "")
    from dstereo.stereo.rectify import rectified_from_projections
    from dstereo.stereo.triangulate import depth_from_disparity

    r = rectified_from_projections(*c.projections(), c.image_size)
    z = depth_from_disparity(jnp.array([[20.0]]), r.Q)[0, 0]
    assert float(z) == pytest.approx(c.K1[0, 0] * c.baseline / (20.0 + c.extras["doffs"]), rel=1e-12)


def test_pfm_round_trip_and_middlebury_ground_truth(tmp_path):
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    image[1, 2] = np.inf
    write_pfm(tmp_path / "a.pfm", image)
    assert np.array_equal(read_pfm(tmp_path / "a.pfm"), image)
    rgb = np.random.default_rng(0).random((2, 3, 3)).astype(np.float32)
    write_pfm(tmp_path / "b.pfm", rgb)
    assert np.array_equal(read_pfm(tmp_path / "b.pfm"), rgb)
    gt = read_pfm(require_data("middlebury2014q") / "Teddy" / "disp0GT.pfm")
    assert gt.shape == (375, 450) and np.isinf(gt).any() and np.nanmax(gt[np.isfinite(gt)]) < 64
    (tmp_path / "bad.pfm").write_bytes(b"P5\n1 1\n255\n\x00")
    with pytest.raises(DstereoError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")


def test_opencv_yaml_files(tmp_path):
    folder = require_data("opencv_stereo")
    a = read_stereo_calibration(folder / "intrinsics.yml")
    b = read_stereo_calibration(folder / "extrinsics.yml")
    assert np.array_equal(a.K1, b.K1) and np.array_equal(a.T, b.T) and a.D1[7] == pytest.approx(-0.39963356690988139)
    calib = StereoCalibration(a.K1, a.D1, a.K2, a.D2, a.R, a.T, image_size=(640, 480))
    write_opencv_stereo(tmp_path / "stereo.yml", calib)
    c = read_stereo_calibration(tmp_path / "stereo.yml")
    assert c.image_size == (640, 480) and np.allclose(c.K2, a.K2) and np.allclose(c.D2, a.D2) and np.allclose(c.R, a.R)
    fs = cv2.FileStorage(str(tmp_path / "skew.yml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", a.K1 + np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]])), ("M2", a.K2), ("R", a.R),
                       ("T", a.T.reshape(3, 1))):
        fs.write(key, value)
    fs.release()
    with pytest.raises(DstereoError, match="skew"):
        read_stereo_calibration(tmp_path / "skew.yml")
    fs = cv2.FileStorage(str(tmp_path / "partial.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("M1", a.K1)
    fs.release()
    with pytest.raises(DstereoError, match="missing"):
        read_stereo_calibration(tmp_path / "partial.yml")


def test_config_file_sets_sgbm_and_depth_range(tmp_path):
    (tmp_path / "dstereo.toml").write_text(
        '[reconstruct]\npreset = "thesis-5.9"\nz_min = 550\nz_max = 650\nalpha = 0\n[sgbm]\nblockSize = 7\n')
    cfg = load_config(tmp_path / "dstereo.toml")
    assert cfg.depth_range == (550.0, 650.0) and cfg.alpha == 0 and cfg.sgbm.block_size == 7
    assert cfg.sgbm.min_disparity == 16 and cfg.sgbm.p1 == 216 and cfg.sgbm.p2 == 864
    (tmp_path / "bad.toml").write_text("[reconstruct]\nzmin = 3\n")
    with pytest.raises(DstereoError, match="unknown"):
        load_config(tmp_path / "bad.toml")


def test_sgbm_parameters():
    assert PRESETS["thesis-5.15"].num_disparities == 144 and PRESETS["thesis-5.15"].block_size == 11
    p = SGBMParams().with_overrides(parse_overrides(["numDisparities=32", "P1=100", "P2=400", "mode=hh"]))
    assert (p.num_disparities, p.penalties(3), p.mode) == (32, (100, 400), "hh")
    assert SGBMParams(block_size=3).penalties(1) == (72, 288)
    for bad in ({"num_disparities": 30}, {"block_size": 4}, {"mode": "fast"}, {"p1": 500, "p2": 100}):
        with pytest.raises(DstereoError):
            SGBMParams(**bad)
    with pytest.raises(DstereoError, match="NAME=VALUE"):
        parse_overrides(["block_size"])
    with pytest.raises(DstereoError, match="unknown SGBM"):
        SGBMParams().with_overrides({"window": 3})


# --- point clouds and meshes -------------------------------------------------------------------------------


def test_grid_mesh_has_no_triangles_across_depth_jumps():
    v, u = np.mgrid[0:4, 0:5].astype(float)
    flat = np.stack([u, v, np.full_like(u, 100.0)], axis=2)
    assert len(grid_faces(flat)[1]) == 2 * 3 * 4
    step = flat.copy()
    step[:, 3:, 2] = 150.0  # a depth jump between columns 2 and 3
    _, faces = grid_faces(step, max_jump=0.05)
    assert len(faces) == 2 * 3 * 3
    cols = np.argwhere(np.ones((4, 5), bool))[:, 1]
    assert not np.any((cols[faces].min(axis=1) <= 2) & (cols[faces].max(axis=1) >= 3))
    holes = flat.copy()
    holes[1, 1] = np.nan
    assert len(grid_faces(holes)[1]) == 2 * 3 * 4 - 6


def test_statistical_outlier_removal():
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:20, 0:20].astype(float)
    pts = np.stack([u, v, 100.0 + 0.01 * rng.standard_normal(u.shape)], axis=2)
    pts[5, 5] = [5.0, 5.0, 180.0]
    out = remove_statistical_outliers(pts, neighbours=8, std_ratio=2.0)
    assert np.isnan(out[5, 5]).all() and np.isfinite(out).all(axis=2).sum() >= 390


# --- Middlebury ------------------------------------------------------------------------------------------


def _teddy():
    folder = require_data("middlebury2014q") / "Teddy"
    return folder, read_middlebury_calib(folder / "calib.txt"), read_image(folder / "im0.png"), read_image(
        folder / "im1.png")


def _score(folder, calib, result):
    gt = read_pfm(folder / "disp0GT.pfm").astype(float)
    nocc = (cv2.imread(str(folder / "mask0nocc.png"), 0) == 255) & np.isfinite(gt)
    est = nocc & np.isfinite(result.disparity)
    z_gt = calib.K1[0, 0] * calib.baseline / (gt + calib.extras["doffs"])
    rel = np.abs(result.depth - z_gt)[est] / z_gt[est]
    bad2 = np.mean(np.abs(result.disparity - gt)[est] > 2.0)
    return est.sum() / nocc.sum(), float(np.median(rel)), bad2


def test_middlebury_teddy_depth_and_density():
    folder, calib, left, right = _teddy()
    result = reconstruct_calibrated(calib, left, right, ReconstructionConfig(sgbm=MIDDLEBURY_SGBM))
    density, median_rel, bad2 = _score(folder, calib, result)
    assert density >= 0.80 and median_rel <= 0.01 and bad2 < 0.10
    checked = reconstruct_calibrated(calib, left, right, ReconstructionConfig(
        sgbm=MIDDLEBURY_SGBM.with_overrides({"lr_check": 1.0})))
    density_lr, _, bad2_lr = _score(folder, calib, checked)
    assert density_lr < density and bad2_lr <= bad2


def test_mirrored_rig_gives_the_same_depths():
    """Right camera on the left (T_x > 0): matched mirrored, same scene depths."""
    _, calib, left, right = _teddy()
    normal = reconstruct_calibrated(calib, left, right, ReconstructionConfig(sgbm=MIDDLEBURY_SGBM))
    swapped = StereoCalibration(calib.K2, calib.D2, calib.K1, calib.D1, np.eye(3), -calib.T, calib.image_size,
                                rectified=True)
    mirrored = reconstruct_calibrated(swapped, right, left, ReconstructionConfig(sgbm=MIDDLEBURY_SGBM))
    assert np.nanmedian(mirrored.disparity) < 0
    assert np.nanmedian(mirrored.depth) == pytest.approx(np.nanmedian(normal.depth), rel=0.01)


# --- synthetic truth -------------------------------------------------------------------------------------


def _render_pair(cam_l, cam_r, eye_l, eye_r, target, surface, texture, up=(0.0, -1.0, 0.0)):
    pose_l, pose_r = look_at(eye_l, target, up), look_at(eye_r, target, up)
    options = RenderOptions(supersample=SUPERSAMPLE, read_noise_dn=1.0)
    left, truth = render_object(cam_l, pose_l, surface, texture, options=options, seed=1)
    right, _ = render_object(cam_r, pose_r, surface, texture, options=options, seed=2)
    T_rl = pose_matrix(pose_r) @ np.linalg.inv(pose_matrix(pose_l))
    to_bgr = lambda im: cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) if im.ndim == 2 else im  # noqa: E731
    return to_bgr(left), to_bgr(right), T_rl, pose_l, truth


@pytest.fixture(scope="module")
def thesis_sample():
    """Cork sample ~600 mm away, cameras 100 mm apart converging on it, f ~ 10,000 px, two different cameras
    (320 x 240): (calibration, left, right, left camera pose, sample)."""
    w, h = 320, 240
    cam_l = Camera.create(10000.0, 10000.0, w / 2 + 2.5, h / 2 - 2.5, [0.05, 0, 0, 0, 0], image_size=(w, h))
    cam_r = Camera.create(10050.0, 10030.0, w / 2 - 4.5, h / 2 + 0.5, [-0.03, 0, 0, 0, 0], image_size=(w, h))
    sample = Sample(recession_peak=2.0, recession_sigma=5.0)
    left, right, T_rl, pose_l, _ = _render_pair(cam_l, cam_r, [-50, 0, 652], [50, 0, 652], [0, 0, 52], sample,
                                                Speckle.create(1, size_mm=0.4))
    calib = StereoCalibration(cam_l.matrix(), cam_l.coeffs(), cam_r.matrix(), cam_r.coeffs(), T_rl[:3, :3],
                              T_rl[:3, 3], (w, h))
    return calib, left, right, pose_l, sample


THESIS_CONFIG = ReconstructionConfig(sgbm=SGBMParams(block_size=7, mode="hh", uniqueness_ratio=5),
                                     depth_range=(590, 615), uncertainty=False)


def _surface_distances(result, pose_l, sample) -> np.ndarray:
    """First-order signed distance (mm) of every reconstructed point to the true front face."""
    p = result.points[np.all(np.isfinite(result.points), axis=2)]
    m = np.linalg.inv(pose_matrix(pose_l))  # left camera -> object frame
    p_obj = jnp.asarray(p @ m[:3, :3].T + m[:3, 3])
    front = jnp.asarray(0)
    f = jax.vmap(lambda x: sample.implicit(x, front))(p_obj)
    g = jax.vmap(jax.grad(lambda x: sample.implicit(x, front)))(p_obj)
    return np.asarray(f / jnp.linalg.norm(g, axis=1))


def test_synthetic_sample_in_thesis_geometry_within_a_tenth_of_a_mm(thesis_sample):
    """The RMS distance of the reconstructed points (SGBM alone) to the true front face is <= 0.1 mm."""
    calib, left, right, pose_l, sample = thesis_sample
    result = reconstruct_calibrated(calib, left, right, THESIS_CONFIG)
    distance = _surface_distances(result, pose_l, sample)
    assert len(distance) > 0.6 * left.shape[0] * left.shape[1]
    rms = float(np.sqrt(np.mean(distance**2)))
    print(f"RMS distance to the true surface {rms:.4f} mm over {len(distance)} points")
    assert rms <= 0.1, f"RMS distance to the true surface {rms:.4f} mm"


def test_subpixel_refinement_cuts_the_surface_error(thesis_sample):
    """The same pair with `refine`: the RMS distance to the true face drops well below SGBM's (measured
    0.046 -> 0.036 mm at f = 10,000 px); every pixel the refinement kept had an SGBM disparity, the ones it dropped are NaN
    everywhere (disparity, depth, points) and counted in summary['refine']."""
    from dataclasses import replace

    calib, left, right, pose_l, sample = thesis_sample
    unfilled = replace(THESIS_CONFIG, fill=False)  # the refinement's own drops, not refilled (`stereo.fill`)
    plain = reconstruct_calibrated(calib, left, right, unfilled)
    refined = reconstruct_calibrated(calib, left, right, replace(unfilled, refine=True))
    rms = {k: float(np.sqrt(np.mean(_surface_distances(r, pose_l, sample) ** 2)))
           for k, r in (("sgbm", plain), ("refined", refined))}
    print(rms, refined.summary["refine"])
    assert rms["refined"] < RMS_RATIO * rms["sgbm"], rms
    had, kept = np.isfinite(plain.disparity), np.isfinite(refined.disparity)
    assert not np.any(kept & ~had)
    assert np.array_equal(kept, np.all(np.isfinite(refined.points), axis=2)) and np.array_equal(
        kept, np.isfinite(refined.depth))
    assert refined.summary["refine"]["dropped_fraction"] == pytest.approx((had & ~kept).sum() / had.sum())
    assert kept.sum() > 0.95 * had.sum()
    assert plain.summary["refine"] == {"enabled": False}


def test_maps_made_once_give_the_same_reconstruction(thesis_sample):
    """`rectifying_maps` made once (a sequence's frames share them) and passed in give the reconstruction made
    with maps of its own, bit for bit; the shared maps are read-only."""
    from dataclasses import replace

    calib, left, right, _, _ = thesis_sample
    config = replace(THESIS_CONFIG, refine=True)
    maps = rectifying_maps(calib, (left.shape[1], left.shape[0]), config)
    own = reconstruct_calibrated(calib, left, right, config)
    shared = reconstruct_calibrated(calib, left, right, config, maps=maps)
    for name in ("disparity", "points", "left_rect", "right_rect"):
        assert np.array_equal(getattr(own, name), getattr(shared, name), equal_nan=True), name
    assert not maps.exact[0][0].flags.writeable and not maps.outside.flags.writeable


def test_uncalibrated_path_on_a_synthetic_sphere():
    """SIFT + robust F + Hartley rectification + Q from f and baseline: depths within a few % of the truth;
    without a baseline the output is labelled unscaled."""
    w, h = 320, 240
    cam = Camera.create(400.0, 400.0, w / 2 - 0.5, h / 2 - 0.5, image_size=(w, h))
    left, right, _, _, truth = _render_pair(cam, cam, [-50, 0, -600], [50, 0, -600], [0, 0, 0], Sphere(radius=150.0),
                                            Speckle.create(3, size_mm=4.0))
    sgbm = SGBMParams(block_size=7, mode="hh")
    result = reconstruct_uncalibrated(left, right, ReconstructionConfig(sgbm=sgbm, focal_px=400.0, baseline_mm=100.0))
    H1 = result.matrices["H1"]
    v, u = np.mgrid[0:h, 0:w]
    src = np.c_[u.ravel(), v.ravel(), np.ones(u.size)] @ np.linalg.inv(H1).T
    su, sv = (np.rint(src[:, i] / src[:, 2]).astype(int) for i in (0, 1))
    inside = (su >= 0) & (su < w) & (sv >= 0) & (sv < h)
    z_true = np.full(u.size, np.nan)
    z_true[inside] = truth["depth"][sv[inside], su[inside]]
    z = result.depth.ravel()
    both = np.isfinite(z) & np.isfinite(z_true)
    assert both.sum() > 0.2 * u.size
    assert np.median(np.abs(z[both] - z_true[both]) / z_true[both]) < 0.05
    unscaled = reconstruct_uncalibrated(left, right, ReconstructionConfig(sgbm=sgbm, focal_px=400.0))
    assert not unscaled.summary["scaled"] and "UNSCALED" in unscaled.warnings[0]
    assert np.nanmedian(unscaled.depth) == pytest.approx(np.nanmedian(result.depth) / 100.0, rel=1e-6)


# --- results folder, bad input, CLI ------------------------------------------------------------------------


def _write_pair(folder: Path, left: np.ndarray, right: np.ndarray):
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "left.png"), left)
    cv2.imwrite(str(folder / "right.png"), right)
    return folder / "left.png", folder / "right.png"


def test_results_folder_is_complete_and_refuses_to_overwrite(tmp_path):
    folder, calib, _, _ = _teddy()
    out = tmp_path / "res"
    config = ReconstructionConfig(sgbm=MIDDLEBURY_SGBM)
    [result] = run_reconstruction([(folder / "im0.png", folder / "im1.png")], out, folder / "calib.txt", config)
    names = {"rectified_left.png", "rectified_right.png", "epipolar.png", "disparity.npy", "disparity.pfm",
             "disparity.png", "depth.npy", "depth.pfm", "points.npy", "points.ply", "mesh.ply", "summary.json",
             "matrices.npz"}
    assert names <= {p.name for p in out.iterdir()}
    points = np.load(out / "points.npy")
    valid = np.all(np.isfinite(points), axis=2)
    assert points.shape == (375, 450, 3) and 0.5 < valid.mean() < 1.0
    assert np.array_equal(valid, np.isfinite(np.load(out / "disparity.npy")))
    assert np.allclose(read_pfm(out / "disparity.pfm"), np.load(out / "disparity.npy"), equal_nan=True)
    cloud = trimesh.load(out / "points.ply")
    assert len(cloud.vertices) == valid.sum()
    assert np.allclose(np.asarray(cloud.vertices)[:5], points[valid][:5], rtol=1e-6)
    mesh = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.vertices) == valid.sum() and len(mesh.faces) > valid.sum()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["valid_fraction"] == pytest.approx(valid.mean())
    assert {"depth_mm", "timings_s", "sgbm", "units"} <= set(summary) and summary["units"] == "mm"
    with pytest.raises(DstereoError, match="already exists"):
        run_reconstruction([(folder / "im0.png", folder / "im1.png")], out, folder / "calib.txt", config)
    (out / "stale.txt").write_text("old")
    run_reconstruction([(folder / "im0.png", folder / "im1.png")], out, folder / "calib.txt", config, force=True)
    assert not (out / "stale.txt").exists() and [p.name for p in tmp_path.iterdir()] == ["res"]


def test_textureless_pair_fails_cleanly_and_writes_nothing(tmp_path):
    folder, _, _, _ = _teddy()
    flat = np.full((375, 450, 3), 128, np.uint8)
    left, right = _write_pair(tmp_path / "in", flat, flat)
    with pytest.raises(DstereoError, match="texture"):
        run_reconstruction([(left, right)], tmp_path / "out", folder / "calib.txt",
                           ReconstructionConfig(sgbm=MIDDLEBURY_SGBM))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_bad_pairs_are_refused(tmp_path):
    folder, _, image, _ = _teddy()
    left, right = _write_pair(tmp_path / "sizes", image, image[:-10])
    with pytest.raises(DstereoError, match="equal sizes"):
        run_reconstruction([(left, right)], tmp_path / "out", folder / "calib.txt")
    small = cv2.resize(image, (225, 188))
    left, right = _write_pair(tmp_path / "calib_size", small, small)
    with pytest.raises(DstereoError, match="calibrated size"):
        run_reconstruction([(left, right)], tmp_path / "out", folder / "calib.txt")
    with pytest.raises(DstereoError, match="does not exist"):
        run_reconstruction([(tmp_path / "nope.png", right)], tmp_path / "out", folder / "calib.txt")
    assert not (tmp_path / "out").exists()


def test_cli_reconstruct(tmp_path, monkeypatch, capsys):
    from typer.testing import CliRunner

    from dstereo import cli

    folder = require_data("middlebury2014q") / "Teddy"
    args = ["reconstruct", "--calib", str(folder / "calib.txt"), "--left", str(folder / "im0.png"), "--right",
            str(folder / "im1.png"), "--out", str(tmp_path / "r"), "--sgbm", "num_disparities=80", "--sgbm",
            "mode=hh", "--outliers", "8"]
    run = CliRunner().invoke(cli.app, args)
    assert run.exit_code == 0, run.output
    assert "valid" in run.output and (tmp_path / "r" / "summary.json").is_file()
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["sgbm"]["mode"] == "hh" and summary["config"]["outlier_neighbours"] == 8
    # the user's range is kept as given, recorded and printed (issue 14)
    assert summary["search_range"]["source"] == "--sgbm min_disparity/num_disparities"
    assert "disparity search range 0..79 px (--sgbm" in run.output
    monkeypatch.setattr("sys.argv", ["dstereo", *args])
    with pytest.raises(SystemExit) as exc:
        cli.main()
    err = capsys.readouterr().err
    assert exc.value.code == 1 and "already exists" in err and len(err.strip().splitlines()) == 1


def test_roi_keeps_points_inside_only():
    _, calib, left, right = _teddy()
    result = reconstruct_calibrated(calib, left, right, ReconstructionConfig(sgbm=MIDDLEBURY_SGBM,
                                                                             roi=(100, 50, 200, 150)))
    valid = np.all(np.isfinite(result.points), axis=2)
    assert valid[50:200, 100:300].mean() > 0.8 and not valid[:50].any() and not valid[:, 300:].any()
    assert result.summary["valid_fraction"] == pytest.approx(valid.mean())
    with pytest.raises(DstereoError, match="outside"):
        reconstruct_calibrated(calib, left, right, ReconstructionConfig(sgbm=MIDDLEBURY_SGBM, roi=(900, 0, 10, 10)))


@pytest.mark.parametrize("command", ["reconstruct", "recession"])
@pytest.mark.parametrize("bad, message", [
    (("--preset", "nonsense"), "--preset 'nonsense'"),
    (("--z-min", "500"), "give both --z-min and --z-max"),
    (("--roi", "1,2,3"), "--roi '1,2,3'"),
])
def test_matching_options_give_the_same_one_line_errors(tmp_path, command, bad, message):
    """`reconstruct` and `recession` share their matching options (commands/matching_options.py)."""
    from conftest import run_cli

    calib = tmp_path / "stereo.yml"
    calib.write_text("%YAML:1.0\n")
    if command == "reconstruct":
        args = ["reconstruct", "--calib", calib, "--left", tmp_path / "l.png", "--right", tmp_path / "r.png"]
    else:
        args = ["recession", tmp_path, "--calib", calib]
    code, _, err = run_cli(*args, "--out", tmp_path / "out", *bad)
    assert code == 1 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()
