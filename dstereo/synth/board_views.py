"""One camera's board views with known truth, for the uncertainty checks (tests and experiments alike).

Two synthetic cameras, exact corners from `board.true_corners`:
- `scene`: f 800 px, 640 x 480, k1 k2 p1 p2 k3 (`SIZE`, `FREE`, `TRUE`), a 9 x 6 board of 25 mm in V views; with
  `view_error_corners` for three error processes (independent noise, each view seeing its own camera, a board
  flexing per view), `view_effects_monte_carlo` (the spread of re-solves over fresh draws of a process against
  each covariance's prediction) and `board_fixed_spread` (a board-fixed point's projection through each draw);
- `webcam` / `iid_views`: f ~ 820 px, 640 x 480, k1 k2 (a webcam like opencv_stereo's), 9 x 6 board of 20 mm,
  iid Gaussian corner noise: the textbook case.
"""

from __future__ import annotations

import numpy as np

from dstereo.models.camera import Camera
from dstereo.synth.board import Board, object_points, true_corners
from dstereo.synth.poses import board_pose_set, invert

SIZE, PATTERN, SQUARE = (640, 480), (9, 6), 25.0
FREE = ("k1", "k2", "p1", "p2", "k3")
TRUE = (800.0, 805.0, 322.0, 238.0, (-0.25, 0.1, 1e-3, -5e-4, -0.02))
VIEWS = 16
JITTER = np.array([1.5, 1.5, 1.0, 1.0, 0.004, 0, 0, 0, 0])  # std per view of fx fy cx cy k1 (k2.. none)
FLEX_MM = 0.4  # std per view of the board's sag in x and in y (mrcal's parabola), not solved
PROCESSES = ("independent", "camera jitter", "board flex")


def true_params() -> np.ndarray:
    """(9,) fx fy cx cy k1 k2 p1 p2 k3 of the scene's camera."""
    return np.r_[TRUE[:4], TRUE[4]]


def camera(params=None) -> Camera:
    """The scene's camera, or one with `params` (fx fy cx cy k1 k2 p1 p2 k3) in its place."""
    params = true_params() if params is None else np.asarray(params, float)
    return Camera.create(*params[:4], list(params[4:]), FREE, SIZE)


def scene(n_views: int = 12, seed: int = 0):
    """(camera, true poses (V, 6), object points (n, 3), exact corners (V, n, 2)) of the scene's camera."""
    cam = camera()
    poses = board_pose_set([cam], [np.zeros(6)], Board(PATTERN, SQUARE, SQUARE), n_views, seed)
    obj = object_points(PATTERN, SQUARE)
    corners = np.stack([true_corners(cam, p, PATTERN, SQUARE) for p in poses])
    return cam, poses, obj, corners


def board_fixed_spread(cam, true_poses, draws, q, range_):
    """(D, N, 2) projections minus q of the board-fixed points through each draw's solution: the point at `range_`
    along the TRUE ray of each pixel q, mapped into each TRUE board frame, brought back with the draw's solved
    poses (mean over views) and projected by the draw's intrinsics (`draws`: solutions with `params`, `poses`)."""
    import cv2
    from scipy.spatial.transform import Rotation

    k = np.asarray(cam.k)
    K = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
    rays = np.c_[cv2.undistortPoints(q.reshape(-1, 1, 2), K, np.asarray(cam.coeffs()),
                                     criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2),
                 np.ones(len(q))]
    p = range_ * rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def apply(pose, pts):
        return Rotation.from_rotvec(pose[:3]).apply(pts) + pose[3:]

    p_board = [apply(invert(t), p) for t in true_poses]
    out = []
    for d in draws:
        back = np.mean([apply(pd, pb) for pd, pb in zip(d.poses, p_board)], axis=0)
        kd = d.params[:4]
        Kd = np.array([[kd[0], 0, kd[2]], [0, kd[1], kd[3]], [0, 0, 1.0]])
        out.append(cv2.projectPoints(back, np.zeros(3), np.zeros(3), Kd, d.params[4:])[0].reshape(-1, 2) - q)
    return np.array(out)


def view_error_corners(rng: np.random.Generator, process: str, poses, obj) -> np.ndarray:
    """(V, n, 2) observed corners of the scene's camera under one error process:
    - `independent`: N(0, 0.2 px) per corner coordinate (every covariance should be the Jacobian's);
    - `camera jitter`: 0.1 px plus each view seeing its own camera (fx, fy +- 1.5 px, cx, cy +- 1 px, k1 +- 0.004:
      the random-effects model's own premise);
    - `board flex`: 0.1 px plus each view's board sagging by its own N(0, FLEX_MM) in x and in y, the sag not
      solved: a process the random-effects model does not contain."""
    base = true_params()
    out = []
    for p in poses:
        params = base + (rng.normal(0, JITTER) if process == "camera jitter" else 0.0)
        if process == "board flex":
            import cv2
            from scipy.spatial.transform import Rotation

            from dstereo.calib.problem import sag_basis

            pts = obj.copy()
            pts[:, 2] += sag_basis(obj) @ rng.normal(0, FLEX_MM, 2)
            cam = Rotation.from_rotvec(p[:3]).apply(pts) + p[3:]
            k = np.array([[base[0], 0, base[2]], [0, base[1], base[3]], [0, 0, 1.0]])
            out.append(cv2.projectPoints(cam, np.zeros(3), np.zeros(3), k, base[4:])[0].reshape(-1, 2))
        else:
            out.append(true_corners(camera(params), p, PATTERN, SQUARE))
    sigma = 0.2 if process == "independent" else 0.1
    return np.array(out) + rng.normal(0, sigma, (len(poses), len(obj), 2))


