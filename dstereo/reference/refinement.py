"""The result of a reference-object refinement (`Refinement`) and how it is built from the solver's solution."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.reference.correction import PARAM_NAMES, corrected_calibration
from dstereo.reference.solve import Solution

# A free parameter whose standard deviation exceeds these is reported as not determined by the reference.
POOR_ANGLE_DEG = 0.1
POOR_RELATIVE = 0.005


@dataclass
class Refinement:
    """The result: `theta` / `std` over `PARAM_NAMES` (zeros where not free), the corrected calibration."""

    reference: str
    free: tuple[str, ...]
    theta: np.ndarray
    std: np.ndarray
    cov: np.ndarray  # of the free parameters, in `free` order
    calibration: StereoCalibration
    solution: Solution
    residual_unit: str
    nuisance: np.ndarray
    baseline_before_mm: float
    checks: dict = field(default_factory=dict)

    def report(self) -> dict:
        """JSON-ready summary: the correction in deg / % / mm / px with standard deviations, residuals, flags."""
        th = self.theta
        sd = np.where(np.isin(PARAM_NAMES, self.free), self.std, np.nan)  # NaN -> null: held, not estimated
        s, baseline_mm = self.solution, self.baseline_before_mm
        k_l, k_r = self.calibration.k1, self.calibration.k2
        out = {
            "reference": self.reference,
            "free_parameters": list(self.free),
            "rotation_right_camera_deg": {ax: {"value": float(np.degrees(th[i])), "std": float(np.degrees(sd[i]))}
                                          for i, ax in enumerate("xyz")},
            "baseline": {"percent": 100 * float(th[3]), "std_percent": 100 * float(sd[3]),
                         "mm": float(th[3] * baseline_mm), "std_mm": float(sd[3] * baseline_mm),
                         "before_mm": float(baseline_mm), "after_mm": float(self.calibration.baseline)},
            "baseline_direction_deg": {n: {"value": float(np.degrees(th[i])), "std": float(np.degrees(sd[i]))}
                                       for i, n in ((4, "a"), (5, "b"))},
            "residual_rms": {"before": s.rms_before, "after": s.rms_after, "unit": self.residual_unit},
            "sigma": s.sigma, "residuals": s.n_residuals, "dof": s.dof, "iterations": s.steps,
            "converged": s.converged,
            "poorly_determined": poorly_determined(self),
            "conditioning": {"identifiable": s.conditioning.identifiable,
                             "condition_number": s.conditioning.condition_number,
                             "weak_parameters": s.conditioning.weak_parameters,
                             "max_correlation": list(s.conditioning.max_correlation),
                             "message": s.conditioning.message()},
            "checks": self.checks,
        }
        if "focal_left" in self.free:
            out["focal"] = {side: {"percent": 100 * float(th[i]), "std_percent": 100 * float(sd[i]),
                                   "px": float(k[0] - k[0] / (1 + th[i])), "std_px": float(sd[i] * k[0] / (1 + th[i]))}
                            for side, i, k in (("left", 6, k_l), ("right", 7, k_r))}
        return out


def poorly_determined(ref: "Refinement") -> list[str]:
    """Free parameters the observations leave undetermined: std > 0.1 deg (angles) or > 0.5 % (baseline, focal)."""
    angle = {"w_x", "w_y", "w_z", "dir_a", "dir_b"}
    return [n for n in ref.free if ref.std[PARAM_NAMES.index(n)] > (np.radians(POOR_ANGLE_DEG) if n in angle
                                                                    else POOR_RELATIVE)]



def refinement_from_solution(calib, kind: str, free: tuple[int, ...], sol: Solution, unit: str) -> Refinement:
    """The Refinement of `calib` by the solver's solution `sol` (its first len(free) values are the correction)."""
    theta = np.zeros(len(PARAM_NAMES))
    std = np.zeros(len(PARAM_NAMES))
    theta[list(free)] = sol.x[: len(free)]
    std[list(free)] = np.sqrt(np.maximum(np.diag(sol.cov), 0.0))
    return Refinement(kind, tuple(PARAM_NAMES[i] for i in free), theta, std, sol.cov,
                      corrected_calibration(calib, theta), sol, unit, sol.x[len(free):], calib.baseline)
