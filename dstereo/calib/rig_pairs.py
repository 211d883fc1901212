"""The camera pairs of a K-camera joint solve that get a stereo file: each pair's rig (R, T, E, F), the
covariance that file carries (`uncertainty.rig.pair_covariance`), so a reconstruction from it has the
calibration's share of the point sigmas, and the boards the pair saw in its left camera (the writer's board depths
and corner angles, which `reconstruct` reads from a stereo file: its search-range prior and a fisheye's field)."""

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
    poses: np.ndarray  # (V, 6) T_a_board of the frames both cameras saw (the stereo job's pairs)
    board: np.ndarray  # (n, 3) the board the solve fitted (sagged when it solved the sag)

    def columns(self) -> dict[str, tuple[float, float]]:
        """The thesis's rig columns (RIG_COLUMNS) as (value, std) from the pair's covariance; the lengths |T| and
        |RV| with their first-order std (the gradient of the norm through the 3 x 3 block)."""
        from dstereo.models.pose import rotation_vector

        rvec, T = np.asarray(rotation_vector(self.R), float), np.ravel(np.asarray(self.T, float))
        idx = [list(self.cov_names).index(n) for n in ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz")]
        cov = np.asarray(self.cov, float)[np.ix_(idx, idx)]
        out = {n: (float(v), float(np.sqrt(max(cov[i, i], 0.0))))
               for i, (n, v) in enumerate(zip(("RVx", "RVy", "RVz", "Tx", "Ty", "Tz"), np.r_[rvec, T]))}
        out["Tnorm"] = (float(np.linalg.norm(T)), _norm_std(T, cov[3:, 3:]))
        out["RVnorm"] = (float(np.linalg.norm(rvec)), _norm_std(rvec, cov[:3, :3]))
        return {n: out[n] for n in RIG_COLUMNS}


RIG_COLUMNS = ("Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")  # the thesis's, stereo_re aside


def _norm_std(v: np.ndarray, cov: np.ndarray) -> float:
    n = float(np.linalg.norm(v))
    grad = v / n if n > 0 else np.zeros(3)
    return float(np.sqrt(max(grad @ cov @ grad, 0.0)))


def pair_calibration(solution, a: int, b: int, obj: np.ndarray) -> PairCalibration:
    """Cameras a (left) and b (right) of a `calib.solution.Solution` (mode "joint") as one stereo rig;
    `obj` (n, 3) the flat board."""
    from scipy.spatial.transform import Rotation

    from dstereo.calib.problem import sagged_board
    from dstereo.models.pose import rotation_vector, rotation_vectors
    from dstereo.models.rig import essential_matrix, fundamental_matrix
    from dstereo.uncertainty.rig import pair_covariance

    ca, cb = solution.cameras[a], solution.cameras[b]
    R, T = solution.relative(a, b)
    E = np.asarray(essential_matrix(rotation_vector(R), T))
    F = np.asarray(fundamental_matrix(np.asarray(ca.k), np.asarray(cb.k), E))
    names, cov, structure = pair_covariance(solution, a, b)
    both = np.asarray(solution.visible[:, a] & solution.visible[:, b], bool)
    r_a, ref = Rotation.from_rotvec(solution.rvecs[a]), np.asarray(solution.poses, float)[both]  # T_ref_board
    poses = np.zeros((0, 6))  # two cameras placed through a third may share no frame
    if len(ref):
        rot = r_a * Rotation.from_rotvec(ref[:, :3])
        poses = np.concatenate([rotation_vectors(rot.as_matrix()), r_a.apply(ref[:, 3:]) + solution.T[a]], axis=1)
    return PairCalibration(a, b, np.asarray(R), np.asarray(T), E, F, tuple(names), np.asarray(cov), structure,
                           poses, sagged_board(np.asarray(obj, float), solution.board_sag))
