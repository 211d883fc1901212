"""Which calibration the camera file holds, and whether the thesis's subset mean fits the data.

The thesis's answer is the per-parameter mean over the subsets that survive the robust steps. Averaging
correlated, nonlinear parameters one by one gives a camera that is in general no solution of any data: on a
wide-angle lens it fitted its own corners at twice the full-set solve's RMS (issue 15). So by default
(`final = "survivors"`) the camera file holds the least-squares solve on the views that survive the steps:
the views of the surviving subsets, i.e. exactly the data the thesis's mean is computed from, solved as one
consistent calibration (when every view appears in a surviving subset this is the full-set solve itself).
`final = "mean"` keeps the thesis's number. Either way the mean is measured against the solve on the same
views (RMS on the survivors' corners, each board pose refitted for the fixed camera) and a warning with the
figures is given when it fits worse by more than `MEAN_MARGIN`.

A rig's final solve is the K-camera job's (`jobs/calibrate_cameras.calibrate_rig`: the frames of the surviving
rig subsets).

Pose refits are a small Levenberg-Marquardt per view (6 parameters), vmapped; no OpenCV here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.models.camera import project
from dstereo.models.pose import rodrigues

FINAL_CHOICES = ("survivors", "mean")
# The mean is reported as fitting worse when its RMS exceeds the solution's by more than this share: the
# tolerance the acceptance of issue 15 allows a written camera against the solve on its views. A mean within
# its own statistical spread of the solution raises the SSE by about sigma^2 * parameters, i.e. the RMS by
# ~G / (2 * residuals) (< 0.1 % for any real set), so 1 % is a misfit, not noise.
MEAN_MARGIN = 0.01
POSE_ITERATIONS = 60  # LM iterations of a pose refit at most (6 parameters from a nearby start: converges in < 15)
POSE_FTOL = 1e-12  # a refit ends at an accepted step that lowers the cost by at most this fraction


# --- surviving views ------------------------------------------------------------------------------------------


def view_survival(filtering, plan, n_views: int, block: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """((V,) surviving subsets holding each view, (V,) usable subsets holding it), read a block at a time."""
    alive_n, usable_n = np.zeros(n_views, np.int64), np.zeros(n_views, np.int64)
    survivors, usable = filtering.survivors, filtering.usable
    rows_of = plan.rows if hasattr(plan, "rows") else (lambda a, b: np.asarray(plan)[a:b])
    for a in range(0, len(survivors), block):
        rows = rows_of(a, a + len(survivors[a:a + block]))
        alive_n += np.bincount(rows[survivors[a:a + block]].ravel(), minlength=n_views)
        usable_n += np.bincount(rows[usable[a:a + block]].ravel(), minlength=n_views)
    return alive_n, usable_n


def surviving_views(filtering, plan, n_views: int, block: int = 65536) -> np.ndarray:
    """(V,) bool: the views that appear in at least one surviving subset."""
    return view_survival(filtering, plan, n_views, block)[0] > 0


# --- pose refits --------------------------------------------------------------------------------------------


def _mono_residual(pose, k, coeffs, obj, obs_v, rig, lens=project):
    p = obj @ rodrigues(pose[:3]).T + pose[3:6]
    return (jax.vmap(lens, in_axes=(None, None, 0))(k, coeffs, p) - obs_v).ravel()


@functools.lru_cache(maxsize=None)
def _refit(free: tuple[str, ...] = ()):
    """Compiled: every view's pose refitted by LM for a fixed camera; returns poses and SSE per view. `free` names
    the camera's lens model (`mono.lens_functions`: pinhole or fisheye)."""
    from dstereo.calib.mono import lens_functions

    lens = lens_functions(free)[0]

    def one(pose0, cams, obj, obs_v, rig, w_v):
        # w_v: residual weights (0 = an outlier corner, calib/outliers.py), as in the solve
        res = lambda p: _mono_residual(p, cams[0], cams[1], obj, obs_v, rig, lens) * w_v  # noqa: E731
        cost0 = jnp.sum(res(pose0) ** 2)

        def body(state):
            pose, lam, cost, it, _ = state
            r, jac = res(pose), jax.jacfwd(res)(pose)
            a, g = jac.T @ jac, jac.T @ r
            step = jnp.linalg.solve(a + lam * jnp.diag(jnp.diag(a) + 1e-12), -g)
            trial = pose + step
            c = jnp.sum(res(trial) ** 2)
            better = jnp.isfinite(c) & (c < cost)
            # Done once a step gains nothing the cost's rounding can tell (an accepted step's gain <= 1e-12 of it),
            # or steps keep failing (damping 1e4: seven rejections in a row from the start's); it ran all
            # POSE_ITERATIONS before, ~4x as many as a pose needs (measured: the same RMS to 1e-12).
            done = (better & (cost - c <= POSE_FTOL * cost)) | (lam >= 1e4)
            return (jnp.where(better, trial, pose), jnp.where(better, lam * 0.3, lam * 10.0),
                    jnp.where(better, c, cost), it + 1, done)

        state = (pose0, jnp.asarray(1e-3), cost0, jnp.asarray(0), jnp.asarray(False))
        pose, _, cost, _, _ = jax.lax.while_loop(lambda s: ~s[4] & (s[3] < POSE_ITERATIONS), body, state)
        return pose, cost

    from dstereo.runtime import aot, buckets  # kept on disk: a new process skips tracing it

    # one program per bucket of view counts (runtime/buckets.py): poses, corners and weights padded with view 0's
    return buckets.per_row(aot.jit(jax.vmap(one, in_axes=(0, None, None, 0, None, 0)), "calib.final_solution.refit",
                                   (free,)), (0, 3, 5), kind=("refit", (free,)))


