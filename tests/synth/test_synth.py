"""Renderer truth: corners vs live OpenCV detection, depth maps vs closed-form surfaces, determinism, rig truth,
recession truth. Truth is checked with code independent of the renderer (cv2 ray inversion, numpy geometry)."""

import json

import cv2
import jax
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.models import Camera
from dstereo.synth import (
    CALIBRATION_OPTIONS, Board, Plane, RenderOptions, Sample, Sphere, Speckle, board_pose_set, calibration_set,
    camera_rays, corner_coverage, look_at, plasmatron_rig, pose_matrix, read_truth, recession_sequence,
    render_board, render_object, sample_pair, true_corners, write_calibration_set, write_render, write_stereo_renders,
)

W, H = 640, 480
PATTERN = (9, 6)
# Distortion catalogue (OpenCV order k1, k2, p1, p2, k3, k4, k5, k6) with a focal length each.
CORNER_MODELS = {
    "none": (1.2 * W, None),
    "k1k2k3p1p2_moderate": (1.2 * W, [-0.25, 0.12, 0.001, -0.0015, -0.03]),
    "rational_strong": (0.9 * W, [2.0, 0.8, 0.0005, -0.0008, 0.05, 2.6, 1.6, 0.2]),
}
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
SMALL = (320, 240)
OBJECT_TEST_OPTIONS = RenderOptions(supersample=2)


def _camera(focal, coeffs, size=(W, H)):
    w, h = size
    return Camera.create(focal, focal * 1.002, (w - 1) / 2 + 3.0, (h - 1) / 2 - 2.0, coeffs, image_size=size)


def _detect(image):
    """OpenCV at the edge: findChessboardCorners, then cornerSubPix with an 11 x 11 window."""
    found, corners = cv2.findChessboardCorners(image, PATTERN)
    if not found:
        return None
    return cv2.cornerSubPix(image, corners, (5, 5), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)


def _aligned(detected, truth):
    """OpenCV may list the corners from the opposite end; compare in the order that matches."""
    forward = np.sum((detected[0] - truth[0]) ** 2) < np.sum((detected[-1] - truth[0]) ** 2)
    return detected if forward else detected[::-1]


def _rms(a, b):
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


