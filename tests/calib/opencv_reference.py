"""OpenCV reference computations the tests (and `make bench`'s K = 3 case) compare dstereo with; never inside dstereo/.

- `calibrate_multiview`: OpenCV 5's `cv2.calibrateMultiviewExtended`, called correctly (below), with `opencv_cameras`
  (dstereo Cameras holding its K and D) and `float32_corners`;
- `held_out_rms`: leave-one-view-out held-out RMS with cv2.fisheye.calibrate / cv2.calibrateCamera and a scipy pose
  refit of the left-out view (the independent twin of `--model auto`'s held-out error).

What calibrateMultiviewExtended needs, each found by calling it (issue 17):
- object points in metres, float32, one (n, 3) array per frame: it divides them by their largest squared
  pairwise distance, so in mm the board shrinks below its collinearity test's 1e-6 and it reports collinear
  points; its translations come back in the input unit (converted back to mm here);
- image points float32, one (n, 1, 2) array per (camera, frame), an empty (0, 1, 2) array with mask 0 where the
  camera did not see the frame; the mask is (K, F) uint8, the models (K,) uint8;
- `Rs` come back as rotation vectors (not matrices); frame poses (camera 0's) only from the Extended variant;
- a frame's corners in the same order in every camera (`dstereo.io.corner_order`);
- `CALIB_USE_INTRINSIC_GUESS` in `flags` skips its per-camera `calibrateCamera` and holds the given K and D
  through its final optimisation, which refines camera extrinsics and frame poses only (it never refines
  intrinsics jointly, with or without the flag).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MM_PER_M = 1000.0
FIVE = ("k1", "k2", "p1", "p2", "k3")


@dataclass
class OpenCVMultiview:
    """calibrateMultiviewExtended's answer in dstereo's units: K (K, 3, 3), D (K, n_coeffs), R (K, 3, 3) and T
    (K, 3) mm with x_cam_k = R_k x_ref + T_k, frame poses rvecs0 / tvecs0 (F, 3) (mm) of camera 0, the overall
    RMS (px), per-frame RMS (F, K) with NaN where not seen, and the initialisation pairs."""

    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    T: np.ndarray
    rvecs0: np.ndarray
    tvecs0: np.ndarray
    rms: float
    per_view_rms: np.ndarray
    pairs: np.ndarray


def float32_corners(obs: np.ndarray) -> np.ndarray:
    """The corners rounded to float32 as OpenCV receives them (hand the same to dstereo for a 1:1 comparison)."""
    return np.asarray(obs, np.float32).astype(np.float64)


def calibrate_multiview(obj_mm, obs, visible, image_sizes, K0=None, D0=None, n_coeffs: int = 5,
                        criteria=None) -> OpenCVMultiview:
    """Run cv2.calibrateMultiviewExtended on obs (F, K, n, 2) px, visible (F, K), obj_mm (n, 3) mm.

    With K0 (K, 3, 3) and D0 (K, n_coeffs) it holds them (CALIB_USE_INTRINSIC_GUESS); otherwise it first
    calibrates each camera on its own with calibrateCamera (default flags: k1, k2, p1, p2, k3).
    """
    import cv2

    obs = np.asarray(obs, float)
    visible = np.asarray(visible, bool)
    n_frames, n_cams = visible.shape
    obj_m = (np.asarray(obj_mm, float) / MM_PER_M).astype(np.float32)
    obj_points = [obj_m for _ in range(n_frames)]
    empty = np.zeros((0, 1, 2), np.float32)
    image_points = [[obs[f, k].astype(np.float32).reshape(-1, 1, 2) if visible[f, k] else empty
                     for f in range(n_frames)] for k in range(n_cams)]
    sizes = [tuple(int(v) for v in s) for s in image_sizes]
    mask = np.ascontiguousarray(visible.T.astype(np.uint8))
    models = np.full(n_cams, cv2.CALIB_MODEL_PINHOLE, np.uint8)
    guess = K0 is not None
    Ks = [np.asarray(k, np.float64) for k in K0] if guess else None
    Ds = [np.asarray(d, np.float64).reshape(1, -1) for d in D0] if guess else None
    flags = cv2.CALIB_USE_INTRINSIC_GUESS if guess else 0
    flags_intr = np.zeros((n_cams, 1), np.int32)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-15) if criteria is None else criteria
    out = cv2.calibrateMultiviewExtended(obj_points, image_points, sizes, mask, models, Ks, Ds, None, None,
                                         flagsForIntrinsics=flags_intr, flags=flags, criteria=criteria)
    rms, Ks, Ds, Rs, Ts, pairs, rvecs0, tvecs0, per_frame = out
    rot = np.stack([cv2.Rodrigues(np.asarray(r, float).reshape(3))[0] for r in Rs])
    per = np.asarray(per_frame, float).reshape(n_cams, n_frames).T
    return OpenCVMultiview(
        K=np.stack([np.asarray(k, float) for k in Ks]),
        D=np.stack([np.asarray(d, float).ravel()[:n_coeffs] for d in Ds]),
        R=rot, T=np.stack([np.asarray(t, float).reshape(3) for t in Ts]) * MM_PER_M,
        rvecs0=np.stack([np.asarray(r, float).reshape(3) for r in rvecs0]),
        tvecs0=np.stack([np.asarray(t, float).reshape(3) for t in tvecs0]) * MM_PER_M,
        rms=float(rms), per_view_rms=np.where(per < 0, np.nan, per), pairs=np.asarray(pairs))


def opencv_cameras(cv: OpenCVMultiview, image_sizes):
    """dstereo Cameras holding OpenCV's K and D (k1, k2, p1, p2, k3)."""
    from dstereo.models.camera import Camera

    return [Camera.create(k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[:5], free=FIVE, image_size=tuple(size))
            for k, d, size in zip(cv.K, cv.D, image_sizes)]


