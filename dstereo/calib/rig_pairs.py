"""The camera pairs of a K-camera joint solve that get a stereo file: each pair's rig (R, T, E, F) and the
covariance that file carries (`uncertainty.rig.pair_covariance`), so a reconstruction from it has the
calibration's share of the point sigmas."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PairCalibration:
    a: int  # the left camera's index in the solve
    b: int  # the right camera's
    R: np.ndarray  # (3, 3) b from a
    T: np.ndarray  # (3,)
    E: np.ndarray  # (3, 3)
    F: np.ndarray  # (3, 3)
    cov_names: tuple[str, ...]  # stereo.yml's names (left.fx.., right.., RVx..Tz)
    cov: np.ndarray
    structure: str


def pair_calibration(solution, a: int, b: int) -> PairCalibration:
    """Cameras a (left) and b (right) of a `calib.multiview.MultiviewSolution` (mode "joint") as one stereo rig."""
    from dstereo.models.pose import rotation_vector
    from dstereo.models.rig import essential_matrix, fundamental_matrix
    from dstereo.uncertainty.rig import pair_covariance

    ca, cb = solution.cameras[a], solution.cameras[b]
    R, T = solution.relative(a, b)
    E = np.asarray(essential_matrix(rotation_vector(R), T))
    F = np.asarray(fundamental_matrix(np.asarray(ca.k), np.asarray(cb.k), E))
    names, cov, structure = pair_covariance(solution, a, b)
    return PairCalibration(a, b, np.asarray(R), np.asarray(T), E, F, tuple(names), np.asarray(cov), structure)
