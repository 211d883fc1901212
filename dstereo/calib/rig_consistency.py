"""Does one rig explain the frames? The increase of each camera's misfit from alone to joint, tested.

A rig says more than its cameras alone: the board stands at one pose per frame for every camera that sees it, and
the cameras keep their places between frames. Each camera alone fits its intrinsics, every view with a pose of
its own and a board sag of its own; the rig fits each camera's intrinsics too, but each frame with one pose, each
camera with one placement and the board with one sag. So the alone fits are the rig's problem with constraints
removed, and for Gaussian corner noise of variance s_k^2 in camera k the rig's extra misfit

    T = sum_k (SSE_rig_k - SSE_alone_k) / s_k^2  ~  chi^2(c),  c = (parameters alone) - (parameters of the rig)

(the nested least-squares test, linearised). The s_k^2 are measured by the alone fits themselves (SSE over their
degrees of freedom), so T / c is compared with Fisher's F(c, sum of those degrees of freedom). A rig that fails is
one whose frames are not one moment for all cameras (not simultaneous, a moving board), a rig that moved during
the take, or frames paired with the wrong partner: its R, T and their +- then mean little. Per frame, T_f (its
share of T) against chi^2(6 (K_f - 1)) says which frames contribute most.

The rig's SSE must come from a solve that refines the intrinsics (the "joint" solve): one with the intrinsics held
at the cameras' own calibrations is not nested in them (the held values are the alone fits' optimum, not the
rig's) and reads T/c = 2-4.5 on simultaneous renders of K = 2-4 cameras, where the joint solve reads 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from dstereo.calib.problem import POSE_SIZE, WARP_SIZE, Problem, residual_weights, run, shared_data
from dstereo.models.camera import Camera
from dstereo.solver.lm import LMOptions

# A rig is reported inconsistent below this p-value: a good rig sets the warning off once in 1,000 calibrations
# (measured on renders: 0 of 20 simultaneous seeds; a board moved 0.5 mm between exposures reads p < 1e-30).
ALPHA = 1e-3
# A rig whose RMS exceeds this multiple of the worst camera's own RMS (and 1 px) cannot describe frames of one
# moment at all, and is refused: measured 0.448 px vs 0.409 / 0.459 px (OpenCV's sample pairs), 39.7 px vs 0.61 /
# 0.14 px for images of two different rigs named alike. Below it, the consistency test says how well it does.
RIG_RMS_FACTOR = 5.0
TOP_FRAMES = 5  # frames named in the warning
# A frame the rig cannot explain (`RigConsistency.outlying_frames`): its T_f beyond chi^2(dof_f) at ALPHA shared
# among the frames (Bonferroni: a consistent rig loses a frame once in 1,000 calibrations), and its T_f / dof_f
# far above the other frames' (the median plus FRAME_ROBUST_SIGMAS robust sigmas, 1.4826 x MAD), as an outlier
# view is far above the other views: a rig whose every frame reads high has a cause no frame removal fixes.
FRAME_ROBUST_SIGMAS = 6.0
MAX_FRAME_ROUNDS = 10  # frames a job may remove this way, one a round (as calib/outliers.py's rounds)


@dataclass
class RigConsistency:
    labels: tuple[str, ...]
    frames: tuple[str, ...]
    rms_alone: np.ndarray  # (K,) px, each camera's views with poses of their own
    rms_rig: np.ndarray  # (K,) px, the same corners in the rig's (joint) solve
    sigma_alone: np.ndarray  # (K,) px per coordinate, the noise the alone fits measured
    statistic: float  # T
    dof: int  # c
    dof_noise: int  # the degrees of freedom of the s_k^2
    p_value: float
    frame_statistic: np.ndarray  # (F,) T_f
    frame_dof: np.ndarray  # (F,) 6 (K_f - 1)
    counts: np.ndarray  # (K,) corners each camera counts
    alpha: float = ALPHA
    notes: list[str] = field(default_factory=list)

    @property
    def consistent(self) -> bool:
        return not self.p_value < self.alpha

    @property
    def ratio(self) -> float:
        """T / c: 1 on average for a rig that explains its frames."""
        return self.statistic / max(self.dof, 1)

    def worst_frames(self, n: int = TOP_FRAMES) -> list[tuple[str, float, int, float]]:
        """(frame, T_f, dof_f, p_f) of the frames seen by two or more cameras, the least likely first."""
        from scipy import stats  # where used: a one-camera run never loads scipy.stats (tests/test_startup.py)

        frames = np.flatnonzero(self.frame_dof > 0)
        # ordered by the log of p, then by T_f / dof_f: far outliers all have p = 0 (even log p = -inf)
        log_p = stats.chi2.logsf(self.frame_statistic[frames], self.frame_dof[frames])
        order = frames[np.lexsort((-self.frame_statistic[frames] / self.frame_dof[frames], log_p))][:n]
        return [(self.frames[f], float(self.frame_statistic[f]), int(self.frame_dof[f]),
                 float(stats.chi2.sf(self.frame_statistic[f], self.frame_dof[f]))) for f in order]

    def outlying_frames(self) -> list[int]:
        """The frames (indices) the rig cannot explain and the other frames can (FRAME_ROBUST_SIGMAS), the worst
        first; none while the rig as a whole passes the test (a rig that explains its frames has no frame to
        remove: one frame's T_f high among many then reads a view's own detection error, not another moment; on
        the rendered K = 3 rig with OpenCV-detected, simultaneous corners one frame read 5.3x its constraints at
        p = 0.014 for the rig). One bad frame pulls the rig and raises the others' T_f with it: a caller removes the
        worst only and solves again, as outlier views are removed round by round."""
        from scipy import stats

        shared = np.flatnonzero(self.frame_dof > 0)
        if self.consistent or len(shared) < 4:
            return []  # too few frames to tell one from the rest
        ratio = self.frame_statistic[shared] / self.frame_dof[shared]
        med = float(np.median(ratio))
        mad = 1.4826 * float(np.median(np.abs(ratio - med)))
        p = stats.chi2.sf(self.frame_statistic[shared], self.frame_dof[shared])
        far = (p < self.alpha / len(shared)) & (ratio > med + FRAME_ROBUST_SIGMAS * max(mad, 1e-12))
        order = np.argsort(-ratio[far], kind="stable")
        return [int(f) for f in shared[far][order]]

    def line(self) -> str:
        per = ", ".join(f"{lab} {a:.4f} -> {r:.4f} px" for lab, a, r in zip(self.labels, self.rms_alone, self.rms_rig))
        return (f"rig consistency: misfit alone -> rig {per}; T/c = {self.statistic:.1f}/{self.dof} = "
                f"{self.ratio:.2f} (1 expected), p = {self.p_value:.2g}")

    @property
    def excess_px(self) -> float:
        """px per corner: the rms error the rig adds beyond what its cameras alone leave (0 when none)."""
        counts = np.maximum(self.counts, 1)
        extra = (np.sum(self.rms_rig ** 2 * counts) - np.sum(self.rms_alone ** 2 * counts)) / counts.sum()
        return float(np.sqrt(max(extra, 0.0)))

    def warning(self) -> str | None:
        if self.consistent:
            return None
        worst = "; ".join(f"{name} {t / max(d, 1):.1f}x its {d} constraints" for name, t, d, _ in self.worst_frames())
        return (f"the rig fits its frames worse than its cameras' corner noise allows ({self.line()}, below "
                f"{self.alpha:g}): the rig adds {self.excess_px:.3g} px rms per corner, as if the board stood "
                "elsewhere for each camera. Causes: exposures not simultaneous (a moving or hand-held board), a rig "
                "that moved during the take, frames paired with the wrong partner, or detection errors that follow "
                "each view (then the rig's +-, which counts the frames' scatter, holds). Check the synchronisation and "
                f"the frames contributing most: {worst}")

    def as_dict(self) -> dict:
        return {
            "consistent": self.consistent, "statistic": self.statistic, "dof": self.dof, "ratio": self.ratio,
            "dof_noise": self.dof_noise, "p_value": self.p_value, "alpha": self.alpha, "excess_px": self.excess_px,
            "cameras": [{"camera": lab, "rms_alone_px": float(a), "rms_rig_px": float(r), "sigma_alone_px": float(s)}
                        for lab, a, r, s in zip(self.labels, self.rms_alone, self.rms_rig, self.sigma_alone)],
            "worst_frames": [{"frame": n, "statistic": t, "dof": d, "p_value": p} for n, t, d, p in self.worst_frames()],
            "test": "sum over cameras of (rig SSE - alone SSE) / alone noise, against F(dof, dof_noise): poses of "
                    "their own per view (alone) vs one pose per frame and one placement per camera (rig), "
                    "intrinsics refined in both",
            "notes": list(self.notes),
        }


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    from dstereo.models.pose import rotation_vectors

    ra, rb = Rotation.from_rotvec(a[..., :3]), Rotation.from_rotvec(b[..., :3])
    return np.concatenate([rotation_vectors((ra * rb).as_matrix()), ra.apply(b[..., 3:]) + a[..., 3:]], axis=-1)


def _alone(camera: Camera, obj, obs, mask, poses0, sag0, seen):
    """One camera's views, each with its own pose, its intrinsics and the board's sag solved (its own calibration
    on exactly these corners): (SSE per frame (F,), inlier corners per frame (F,), converged). Every frame of the
    rig is passed, the ones this camera did not see with weight 0 (their poses take no part), so that every
    camera of one lens model solves one program: a camera's own frame count made a compile per camera and rig."""
    problem = Problem.of([tuple(camera.dist.free)], refined=True, board_warp=True)
    shared = shared_data(obj, np.asarray(camera.k)[None], np.asarray(camera.dist.coeffs)[None])
    r_w = residual_weights(mask[:, None])  # (F, 2n)
    data = np.where(mask[:, None, :, None], obs[:, None], np.nan)
    g0 = np.concatenate([np.asarray(camera.free_vector(), float), np.asarray(sag0, float)])
    out = run(problem, LMOptions(), g0[None], poses0[None], data[None], np.asarray(seen, float)[None],
              np.array([1e-3]), shared, r_weight=r_w[None], rows=1)
    resid = np.asarray(out.residuals)[0] * r_w
    return np.sum(resid ** 2, axis=-1), mask.sum(axis=-1), int(np.asarray(out.status)[0]) > 0