def _cv_fisheye(obj, obs, size, check_cond=False):
    import cv2

    flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW | (cv2.CALIB_CHECK_COND if check_cond else 0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    try:
        rms, k, d, _, _ = cv2.fisheye.calibrate([obj[None]] * len(obs), [o[None] for o in obs], size, None, None,
                                                flags=flags, criteria=crit)
    except cv2.error as exc:
        return {"ok": False, "error": " ".join(str(exc).split())[-160:]}
    return {"ok": True, "rms": float(rms), "k": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]], "d": d.ravel().tolist()}


def _cv_pinhole(obj, obs, size, rational):
    import cv2

    flags = cv2.CALIB_RATIONAL_MODEL if rational else 0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    rms, k, d, _, _ = cv2.calibrateCamera([obj.astype(np.float32)] * len(obs), [o.astype(np.float32) for o in obs],
                                          size, None, None, flags=flags, criteria=crit)
    return {"ok": True, "rms": float(rms), "K": k, "d": d.ravel()}


def _pose_refine(project, obj, q, rvec, tvec):
    """Held-out view's pose with the intrinsics fixed: least squares in pixels from a PnP start."""
    from scipy.optimize import least_squares

    fit = least_squares(lambda x: (project(x[:3], x[3:]) - q).ravel(), np.concatenate([rvec.ravel(), tvec.ravel()]),
                        method="lm", xtol=1e-14, ftol=1e-14)
    return project(fit.x[:3], fit.x[3:])


def held_out_rms(obj, obs, size, kind):
    """Leave-one-view-out held-out RMS (px per corner) with OpenCV's calibrations (dstereo's equal them)."""
    import cv2

    errs = []
    for v in range(len(obs)):
        train = np.delete(obs, v, axis=0)
        if kind == "fisheye":
            fit = _cv_fisheye(obj, train, size)
            if not fit["ok"]:
                return None
            k, d = fit["k"], np.array(fit["d"])
            kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
            # start: PnP on the undistorted normalised corners (a pinhole with K = I)
            und = cv2.fisheye.undistortPoints(obs[v][None], kmat, d)[0]
            _, rvec, tvec = cv2.solvePnP(obj, und, np.eye(3), np.zeros(5))
            project = lambda r, t: cv2.fisheye.projectPoints(obj[None], r, t, kmat, d)[0][0]  # noqa: E731
        else:
            fit = _cv_pinhole(obj, train, size, rational=kind == "rational")
            kmat, d = fit["K"], fit["d"]
            _, rvec, tvec = cv2.solvePnP(obj, obs[v], kmat, d)
            project = lambda r, t: cv2.projectPoints(obj, r, t, kmat, d)[0][:, 0]  # noqa: E731
        q = _pose_refine(project, obj, obs[v], rvec, tvec)
        errs.append(np.sum((q - obs[v]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errs))))