def process_views(process: str, views: int, seed: int = 0, pose_seed: int | None = None):
    """(object points, observed corners (V, n, 2)) of one draw of `process` (rng seeded by `seed`, poses by
    `pose_seed`, default `seed`)."""
    rng = np.random.default_rng(seed)
    poses = board_pose_set([camera()], [np.zeros(6)], Board(PATTERN, SQUARE, SQUARE), views,
                           seed if pose_seed is None else pose_seed)
    obj = object_points(PATTERN, SQUARE)
    return obj, view_error_corners(rng, process, poses, obj)


def view_effects_monte_carlo(process: str, draws: int, seed: int = 0, views: int = VIEWS):
    """The spread of `draws` re-solves (fresh errors of `process` each, all views) against three predicted
    covariances (the Jacobian's; it times max(1, kappa), the view scatter; the random effects of
    `uncertainty.view_effects`): rows (process, covariance, mean predicted / MC std per parameter, mean
    e' C^-1 e / G of the draws' deviations from the MC mean under each draw's own prediction), the parameter
    names, the number of converged draws. 1 is right in both figures."""
    from dstereo.calib.mono import _residual_weights, _run, _shared, calibrate_full
    from dstereo.solver.lm import LMOptions
    from dstereo.uncertainty.covariance import covariance
    from dstereo.uncertainty.view_effects import view_effects
    from dstereo.uncertainty.view_scatter import view_scatter

    rng = np.random.default_rng(seed)
    poses = board_pose_set([camera()], [np.zeros(6)], Board(PATTERN, SQUARE, SQUARE), views, seed)
    obj = object_points(PATTERN, SQUARE)
    obs = np.stack([view_error_corners(rng, process, poses, obj) for _ in range(draws)])
    nominal = calibrate_full(obj, obs[0], SIZE, FREE)
    k, g = draws, len(nominal.values)
    opts = LMOptions()
    free = nominal.camera().dist.free
    res = _run(free, opts, np.repeat(nominal.values[None], k, 0), np.repeat(nominal.poses[None], k, 0), obs,
               np.ones((k, views)), np.full(k, opts.lambda0), _shared(obj),
               r_weight=np.repeat(_residual_weights(np.ones((views, len(obj)), bool))[None], k, 0))
    est = np.asarray(res.g)
    ok = np.asarray(res.status) > 0
    dev = est[ok] - est[ok].mean(axis=0)
    mc = dev.T @ dev / (len(dev) - 1)
    n_res, dof = 2 * views * len(obj), 2 * views * len(obj) - g - 6 * views
    preds = {"jacobian": [], "view scatter": [], "random effects": []}
    for i in np.flatnonzero(ok):
        sse = float(res.sse[i])
        jac = covariance(np.asarray(res.schur[i]), sse, n_res, g + 6 * views)
        normal = np.asarray(res.normal[i])
        preds["jacobian"].append(jac)
        preds["view scatter"].append(max(1.0, view_scatter(normal, g, sse / dof).kappa) * jac)
        preds["random effects"].append(view_effects(normal, g, sse / dof, dof).cov)
    rows = []
    for name, covs in preds.items():
        covs = np.array(covs)
        std_ratio = np.sqrt(np.mean(covs[:, range(g), range(g)], axis=0) / np.diag(mc))
        m2 = np.mean([d @ np.linalg.solve(c, d) for d, c in zip(dev, covs)]) / g
        rows.append((process, name, std_ratio, m2))
    return rows, nominal.names, int(ok.sum())


def webcam(coeffs=(-0.25, 0.12), free=("k1", "k2")) -> Camera:
    """The webcam-like camera: 640 x 480, f ~ 820 px (like opencv_stereo's), known distortion."""
    return Camera.create(820.0, 818.0, 322.0, 236.0, coeffs, free=free, image_size=(640, 480))


def iid_views(cam: Camera, n_views: int, noise_px: float, seed: int = 0, square: float = 20.0):
    """(obj, obs) of a 9 x 6 board: iid Gaussian noise on the true corners, the textbook case."""
    poses = board_pose_set([cam], [np.zeros(6)], Board(PATTERN, square, square), n_views, seed)
    truth = np.stack([true_corners(cam, p, PATTERN, square) for p in poses])
    return object_points(PATTERN, square), truth + np.random.default_rng(seed + 1).normal(0, noise_px, truth.shape)


# Sensor noise of a rendered calibration: Poisson shot noise (1000 e- at white), 2 DN read noise, the usual 1 px
# lens blur (the exposure of experiments/projection_mc_rendered.py).
RENDERED_NOISE = dict(supersample=2, defocus_sigma_px=1.0, full_well=1000.0, read_noise_dn=2.0)


def rendered_views(cam: Camera, n_views: int, seed: int, square: float = 20.0):
    """(object points (n, 3), detected corners (V', n, 2)) of `n_views` board views of `cam` rendered with sensor
    noise (`RENDERED_NOISE`; poses and noise from `seed`) and detected by the project's detector; a view the
    detector misses is left out, as `dstereo calibrate` leaves it out."""
    from dstereo.io.corners import _detect_one
    from dstereo.synth.scenes import calibration_set
    from dstereo.synth.sensor import RenderOptions

    rendered = calibration_set(cam, pattern=PATTERN, square=square, n_views=n_views, seed=seed,
                               options=RenderOptions(**RENDERED_NOISE))
    found = [q for q in (_detect_one(img if img.ndim == 2 else img[..., 0], PATTERN)[0] for img in rendered.left)
             if q is not None]
    return np.asarray(rendered.truth["object_points"], float), np.stack(found)