# --- chessboard -----------------------------------------------------------------------------------------------
def test_true_corners_match_cv2_project_points():
    focal, coeffs = CORNER_MODELS["rational_strong"]
    cam = _camera(focal, coeffs)
    pose = np.array([0.3, -0.2, 0.1, -15.0, -10.0, 160.0])
    obj = np.array([(x * 4.0, y * 4.0, 0.0) for y in range(6) for x in range(9)])  # OpenCV samples' order
    ref, _ = cv2.projectPoints(obj, pose[:3], pose[3:], cam.matrix(), cam.coeffs())
    np.testing.assert_allclose(true_corners(cam, pose, PATTERN, 4.0), ref.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("model", sorted(CORNER_MODELS))
def test_detected_corners_match_truth(model):
    """Noise-free renders (1 px lens blur): cornerSubPix agrees with the true corners to <= 0.05 px RMS."""
    focal, coeffs = CORNER_MODELS[model]
    cam = _camera(focal, coeffs)
    board = Board(PATTERN, 4.0, 4.0)
    poses = board_pose_set([cam], [np.zeros(6)], board, n_views=6, seed=11)
    rays = camera_rays(cam, CALIBRATION_OPTIONS.supersample)
    errors = []
    for pose in poses:
        image, truth = render_board(cam, pose, board, CALIBRATION_OPTIONS, rays=rays)
        detected = _detect(image)
        assert detected is not None, f"{model}: OpenCV found no board at pose {pose.round(3)}"
        errors.append(_aligned(detected, truth["corners"]) - truth["corners"])
    rms = float(np.sqrt(np.mean(np.sum(np.concatenate(errors) ** 2, axis=1))))
    assert rms <= 0.05, f"{model}: corner RMS {rms:.4f} px"


def test_board_pose_set_covers_corners_and_respects_tilt():
    cam = _camera(*CORNER_MODELS["k1k2k3p1p2_moderate"])
    board = Board(PATTERN, 4.0, 4.0)
    poses = board_pose_set([cam], [np.zeros(6)], board, n_views=9, seed=5, max_tilt_deg=45.0)
    tilts = np.degrees(np.arccos([pose_matrix(p)[2, 2] for p in poses]))
    assert np.all(tilts <= 45.0 + 1e-9) and np.max(tilts) > 25.0
    corners = np.concatenate([true_corners(cam, p, PATTERN, 4.0) for p in poses])
    assert np.all((corners >= 0) & (corners <= np.array([W - 1, H - 1])))
    cover = corner_coverage(corners, (W, H))
    assert min(cover["upper_left"], cover["lower_left"], cover["upper_right"], cover["lower_right"]) > 12.0
    # Points reach into every image corner (outer tenth of width and height).
    for cu, cv in [(0, 0), (1, 0), (0, 1), (1, 1)]:
        du = np.abs(corners[:, 0] / (W - 1) - cu)
        dv = np.abs(corners[:, 1] / (H - 1) - cv)
        assert np.any((du < 0.2) & (dv < 0.2)), f"no board point near image corner {(cu, cv)}"


@pytest.mark.parametrize("model", sorted(CORNER_MODELS))
def test_rays_match_camera_unproject(model):
    """The renderer's fast Newton inverse equals the model's `Camera.unproject` at every sub-pixel sample."""
    cam = _camera(*CORNER_MODELS[model], size=SMALL)
    rays = np.asarray(camera_rays(cam, 2))
    rng = np.random.default_rng(0)
    v, u, k = rng.integers(0, SMALL[1], 50), rng.integers(0, SMALL[0], 50), rng.integers(0, 4, 50)
    q = np.stack([u + (k % 2 + 0.5) / 2 - 0.5, v + (k // 2 + 0.5) / 2 - 0.5], axis=1)  # 2 x 2 samples, row-major
    expected = np.asarray(jax.jit(jax.vmap(Camera.unproject, in_axes=(None, 0)))(cam, q))[:, :2]
    # The same Newton inverse, 12 steps in the renderer and 8 in Camera.unproject: both reach Newton's fixed point
    # (quadratic convergence), so they differ by rounding of O(1) values (measured <= 6e-17)
    np.testing.assert_allclose(rays[v, u, k], expected, rtol=0, atol=1e-13)


def test_board_rejects_symmetric_pattern_and_non_invertible_lens():
    with pytest.raises(DstereoError, match="odd"):
        Board((9, 7), 4.0)
    cam = _camera(0.4 * W, [-1.5, 0.0, 0.0, 0.0, 0.0], size=SMALL)  # folds back before the image corner
    with pytest.raises(DstereoError, match="not invertible"):
        camera_rays(cam, 1)


# --- stereo rig -----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rig_set():
    rig = plasmatron_rig()
    return rig, calibration_set(rig.left, rig.right, rig.T_right_left, n_views=4, seed=3)


def test_stereo_truth_matches_rig_relation(rig_set):
    rig, cset = rig_set
    t = cset.truth
    r_rl, t_rl = np.array(t["R"]), np.array(t["T"])
    obj = t["object_points"]
    for pose, c_left, c_right in zip(t["poses_left"], t["corners_left"], t["corners_right"]):
        # Independent composition with OpenCV: T_right_board = T_right_left o T_left_board.
        rvec_r, tvec_r = cv2.composeRT(pose[:3, None], pose[3:, None], cv2.Rodrigues(r_rl)[0], t_rl[:, None])[:2]
        ref, _ = cv2.projectPoints(obj, rvec_r, tvec_r, rig.right.matrix(), rig.right.coeffs())
        np.testing.assert_allclose(c_right, ref.reshape(-1, 2), atol=1e-8)
        ref_l, _ = cv2.projectPoints(obj, pose[:3], pose[3:], rig.left.matrix(), rig.left.coeffs())
        np.testing.assert_allclose(c_left, ref_l.reshape(-1, 2), atol=1e-8)
    # stereoCalibrate with fixed intrinsics recovers the rig from the true corners (float32 inputs: ~1e-5 px).
    f32 = lambda arrays: [a.astype(np.float32) for a in arrays]  # noqa: E731
    out = cv2.stereoCalibrate(
        f32([obj] * len(t["poses_left"])), f32(t["corners_left"]), f32(t["corners_right"]), rig.left.matrix(),
        rig.left.coeffs().copy(), rig.right.matrix(), rig.right.coeffs().copy(), (W, H), flags=cv2.CALIB_FIX_INTRINSIC)
    rms, r_est, t_est = out[0], out[5], out[6]
    assert rms < 1e-3
    np.testing.assert_allclose(r_est, r_rl, atol=2e-6)
    np.testing.assert_allclose(t_est.ravel(), t_rl, atol=2e-3)
    assert abs(np.linalg.norm(t_rl) - 100.0) < 1e-9  # the thesis's ~100 mm baseline


def test_stereo_renders_detect_at_truth(rig_set):
    _, cset = rig_set
    for side, images in (("left", cset.left), ("right", cset.right)):
        for image, truth in zip(images, cset.truth[f"corners_{side}"]):
            detected = _detect(image)
            assert detected is not None, f"{side}: board not found"
            assert _rms(_aligned(detected, truth), truth) <= 0.05


def test_board_depth_truth_matches_closed_form(rig_set):
    rig, cset = rig_set
    truth = cset.views_right[2]
    o, d = _object_frame(_cv2_rays(rig.right), truth["pose_cam_board"])
    t = -o[2] / d[..., 2]
    p = o + t[..., None] * d
    # 9 x 6 inner corners, 3.75 mm squares: squares reach one square beyond the outer corners, the margin one more.
    x0, y0, x1, y1 = -3.75 * 2, -3.75 * 2, 3.75 * 10, 3.75 * 7
    on_board = (p[..., 0] >= x0) & (p[..., 0] <= x1) & (p[..., 1] >= y0) & (p[..., 1] <= y1)
    depth = truth["depth"]
    assert np.sum(np.isfinite(depth) != on_board) <= 2 and on_board.mean() > 0.1
    both = on_board & np.isfinite(depth)
    assert np.max(np.abs(depth[both] - t[both]) / t[both]) <= 1e-6
    assert np.all(truth["corners_in_image"])


def test_calibration_set_is_deterministic_and_written_with_truth(rig_set, tmp_path):
    rig, cset = rig_set
    noisy = RenderOptions(supersample=1, read_noise_dn=2.0, full_well=2000.0, vignetting=0.3, defocus_sigma_px=0.7)
    a = calibration_set(rig.left, rig.right, rig.T_right_left, n_views=2, seed=9, options=noisy)
    b = calibration_set(rig.left, rig.right, rig.T_right_left, n_views=2, seed=9, options=noisy)
    c = calibration_set(rig.left, rig.right, rig.T_right_left, n_views=2, seed=10, options=noisy)
    png = lambda img: cv2.imencode(".png", img)[1].tobytes()  # noqa: E731
    assert [png(i) for i in a.left + a.right] == [png(i) for i in b.left + b.right]
    assert png(a.left[0]) != png(c.left[0])
    folder = write_calibration_set(tmp_path / "cal", a)
    names = sorted(p.name for p in (folder / "images_left").iterdir())
    assert names[:3] == ["left_00.json", "left_00.npz", "left_00.png"] and len(names) == 6
    back = read_truth(folder / "images_right", "right_01")
    np.testing.assert_array_equal(back["corners"], a.views_right[1]["corners"])
    np.testing.assert_array_equal(cv2.imread(str(folder / "images_right" / "right_01.png"), 0), a.right[1])
    assert json.loads((folder / "truth.json").read_text())["board"]["square"] == 3.75
    with pytest.raises(DstereoError, match="already exists"):
        write_calibration_set(tmp_path / "cal", a)


# --- objects and depth truth ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def object_camera():
    cam = _camera(1.25 * SMALL[0], [-0.25, 0.12, 0.001, -0.0015, -0.03], size=SMALL)
    return cam, camera_rays(cam, OBJECT_TEST_OPTIONS.supersample), camera_rays(cam, 1)


def _cv2_rays(cam):
    """Pixel-centre rays (x, y, 1) by OpenCV's own iterative inversion, independent of the renderer."""
    w, h = cam.image_size
    v, u = np.mgrid[0:h, 0:w].astype(float)
    q = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    xy = cv2.undistortPoints(q, cam.matrix(), cam.coeffs(), criteria=crit).reshape(h, w, 2)
    return np.concatenate([xy, np.ones((h, w, 1))], axis=-1)


def _object_frame(cam_rays, pose):
    m = pose_matrix(pose)
    r = m[:3, :3]
    return -r.T @ m[:3, 3], cam_rays @ r  # origin, directions (h, w, 3) in the object frame


def _render(object_camera, surface, pose, seed=0):
    cam, rays, centre = object_camera
    return render_object(cam, pose, surface, Speckle.create(seed), options=OBJECT_TEST_OPTIONS, seed=seed,
                         rays=rays, centre_rays=centre)


def test_plane_depth_matches_closed_form(object_camera):
    cam = object_camera[0]
    pose = look_at([40.0, -30.0, -120.0], [5.0, 3.0, 0.0], up=(0.0, -1.0, 0.0))  # T_cam_plane, ~26 deg oblique
    plane = Plane(40.0, 30.0)
    _, truth = _render(object_camera, plane, pose)
    o, d = _object_frame(_cv2_rays(cam), pose)
    t = -o[2] / d[..., 2]
    p = o + t[..., None] * d
    inside = (t > 0) & (np.abs(p[..., 0]) <= 40.0) & (np.abs(p[..., 1]) <= 30.0)
    depth = truth["depth"]
    assert 0.2 < inside.mean() < 0.95
    assert np.sum(np.isfinite(depth) != inside) <= 2
    both = inside & np.isfinite(depth)
    assert np.max(np.abs(depth[both] - t[both]) / t[both]) <= 1e-6


def test_sphere_depth_matches_closed_form(object_camera):
    cam = object_camera[0]
    pose = np.array([0.2, -0.3, 0.1, 8.0, -5.0, 140.0])
    _, truth = _render(object_camera, Sphere(30.0), pose)
    o, d = _object_frame(_cv2_rays(cam), pose)
    a, b, c = np.sum(d * d, -1), 2 * (d @ o), o @ o - 30.0**2
    disc = b * b - 4 * a * c
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)  # nearer root: camera is outside
    hit = disc > 0
    depth = truth["depth"]
    assert 0.1 < hit.mean() < 0.9
    assert np.sum(np.isfinite(depth) != hit) <= 2
    both = hit & np.isfinite(depth)
    assert np.max(np.abs(depth[both] - t[both]) / t[both]) <= 1e-6


def _sample_numpy(s: Sample):
    """Front height and side radius of the sample, written again in numpy from the documented formulas."""
    h, a = (s.dome_height, s.head_radius)

    def front(rho2):
        rs = (a * a + h * h) / (2 * h) if h > 0 else 0.0
        cap = np.sqrt(rs * rs - np.minimum(rho2, a * a)) - (rs - h) if h > 0 else 0.0
        return s.length + cap - s.recession_uniform - s.recession_peak * np.exp(-rho2 / (2 * s.recession_sigma**2))

    def side(z):
        return s.base_radius + (s.head_radius - s.base_radius) * z / s.length

    def inside(p):
        rho2 = p[..., 0] ** 2 + p[..., 1] ** 2
        return (p[..., 2] >= 0) & (p[..., 2] <= front(rho2)) & (rho2 <= side(p[..., 2]) ** 2)

    return front, side, inside


@pytest.mark.parametrize("variant", ["flat", "dome", "dome_receded"])
def test_sample_depth_lies_on_the_analytic_surface(object_camera, variant):
    cam = object_camera[0]
    sample = {"flat": Sample.flat(), "dome": Sample(),
              "dome_receded": Sample(recession_uniform=0.8, recession_peak=1.2, recession_sigma=7.0)}[variant]
    pose = look_at([70.0, -45.0, 190.0], [0.0, 0.0, 38.0], up=(0.0, 0.0, 1.0))  # ~28 deg off the axis
    _, truth = _render(object_camera, sample, pose)
    depth = truth["depth"]
    o, d = _object_frame(_cv2_rays(cam), pose)
    front, side, inside = _sample_numpy(sample)
    hit = np.isfinite(depth)
    p = o + depth[hit][:, None] * d[hit]
    rho = np.hypot(p[:, 0], p[:, 1])
    residual = np.minimum(np.abs(p[:, 2] - front(rho**2)), np.abs(rho - side(p[:, 2])))
    assert 0.1 < hit.mean() < 0.9
    assert np.max(residual / depth[hit]) <= 1e-6
    parts = truth["part"][hit]
    assert np.sum(parts == 1) > 100 and np.sum(parts == 0) > 1000  # both the side and the front face are seen
    # First hit: just before it the ray is still outside the solid; rays marked background never enter it.
    assert not np.any(inside(o + 0.9999 * depth[hit][:, None] * d[hit]))
    miss_dirs = d[~hit][::7]
    for t in np.linspace(100.0, 320.0, 600):
        assert not np.any(inside(o + t * miss_dirs))


def test_object_render_is_deterministic(object_camera):
    pose = np.array([0.2, -0.3, 0.1, 8.0, -5.0, 140.0])
    noisy = RenderOptions(supersample=2, read_noise_dn=1.5, full_well=3000.0, vignetting=0.2, defocus_sigma_px=0.6)
    cam, rays, centre = object_camera

    def run(seed):
        return render_object(cam, pose, Sphere(30.0), Speckle.create(seed), options=noisy, seed=seed, rays=rays,
                             centre_rays=centre)

    (a, ta), (b, tb), (c, _) = run(4), run(4), run(5)
    assert a.tobytes() == b.tobytes() and np.array_equal(ta["depth"], tb["depth"], equal_nan=True)
    assert a.tobytes() != c.tobytes()
    assert np.std(a[np.isfinite(ta["depth"])]) > 20  # the speckle is there


# --- sample pair and recession --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_rig():
    return plasmatron_rig(image_size=SMALL, focal_px=2400.0)


def test_sample_pair_both_cameras_see_the_same_surface_point(small_rig, tmp_path):
    pair = sample_pair(small_rig, seed=2, options=OBJECT_TEST_OPTIONS)
    rig = small_rig
    stag_obj = np.array(pair.truth_left["surface"]["stagnation_point"])
    for cam, truth in ((rig.left, pair.truth_left), (rig.right, pair.truth_right)):
        m = pose_matrix(truth["pose_cam_object"])
        p = m[:3, :3] @ stag_obj + m[:3, 3]
        q, _ = cv2.projectPoints(p[None], np.zeros(3), np.zeros(3), cam.matrix(), cam.coeffs())
        u, v = np.rint(q.ravel()).astype(int)
        # The depth at the pixel nearest the stagnation point is within a hair of the point's own depth.
        assert abs(truth["depth"][v, u] - p[2]) < 0.05
        assert 595.0 < p[2] < 600.0  # head circle 600 mm from each camera, dome apex 4 mm nearer
    # The relative pose in the truth is the rig's.
    t_left, t_right = (pose_matrix(t["pose_cam_object"]) for t in (pair.truth_left, pair.truth_right))
    rel = t_right @ np.linalg.inv(t_left)
    np.testing.assert_allclose(rel, pose_matrix(rig.T_right_left), atol=1e-9)
    write_render(tmp_path, pair.left, pair.truth_left, name="left")
    assert np.array_equal(read_truth(tmp_path, "left")["depth"], pair.truth_left["depth"], equal_nan=True)


def test_recession_sequence_truth(small_rig, tmp_path):
    frames = recession_sequence(small_rig, n_frames=10, duration_s=40.0, seed=1, options=OBJECT_TEST_OPTIONS)
    times = np.array([f.truth_left["time_s"] for f in frames])
    stag = np.array([f.truth_left["recession_stagnation_mm"] for f in frames])
    assert len(frames) == 10 and np.all(np.diff(times) > 0)
    # stag[-1] = (0.02 + 0.03) mm/s x 40 s: two roundings of 2.0
    assert stag[0] == 0.0 and np.all(np.diff(stag) > 0) and abs(stag[-1] - 2.0) < 1e-12
    prof = frames[0].truth_left["profile"]
    # The profile is linear in time: both sides are the same two products, rounding only.
    np.testing.assert_allclose(stag, (prof["uniform_rate"] + prof["peak_rate"]) * times, rtol=1e-12)
    base = Sample()
    for f, r in zip(frames, stag):
        s = f.truth_left["surface"]
        assert abs(s["stagnation_point"][2] - (base.length + base.dome_height - r)) < 1e-9
        assert f.truth_left["time_s"] == f.truth_right["time_s"]
    # The depth at the stagnation pixel grows as the face (locally flat there, normal n along the axis) moves
    # back: a ray p = Z (x, y, 1) meets n . p = c - r at Z + r / (-n . (x, y, 1)).
    m = pose_matrix(frames[0].truth_left["pose_cam_object"])
    n_cam = m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    p0 = m[:3, :3] @ np.array(frames[0].truth_left["surface"]["stagnation_point"]) + m[:3, 3]
    q, _ = cv2.projectPoints(p0[None], np.zeros(3), np.zeros(3), small_rig.left.matrix(), small_rig.left.coeffs())
    u, v = np.rint(q.ravel()).astype(int)
    depth = np.array([f.truth_left["depth"][v, u] for f in frames])
    assert np.all(np.diff(depth) > 0)
    np.testing.assert_allclose(depth - depth[0], stag / -(n_cam @ (p0 / p0[2])), atol=0.005)
    assert not np.array_equal(frames[0].left, frames[-1].left)
    folder = write_stereo_renders(tmp_path / "seq", frames)
    index = json.loads((folder / "index.json").read_text())
    assert [e["time_s"] for e in index] == times.tolist() and index[-1]["right"] == "images_right/right_009.png"
    assert read_truth(folder / "images_right", "right_004")["time_s"] == times[4]