def _homography_poses(k, coeffs, obj, obs) -> np.ndarray | None:
    """(V, 6) board poses from the homography of the corners undistorted by this camera (OpenCV's solvePnP
    start), or None where that fails."""
    from dstereo.calib.board_poses import board_poses
    from dstereo.models.camera import Camera

    try:
        poses = board_poses(Camera.create(*map(float, k), np.asarray(coeffs, float)), obj, obs)
    except Exception:  # noqa: BLE001 - a degenerate homography: the other start stands alone
        return None
    return poses if np.all(np.isfinite(poses)) else None


def refit_rms(k, coeffs, obj, obs, start_poses, free: tuple[str, ...] = (), inliers=None) -> tuple[float, np.ndarray]:
    """(RMS px over all corners, (V, 6) poses) of a fixed camera (k (4,), coeffs (8,)) on views `obs` (V, n, 2),
    each view's board pose refitted from `start_poses` (V, 6) and from two homography starts (the corners
    undistorted by this camera, and taken as they are); per view the best fit counts. Several starts because a
    camera that is no solution (a subset mean of a rational model) can put a pole of its distortion near the
    corners, and LM from one start then stops behind it (measured on opencv_stereo left, rational: 0.4083 px
    from the solve's poses, 0.4041 px from the three; cv2.solvePnP + RefineLM 0.4040 px).
    RMS = sqrt(SSE / corners), OpenCV's convention. `free` names the lens model (a fisheye camera's corners
    are not undistorted by the pinhole homography start: its poses start from `start_poses` and the raw corners).
    `inliers` (V, n) bool: the corners that count (outlier rejection's mask; default all).
    """
    from dstereo.models.distortion import lens_model

    free = tuple(free)
    cams = (np.asarray(k, float), np.asarray(coeffs, float))
    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    refit = _refit(free)
    mask = np.ones(obs.shape[:2], bool) if inliers is None else np.asarray(inliers, bool)
    w = np.repeat(mask.astype(float), 2, axis=1)
    poses, sse = (np.asarray(a) for a in refit(np.asarray(start_poses, float), cams, obj, obs, np.zeros(6), w))
    starts = [_homography_poses(k, np.zeros(8), obj, obs)]
    if lens_model(free) == "pinhole":
        starts.append(_homography_poses(k, coeffs, obj, obs))
    for other in starts:
        if other is None:
            continue
        poses_h, sse_h = (np.asarray(a) for a in refit(other, cams, obj, obs, np.zeros(6), w))
        better = np.isfinite(sse_h) & ~(sse_h >= sse)
        poses, sse = np.where(better[:, None], poses_h, poses), np.where(better, sse_h, sse)
    return float(np.sqrt(np.sum(sse) / max(int(mask.sum()), 1))), poses


# --- the decision -------------------------------------------------------------------------------------------


@dataclass
class MeanCheck:
    """The subset mean against the solve on the same views: RMS on the survivors' corners, poses refitted."""

    views: int  # views (or pairs) the comparison uses
    rms_solution: float
    rms_mean: float
    margin: float = MEAN_MARGIN

    @property
    def ratio(self) -> float:
        return self.rms_mean / self.rms_solution if self.rms_solution > 0 else float("inf")

    @property
    def mean_worse(self) -> bool:
        return not (self.ratio <= 1.0 + self.margin)  # NaN (a mean that cannot be evaluated) counts as worse

    def text(self, what: str = "camera") -> str:
        return (f"the thesis's subset mean {what} fits its {self.views} surviving views at RMS {self.rms_mean:.4f} px "
                f"against {self.rms_solution:.4f} px for the solve on the same views ({self.ratio:.3f}x, poses "
                f"refitted): averaging parameters one by one gives no consistent calibration")

    def as_dict(self) -> dict:
        return {"views": self.views, "rms_solution_px": self.rms_solution, "rms_mean_px": self.rms_mean,
                "ratio": self.ratio, "margin": self.margin, "mean_worse": self.mean_worse,
                "measure": "RMS over the surviving views' corners, sqrt(SSE / corners), each board pose refitted "
                           "for the fixed calibration (LM from the solve's poses)"}


