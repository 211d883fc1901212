"""The one result type of a calibration solve: K cameras over F board frames (`calib/problem.py`).

One camera (K = 1, `mono.calibrate_full`) is the same type with one camera over its views: its frames are its
views, its reference is itself (`rvecs`, `T` one zero row) and its parameter names carry no camera label (fx, fy,
..., as a camera file names them); a rig (K >= 2, `multiview.calibrate_views`) names them `<label>.<name>`.
Every array keeps its frame and camera axes for every K; `camera(k)` is the one convenience, a camera of the solve.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dstereo.calib.problem import WARP_NAMES, WARP_SIZE
from dstereo.solver.lm import STATUS_TEXT
from dstereo.uncertainty.covariance import Conditioning


@dataclass
class Solution:
    """A solve of K cameras over F frames. Camera 0 is the reference: x_cam_k = R_k x_ref + T_k."""

    names: tuple[str, ...]  # the shared vector's parameters (K = 1: fx, fy, ...; K >= 2: <label>.<name>)
    values: np.ndarray  # (G,) in `names` order
    std: np.ndarray  # (G,) the reported standard deviations (K = 1: the Jacobian's; a rig: with the frames'
    # effects, `uncertainty/view_effects.py`)
    cov: np.ndarray  # (G, G) the covariance `std` comes from
    cameras: list  # K `models.camera.Camera`s at the solution (free set and image size each)
    rvecs: np.ndarray  # (K, 3) each camera's rotation from the reference, row 0 zero
    T: np.ndarray  # (K, 3) each camera's translation from the reference, row 0 zero
    poses: np.ndarray  # (F, 6) rvec, tvec of each frame's board in the reference camera (T_ref_board)
    visible: np.ndarray  # (F, K) bool: which camera saw which frame
    rms: float  # sqrt(SSE / corners) over every fitted corner: OpenCV's reprojection error for K = 1
    per_view_rms: np.ndarray  # (F, K) over each view's inlier corners (0 when it has none), NaN where not seen
    residuals: np.ndarray  # (F, K, n, 2) projected - observed of every seen corner, outliers' included; 0 where
    # not seen
    iterations: int
    status: int
    conditioning: Conditioning
    mode: str = "joint"  # "joint": every camera's intrinsics solved (one camera always); "fixed": held
    labels: tuple[str, ...] = ("cam0",)
    inliers: np.ndarray | None = None  # (F, K, n) bool: the corners the solve fitted (None: every seen one)
    normal: np.ndarray | None = None  # (F, P+1, P+1) per frame [J r]'[J r] at the solution (P = G + 6): subsets
    # and the projection maps start from it
    std_jacobian: np.ndarray | None = None  # (G,) the Jacobian's alone (independent corner noise)
    flipped: list[tuple[int, int]] = field(default_factory=list)  # (frame, camera) read in reversed corner order
    timings: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.status > 0

    @property
    def status_text(self) -> str:
        return STATUS_TEXT[self.status]

    @property
    def board_sag(self) -> np.ndarray | None:
        """(2,) the board's sag (x, y) in the board unit when solved, else None."""
        return np.array(self.values[-WARP_SIZE:]) if self.names[-1] == WARP_NAMES[-1] else None

    @property
    def R(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        return Rotation.from_rotvec(self.rvecs).as_matrix()

    def camera(self, k: int = 0):
        """Camera k of the solve (`models.camera.Camera`: intrinsics, lens with its free set, image size)."""
        return self.cameras[k]

    def camera_inliers(self, k: int = 0) -> np.ndarray | None:
        """(F, n) bool: camera k's fitted corners of each frame as `inliers` holds them (None: every one)."""
        return None if self.inliers is None else np.asarray(self.inliers[:, k])

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.values)))

    def fitted(self) -> np.ndarray:
        """(F, K, n) bool: the corners the solve fitted (seen, and inliers)."""
        seen = np.broadcast_to(np.asarray(self.visible, bool)[:, :, None], self.residuals.shape[:3])
        return seen if self.inliers is None else seen & np.asarray(self.inliers, bool)

    def relative(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) of camera b relative to camera a: x_b = R x_a + T (a stereo pair with a on the left)."""
        from scipy.spatial.transform import Rotation

        r_a, r_b = Rotation.from_rotvec(self.rvecs[a]), Rotation.from_rotvec(self.rvecs[b])
        r = r_b * r_a.inv()
        return r.as_matrix(), self.T[b] - r.apply(self.T[a])

    def camera_rms(self) -> np.ndarray:
        """(K,) each camera's RMS over its fitted corners."""
        fit = self.fitted()
        sq = np.sum(np.where(fit[..., None], self.residuals, 0.0) ** 2, axis=-1)  # (F, K, n)
        return np.sqrt(sq.sum(axis=(0, 2)) / np.maximum(fit.sum(axis=(0, 2)), 1))


def per_view_rms(residuals: np.ndarray, fitted: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """(F, K) RMS of each view over its fitted corners (0 when it has none), NaN where not seen."""
    sq = np.sum(np.sum(np.asarray(residuals) ** 2, axis=-1) * fitted, axis=-1)
    out = np.sqrt(sq / np.maximum(fitted.sum(axis=-1), 1))
    return np.where(visible, out, np.nan)
