"""A stereo pair's calibration as a calibration file gives it (two cameras and their rig, numpy, mm and px); read
and written by `io/calib_files.py`, used by every room that reconstructs."""

from __future__ import annotations

from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from dstereo.models.camera import Camera
from dstereo.models.distortion import Distortion
from dstereo.models.fisheye import FISHEYE_NAMES
from dstereo.models.rig import Rig


@dataclass(frozen=True)
class StereoCalibration:
    """A stereo pair's calibration in numpy (mm, px): x_right = R x_left + T.

    `rectified` marks a pair that needs no rectification (Middlebury); then P1, P2 are [K1 | 0], [K2 | -f B].
    `image_size` is (width, height) or None when the file does not say. `models` names each camera's lens model,
    "pinhole" (OpenCV's 8 coefficients in D) or "fisheye" (cv2.fisheye's k1..k4 in D[:4], the rest zero).
    """

    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    image_size: tuple[int, int] | None = None
    rectified: bool = False
    source: str = ""
    extras: dict = field(default_factory=dict)
    models: tuple[str, str] = ("pinhole", "pinhole")
    # How the file's lengths became mm (its readers convert, io/calib_files.py): "stereo.yml is in cm: converted to
    # mm (x 10)", "... names no unit: its lengths are taken as mm" (OpenCV's own files); "" when built in code
    unit_note: str = ""

    @staticmethod
    def k_vector(K: np.ndarray) -> np.ndarray:
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])

    @property
    def k1(self) -> np.ndarray:
        return self.k_vector(self.K1)

    @property
    def k2(self) -> np.ndarray:
        return self.k_vector(self.K2)

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.T))

    def cameras(self) -> tuple[Camera, Camera]:
        """(left, right) as `dstereo.models.camera.Camera`: a pinhole camera with no coefficient free (a calibration
        being used); a fisheye camera names cv2.fisheye's coefficients (`FISHEYE_NAMES`) so that its `dist.free`
        says its lens model (`distortion.lens_model`), as every calibration's cameras do."""
        size = tuple(self.image_size) if self.image_size is not None else (0, 0)

        def camera(K, D, model):
            coeffs = jnp.asarray(np.asarray(D, float).ravel()[:8])
            free = FISHEYE_NAMES if model == "fisheye" else ()
            return Camera(jnp.asarray(self.k_vector(K)), Distortion(coeffs, free), size)

        return camera(self.K1, self.D1, self.models[0]), camera(self.K2, self.D2, self.models[1])

    @property
    def rig(self) -> Rig:
        """R, T as the one rig type (`dstereo.models.rig.Rig`); R and T stay as the file gave them."""
        return Rig.from_matrix(self.R, self.T)

    def projections(self) -> tuple[np.ndarray, np.ndarray]:
        """P1, P2 of an already rectified pair (only meaningful when `rectified`)."""
        P1 = np.c_[self.K1, np.zeros(3)]
        P2 = np.c_[self.K2, self.K2 @ self.T]
        return P1, P2