def rig_consistency(obj, obs, mask, cameras: list[Camera], rig_sse: np.ndarray, extrinsics: np.ndarray,
    poses: np.ndarray, sag, labels, frames) -> RigConsistency:
    """The test of the module docstring for a rig solved with its intrinsics refined.

    obj (n, 3) flat board; obs (F, K, n, 2) the corners as the rig read them; mask (F, K, n) the corners it counted
    (seen and inliers); cameras the rig's cameras (the alone fits start there); rig_sse (F, K) the rig's SSE per view over those corners;
    extrinsics (K, 6) T_k_ref and poses (F, 6) T_ref_board of the rig (the alone fits start there); sag (2,) the
    rig's board sag or None (flat).
    """
    obj, obs, mask = np.asarray(obj, float), np.asarray(obs, float), np.asarray(mask, bool)
    n_frames, k = mask.shape[:2]
    seen = mask.any(axis=-1)  # (F, K) views that count
    sse_alone = np.zeros((n_frames, k))
    sigma2, dof_noise, notes = np.zeros(k), 0, []
    sag0 = np.zeros(WARP_SIZE) if sag is None else np.asarray(sag, float)
    for c in range(k):
        rows = np.flatnonzero(seen[:, c])
        start = _compose(np.asarray(extrinsics[c], float)[None], np.asarray(poses, float))
        sse, count, converged = _alone(cameras[c], obj, obs[:, c], mask[:, c], start, sag0, seen[:, c])
        if not converged:
            notes.append(f"camera {labels[c]}: the alone fit did not converge; the test is approximate")
        sse_alone[:, c] = np.where(seen[:, c], sse, 0.0)
        n_params = POSE_SIZE * len(rows) + WARP_SIZE + 4 + len(cameras[c].dist.free)
        dof = int(2 * count.sum() - n_params)
        sigma2[c] = sse.sum() / max(dof, 1)
        dof_noise += max(dof, 1)
    rig_sse = np.where(seen, np.asarray(rig_sse, float), 0.0)
    frame_stat = np.sum((rig_sse - sse_alone) / np.maximum(sigma2, 1e-300), axis=1)
    k_f = seen.sum(axis=1)
    frame_dof = POSE_SIZE * np.maximum(k_f - 1, 0)
    # parameters alone: a pose per view and a sag per camera; the rig: a pose per frame, a placement per camera
    # but the reference, one sag (when it solved one: else the alone sags are extra freedom it lacks); the
    # intrinsics are in both and cancel
    n_alone = POSE_SIZE * int(seen.sum()) + WARP_SIZE * k
    n_rig = POSE_SIZE * int((k_f > 0).sum()) + POSE_SIZE * (k - 1) + (WARP_SIZE if sag is not None else 0)
    dof = max(n_alone - n_rig, 1)
    statistic = float(frame_stat.sum())
    from scipy import stats

    p = float(stats.f.sf(statistic / dof, dof, dof_noise))
    counts = np.maximum(mask.sum(axis=(0, 2)), 1)
    return RigConsistency(
        labels=tuple(labels), frames=tuple(frames), rms_alone=np.sqrt(sse_alone.sum(0) / counts),
        rms_rig=np.sqrt(rig_sse.sum(0) / counts), sigma_alone=np.sqrt(sigma2),
        statistic=statistic, dof=int(dof), dof_noise=int(dof_noise), p_value=p, frame_statistic=frame_stat,
        frame_dof=frame_dof, counts=mask.sum(axis=(0, 2)), notes=notes)


def of_multiview(joint, obj, obs, inliers=None, frames=None) -> RigConsistency:
    """The test on a `calib.solution.Solution` of K >= 2 cameras solved in "joint" mode (obs as given to it,
    (F, K, n, 2))."""
    from dstereo.calib.multiview import as_solved

    obs, inliers = as_solved(obs, inliers, joint.flipped)  # as the solve read them
    mask = joint.visible[:, :, None] & np.isfinite(obs[..., 0])
    if inliers is not None:
        mask &= np.asarray(inliers, bool)
    rig_sse = np.sum(np.where(joint.fitted()[..., None], joint.residuals, 0.0) ** 2, axis=(2, 3))
    extrinsics = np.concatenate([joint.rvecs, joint.T], axis=1)
    frames = frames if frames is not None else [f"frame {f}" for f in range(len(obs))]
    return rig_consistency(obj, obs, mask, joint.cameras, rig_sse, extrinsics, joint.poses, joint.board_sag,
                           joint.labels, frames)