@dataclass
class FinalSolution:
    """What the camera file holds and how it relates to the thesis's subset mean."""

    choice: str  # "survivors" or "mean"
    views: np.ndarray  # (V,) bool: the surviving views
    solution: object  # calib.solution.Solution on the surviving views (the full-set solve when all survive)
    subset_mean: dict[str, float]
    check: MeanCheck
    survival: tuple[np.ndarray, np.ndarray] | None = None  # `view_survival`

    @property
    def final(self) -> dict[str, float]:
        return dict(self.subset_mean) if self.choice == "mean" else self.solution.as_dict()

    def source(self, names_used: list[str]) -> str:
        kept, n = int(self.views.sum()), len(self.views)
        dropped = [names_used[i] for i in np.flatnonzero(~self.views)]
        solve = (f"least-squares solve on the {kept} views of the surviving subsets"
                 + ("" if kept == n else f" ({n - kept} view(s) in no surviving subset left out: "
                                         f"{', '.join(dropped[:10])}{', ...' if len(dropped) > 10 else ''})")
                 + (" = the full-set solve" if kept == n else ""))
        if self.choice == "mean":
            return "mean over the surviving subsets (the thesis's answer; --final mean); the consistent " + solve + \
                " is in summary.json final_check"
        return solve + "; the thesis's subset mean is beside it (subset_mean)"

    def as_dict(self, names_used: list[str]) -> dict:
        out = {"choice": self.choice, "source": self.source(names_used),
               "survivor_views": [names_used[i] for i in np.flatnonzero(self.views)],
                "left_out_views": [names_used[i] for i in np.flatnonzero(~self.views)],
                "solution": self.solution.as_dict(),
                "solution_std": dict(zip(self.solution.names, map(float, self.solution.std))),
               "solution_rms_px": float(self.solution.rms), "subset_mean": dict(self.subset_mean),
               "mean_check": self.check.as_dict()}
        if self.survival is not None:  # share of each view's (converged) subsets that survive the steps
            alive, usable = self.survival
            out["view_survival"] = {names_used[i]: {"surviving_subsets": int(alive[i]), "subsets": int(usable[i]),
                                                    "share": float(alive[i] / usable[i]) if usable[i] else None}
                                    for i in range(len(alive))}
        return out


def camera_final(choice: str, filtering, plan, obj, obs, full, image_size, subset_mean: dict) -> FinalSolution:
    """The solve on the surviving views (re-solved only when some view survives in no subset) and the mean check."""
    from dstereo.calib.mono import calibrate_full

    survival = view_survival(filtering, plan, len(obs))
    views = survival[0] > 0
    inliers = None if full.inliers is None else full.camera_inliers()[views]  # the full set's outlier mask carries
    free = tuple(full.camera().dist.free)
    solution = full if views.all() else calibrate_full(obj, obs[views], image_size, free=free,
                                                       inliers=inliers, board_warp=full.board_sag is not None,
                                                       alone=True)  # after the subsets: no program to share
    names = full.names
    k = np.array([subset_mean[n] for n in names[:4]])
    coeffs = np.array(solution.camera().coeffs(), float)
    from dstereo.models.distortion import coeff_slots

    from dstereo.calib.problem import WARP_NAMES, sagged_board

    for n in names[4:]:
        if n not in WARP_NAMES:  # the board's sag is the board's, not the camera's
            coeffs[coeff_slots(free).index(n)] = subset_mean[n]
    # both cameras refitted on the board the solution found (its sag, when solved): the mean is judged as a camera
    board = sagged_board(obj, solution.board_sag)
    rms_mean, _ = refit_rms(k, coeffs, board, obs[views], solution.poses, free, inliers)
    rms_sol, _ = refit_rms(solution.values[:4], solution.camera().coeffs(), board, obs[views], solution.poses, free,
                           inliers)
    # The solution's own refit equals its RMS to the solver's tolerance; the refitted figure is compared so that
    # both sides are measured the same way.
    return FinalSolution(choice, views, solution, dict(subset_mean), MeanCheck(int(views.sum()), rms_sol, rms_mean),
                         survival)


def written_camera_solution(cal):
    """The `calib.solution.Solution` whose covariance goes with the written camera: the survivors' solve, or the
    full set."""
    fs = getattr(cal, "final_solution", None)
    return cal.full if fs is None else fs.solution
