"""N cameras from board frames that each camera may or may not see: the K-camera case of `calib/problem.py`.

Start: each camera's own calibration on the frames it saw (or the cameras given), its board pose per frame,
then each camera's pose relative to the reference from the frames it shares with a camera already placed
(a maximum spanning tree over shared-frame counts, so a camera that never sees a frame with the reference is
placed through another), and each frame's pose in the reference from the cameras that saw it. A view whose
corners a camera reports in the reversed order (a 180-degree flip of the detection) implies a pose far from
the other cameras': it is re-read reversed when that agrees, and refused when neither order agrees. Then
the one structured LM with all intrinsics held; in joint mode a second solve over everything from there.
"""

from __future__ import annotations

import time

import jax
import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.calib.mono import calibrate_full
from dstereo.calib.problem import POSE_SIZE, WARP_NAMES, WARP_SIZE, Problem, residual_weights, run, shared_data
from dstereo.calib.subset_solve import SubsetStart, solve_frame_subsets
from dstereo.calib.solution import Solution, per_view_rms
from dstereo.calib.subsets import SubsetSolutions
from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES, Camera
from dstereo.models.distortion import PRESETS
from dstereo.models.pose import rotation_vectors
from dstereo.models.rig import RIG_NAMES
from dstereo.solver.lm import LMOptions
from dstereo.uncertainty.covariance import conditioning, scaled_inverse
from dstereo.uncertainty.view_effects import solve_covariance

EXTRINSIC_NAMES = RIG_NAMES  # a camera's pose in the reference: the rig of (reference, camera)
MODES = ("fixed", "joint")
# A frame's pose implied through one camera that differs from the consensus by more than this is read as a
# corner-order flip (a flip is a 180-degree turn, far above any calibration's disagreement of a degree or two).
FLIP_ANGLE_DEG = 30.0


# --- poses as (rvec, t) 6-vectors: x_a = R x_b + t for T_a_b --------------------------------------------------


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ra, rb = Rotation.from_rotvec(a[..., :3]), Rotation.from_rotvec(b[..., :3])
    return np.concatenate([rotation_vectors((ra * rb).as_matrix()), ra.apply(b[..., 3:]) + a[..., 3:]], axis=-1)


def _inverse(a: np.ndarray) -> np.ndarray:
    r = Rotation.from_rotvec(a[..., :3]).inv()
    return np.concatenate([rotation_vectors(r.as_matrix()), -r.apply(a[..., 3:])], axis=-1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees((Rotation.from_rotvec(a[..., :3]).inv() * Rotation.from_rotvec(b[..., :3])).magnitude())


def _median_pose(poses: np.ndarray) -> np.ndarray:
    """A robust mean of close poses: the rotation nearest all (scipy's chordal mean of the ones within 2x the
    median angle of the first estimate) and the median translation."""
    first = np.concatenate([np.median(poses[:, :3], axis=0), np.median(poses[:, 3:], axis=0)])
    ang = _angle_deg(poses, first[None])
    near = ang <= 2 * np.median(ang) + 1e-9
    rot = rotation_vectors(Rotation.from_rotvec(poses[near, :3]).mean().as_matrix())
    return np.concatenate([rot, np.median(poses[near, 3:], axis=0)])


# --- start --------------------------------------------------------------------------------------------------


def _check(obj, obs, visible, image_sizes) -> None:
    if obs.ndim != 4 or obs.shape[1:] != (visible.shape[1], obj.shape[0], 2) or visible.shape[0] != obs.shape[0]:
        raise DstereoError(f"multiview corners: expected (frames, cameras, {obj.shape[0]}, 2) image points and "
                           f"(frames, cameras) visibility, got {obs.shape} and {visible.shape}")
    if len(image_sizes) != visible.shape[1]:
        raise DstereoError(f"multiview: {len(image_sizes)} image sizes for {visible.shape[1]} cameras")
    if visible.shape[1] < 2:
        raise DstereoError("multiview calibration needs at least two cameras")
    for f in np.flatnonzero(~visible.any(axis=1)):
        raise DstereoError(f"multiview: frame {f} is seen by no camera; leave it out")
    bad = visible & ~np.isfinite(obs).all(axis=(2, 3))
    if bad.any():
        f, k = np.argwhere(bad)[0]
        raise DstereoError(f"multiview: camera {k} sees frame {f} but some of its corners are not finite")


def _own_poses(cam: Camera, obj, obs_k, own_poses=None) -> np.ndarray:
    from dstereo.calib.board_poses import board_poses

    return own_poses if own_poses is not None else board_poses(cam, obj, obs_k)


def _placement_order(visible: np.ndarray) -> list[tuple[int, int]]:
    """(camera, placed through camera) in the order a maximum spanning tree from camera 0 over shared-frame
    counts adds them. Raises when a camera shares no frame with any camera connected to the reference."""
    k = visible.shape[1]
    shared = visible.T.astype(int) @ visible.astype(int)
    placed, order = {0}, []
    while len(placed) < k:
        best = max(((shared[a, b], b, a) for a in placed for b in range(k) if b not in placed), default=None)
        if best is None or best[0] == 0:
            lost = sorted(set(range(k)) - placed)
            raise DstereoError(f"multiview: camera(s) {lost} share no frame with the reference camera or any camera "
                               "connected to it; add frames that both see the board")
        order.append((best[1], best[2]))
        placed.add(best[1])
    return order


def _consensus(candidates: np.ndarray) -> np.ndarray:
    """The pose most candidates agree with (within FLIP_ANGLE_DEG): a robust mean of that cluster. A pair's
    relative pose from each shared frame, read in both corner orders: the true one appears once per frame,
    wrong readings scatter."""
    ang = _angle_deg(candidates[:, None], candidates[None])
    best = np.argmax((ang <= FLIP_ANGLE_DEG).sum(axis=1))
    return _median_pose(candidates[ang[best] <= FLIP_ANGLE_DEG])


def initial_state(obj, obs, visible, cameras: list[Camera], own_poses=None):
    """(extrinsics (K, 6) T_k_ref, frame poses (F, 6) T_ref_board, obs with flipped views re-read, flips).

    Cameras are placed in spanning-tree order; each camera's views are then checked against the cameras placed
    before it that saw the same frame: a view whose pose agrees only when read in reversed corner order is
    re-read so; one that agrees in neither order is refused (another board, or a bad detection)."""
    obs = obs.copy()
    f_count, k = visible.shape
    board = np.full((f_count, k, 6), np.nan)  # T_k_board
    rev = np.full((f_count, k, 6), np.nan)  # the same, corners read in reversed order
    for c in range(k):
        rows = np.flatnonzero(visible[:, c])
        board[rows, c] = _own_poses(cameras[c], obj, obs[rows, c], None if own_poses is None else own_poses[c])
        rev[rows, c] = _own_poses(cameras[c], obj, obs[rows, c][:, ::-1])
    ext, placed, flips = np.zeros((k, 6)), [0], []
    for c, via in _placement_order(visible):
        both = np.flatnonzero(visible[:, c] & visible[:, via])
        inv_via = _inverse(board[both, via])
        rel = _consensus(np.concatenate([_compose(board[both, c], inv_via), _compose(rev[both, c], inv_via)]))
        ext[c] = _compose(rel, ext[via])
        for f in np.flatnonzero(visible[:, c]):
            others = [o for o in placed if visible[f, o]]
            if not others:
                continue
            seen = _compose(_inverse(ext[others[0]]), board[f, others[0]])[None]
            as_read, reversed_ = (_angle_deg(_compose(_inverse(ext[c]), x[f, c])[None], seen)[0] for x in (board, rev))
            if min(as_read, reversed_) > FLIP_ANGLE_DEG:
                raise DstereoError(
                    f"multiview: frame {f} in camera {c} implies a board pose {as_read:.0f} degrees from camera "
                    f"{others[0]}'s (reversed corner order: {reversed_:.0f}); check that image (another board, or a bad "
                    "detection)")
            if reversed_ < as_read:
                flips.append((int(f), c))
                obs[f, c], board[f, c] = obs[f, c][::-1], rev[f, c]
        placed.append(c)
    poses = np.stack([_frame_pose(board, ext, visible, f) for f in range(f_count)])
    return ext, poses, obs, sorted(flips)


def _frame_pose(board, ext, visible, f) -> np.ndarray:
    """T_ref_board of frame f: from the first camera that saw it (the reference's own estimate if it did)."""
    c = int(np.flatnonzero(visible[f])[0])
    return _compose(_inverse(ext[c]), board[f, c])


# --- solve --------------------------------------------------------------------------------------------------


def _names(problem: Problem, labels) -> tuple[str, ...]:
    names = tuple(f"{labels[c]}.{n}" for c in range(1, problem.k) for n in EXTRINSIC_NAMES)
    for label, spec in zip(labels, problem.cameras):
        if spec.refined:
            names += tuple(f"{label}.{n}" for n in INTRINSIC_NAMES + spec.free)
    return names + (WARP_NAMES if problem.board_warp else ())


def _shared(obj, cameras):
    return shared_data(obj, np.stack([np.asarray(c.k) for c in cameras]),
                       np.stack([np.asarray(c.dist.coeffs) for c in cameras]))


def _g0(problem: Problem, ext: np.ndarray, cameras, sag=None) -> np.ndarray:
    parts = [ext[1:].ravel()]
    parts += [np.asarray(c.free_vector()) for c, s in zip(cameras, problem.cameras) if s.refined]
    if problem.board_warp:
        parts.append(np.zeros(WARP_SIZE) if sag is None else sag)
    return np.concatenate(parts)


def as_solved(obs, inliers, flips):
    """(obs, inliers) with each view of `flips` ((frame, camera) pairs) re-read in reversed corner order, as the
    solve reads it: a corner's inlier flag goes with the corner (the flags are indexed like the detection)."""
    obs = np.array(obs, float)
    inliers = None if inliers is None else np.array(inliers, bool)
    for f, c in flips:
        obs[f, c] = obs[f, c][::-1]
        if inliers is not None:
            inliers[f, c] = inliers[f, c][::-1]
    return obs, inliers


def _data(obs, visible, inliers):
    """(obs with NaN where unseen, residual weights (F, K 2n))."""
    data = np.where(visible[:, :, None, None], obs, np.nan)
    mask = visible[:, :, None] if inliers is None else visible[:, :, None] & inliers
    return data, residual_weights(np.broadcast_to(mask, obs.shape[:3]))


def _solve(problem, options, g0, p0, data, r_w, shared):
    out = run(problem, options, g0[None], p0[None], data[None], np.ones((1, len(p0))), np.array([options.lambda0]),
              shared, r_weight=r_w[None])
    return jax.tree_util.tree_map(lambda a: np.array(a[0]), out)


def cameras_alone(obj, obs, visible, image_sizes, free=PRESETS["default"], inliers=None, labels=None):
    """([Camera], [poses (V_k, 6)]): each camera calibrated alone on the frames it saw (at least 3); `free` one set
    or one per camera."""
    k = visible.shape[1]
    frees = [tuple(f) for f in (free if free and isinstance(free[0], (tuple, list)) else [free] * k)]
    labels = tuple(labels or (f"cam{c}" for c in range(k)))
    cameras, own = [], []
    for c in range(k):
        rows = np.flatnonzero(visible[:, c])
        if len(rows) < 3:
            raise DstereoError(f"multiview: camera {labels[c]} sees {len(rows)} frames; calibrating it alone "
                               "first needs at least 3 (or pass its intrinsics)")
        try:
            sol = calibrate_full(obj, obs[rows, c], tuple(image_sizes[c]), frees[c],
                                 inliers=None if inliers is None else inliers[rows, c])
        except DstereoError as exc:
            raise DstereoError(f"multiview: camera {labels[c]} calibrated alone: {exc}") from None
        cameras.append(sol.camera())
        own.append(sol.poses)
    return cameras, own


def calibrate_views(
    obj: np.ndarray,
    obs: np.ndarray,
    visible: np.ndarray,
    image_sizes,
    free=PRESETS["default"],
    mode: str = "joint",
    cameras: list[Camera] | None = None,
    options: LMOptions = LMOptions(),
    inliers: np.ndarray | None = None,
    labels: tuple[str, ...] | None = None,
    board_warp: bool = False,
) -> Solution:
    """Calibrate K cameras from frames of one board: obj (n, 3), obs (F, K, n, 2), visible (F, K) bool.

    `free`: one free-coefficient set for every camera or a list of K (each camera its own lens model).
    `cameras`: the cameras to start from (required in "fixed" mode, which holds them); else each camera is first
    calibrated alone on the frames it saw (at least 3). `inliers` (F, K, n) bool: corners that count.
    `board_warp`: solve the board's sag with the rest (two parameters, last in `names`)."""
    t0 = time.perf_counter()
    obj, obs, visible = np.asarray(obj, float), np.asarray(obs, float), np.asarray(visible, bool)
    _check(obj, obs, visible, image_sizes)
    if mode not in MODES:
        raise DstereoError(f"multiview mode '{mode}' is unknown; use one of {list(MODES)}")
    k = visible.shape[1]
    frees = [tuple(f) for f in (free if free and isinstance(free[0], (tuple, list)) else [free] * k)]
    labels = tuple(labels or (f"cam{c}" for c in range(k)))
    own = None
    if cameras is None:
        if mode == "fixed":
            raise DstereoError("multiview fixed mode holds given intrinsics: pass the cameras")
        cameras, own = cameras_alone(obj, obs, visible, image_sizes, frees, inliers, labels)
    ext, poses0, obs, flips = initial_state(obj, obs, visible, cameras, own)
    _, inliers = as_solved(obs, inliers, flips)  # obs comes re-read already; its inlier flags follow it
    data, r_w = _data(obs, visible, inliers)
    shared = _shared(obj, cameras)
    held = Problem.of([tuple(c.dist.free) for c in cameras], refined=False, board_warp=board_warp)
    out = _solve(held, options, _g0(held, ext, cameras), poses0, data, r_w, shared)
    iterations, problem = int(out.iterations), held
    if mode == "joint":
        problem = Problem.of([tuple(c.dist.free) for c in cameras], refined=True, board_warp=board_warp)
        ext_fit = np.vstack([np.zeros(6), out.g[:held.n_extrinsic].reshape(-1, 6)])
        sag = out.g[held.warp_slice] if board_warp else None
        out = _solve(problem, options, _g0(problem, ext_fit, cameras, sag), out.p, data, r_w, shared)
        iterations += int(out.iterations)
    sol = _solution(out, problem, mode, labels, cameras, obj, data, r_w, visible, iterations)
    sol.flipped = flips
    sol.timings["solve_s"] = time.perf_counter() - t0
    if not np.isfinite(sol.rms):
        raise DstereoError(f"multiview calibration failed ({sol.status_text}); check that every camera's images of "
                           "a frame show the same board")
    return sol


def _cameras_from(problem: Problem, g, cameras) -> list[Camera]:
    return [cam if sl is None else cam.with_free_vector(np.asarray(g[sl]))
            for cam, sl in zip(cameras, problem.intrinsic_slices())]


def _solution(out, problem, mode, labels, cameras, obj, data, r_w, visible, iterations) -> Solution:
    g = out.g
    names = _names(problem, labels)
    n_params = len(g) + POSE_SIZE * len(out.p)
    # the +- reported: with the frames' effects (`uncertainty/view_effects.py`), the Jacobian one beside it
    cov, jac, _ = solve_covariance(out, n_params)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    k, n = visible.shape[1], obj.shape[0]
    # every seen corner's residual, outliers' included (their weight is 0 in the solve); 0 where not seen
    seen = np.broadcast_to(visible[:, :, None, None], (len(out.p), k, n, 2))
    resid = np.where(seen, np.asarray(out.residuals).reshape(len(out.p), k, n, 2), 0.0)
    fitted = r_w.reshape(len(out.p), k, n, 2)[..., 0] > 0
    ext = np.vstack([np.zeros(6), g[:problem.n_extrinsic].reshape(-1, 6)])
    return Solution(
        mode=mode, labels=labels, names=names, values=g, std=std, cov=cov, cameras=_cameras_from(problem, g, cameras),
        std_jacobian=np.sqrt(np.maximum(np.diag(jac), 0.0)),
        rvecs=ext[:, :3], T=ext[:, 3:], poses=out.p, visible=visible,
        rms=float(np.sqrt(out.sse / max(float(fitted.sum()), 1.0))), per_view_rms=per_view_rms(resid, fitted, visible),
        residuals=resid, inliers=None if (fitted == visible[:, :, None]).all() else fitted,
        iterations=iterations, status=int(out.status),
        conditioning=conditioning(out.schur, names),
    )


# --- subsets of frames ------------------------------------------------------------------------------------


def solve_view_subsets(obj, obs, visible, index, start: Solution, options: LMOptions = LMOptions(lambda0=1e-6),
                       progress=None, inliers=None) -> SubsetSolutions:
    """Solve every subset of frames (rows of `index`) with the one subset runner, from the full-set `start`
    (same mode and cameras). A subset in which a camera sees no frame leaves that camera's parameters
    undetermined: its solve is reported, not hidden (status, and NaN or huge std).

    A board sag the full set solved is held there, as one camera's subsets hold it (`mono.solve_subsets`: the board
    is one object in every frame; m frames re-estimating it add only their noise): the subsets solve the flat
    problem on the sagged board, and their sag columns hold the full set's value with std 0."""
    from dstereo.calib.problem import sagged_board

    t0 = time.perf_counter()
    obj, obs, visible, index = np.asarray(obj, float), np.asarray(obs, float), np.asarray(visible, bool), np.asarray(index)
    obs, inliers = as_solved(obs, inliers, start.flipped)
    values = np.asarray(start.values, float)
    sag = values[-WARP_SIZE:] if start.names[-1] == WARP_NAMES[-1] else None
    if sag is not None:
        obj, values = sagged_board(obj, sag), values[:-WARP_SIZE]
    problem = Problem.of([tuple(c.dist.free) for c in start.cameras], refined=start.mode == "joint")
    # in fixed mode the held cameras are the solution's; in joint mode they only fill non-free coefficients
    data, r_w = _data(obs, visible, inliers)
    out = solve_frame_subsets(problem, data, r_w, _shared(obj, start.cameras), index,
                              SubsetStart(values, start.poses), options, progress)
    m = index.shape[1]
    # each subset's own poses, in its frames' order (a masked solve returns every frame's, the others unchanged)
    poses = out.p if out.p.shape[1] == m else np.take_along_axis(np.asarray(out.p), index[:, :, None], axis=1)
    sigma2 = out.sse / (out.n_residuals - (out.g.shape[1] + POSE_SIZE * m))
    cov_diag = np.diagonal(scaled_inverse(out.schur), axis1=1, axis2=2)
    g, std = np.asarray(out.g), np.sqrt(np.maximum(cov_diag * sigma2[:, None], 0.0))
    if sag is not None:
        g = np.c_[g, np.repeat(sag[None], len(g), 0)]
        std = np.c_[std, np.zeros((len(std), WARP_SIZE))]
    return SubsetSolutions(
        index=index, names=start.names, values=g, std=std,
        rms=np.sqrt(out.sse / (out.n_residuals / 2)), iterations=out.iterations, status=out.status,
        timings={"solve_s": time.perf_counter() - t0}, poses=np.asarray(poses))
