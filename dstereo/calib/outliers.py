"""Outlier rejection of corners and of whole views: iterative k-sigma on the whitened residuals.

A corner's residual (projected - observed, px) whitened by the solve's noise estimate sigma (per coordinate,
sigma^2 = inlier SSE / (inlier residuals - free parameters)) has |r|^2 / sigma^2 ~ chi^2(2) for Gaussian noise,
so P(|r| > k sigma) = exp(-k^2 / 2). With N corners, k = sqrt(2 ln(2 N)) makes the expected number of clean
corners rejected 0.5 per set (N = 1566: k = 4.0; leverage makes fitted residuals smaller than the noise, so
fewer in practice), never below K_MIN = 3 (mrcal's order of magnitude). Each round refits with the outliers
weighted 0 (`mono.calibrate_full(inliers=...)`, the same compiled solver) and re-tests every corner, those
rejected earlier included: an early round's sigma, inflated by a gross outlier, can neither hide it for good
nor keep a good corner out. Rounds stop when the mask repeats (at most MAX_ROUNDS).

A view with more than VIEW_FRACTION of its corners rejected is a mis-detected or moved board, not a few bad
corners: it is rejected whole (the caller drops it), and the rest is refitted without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dstereo.errors import DstereoError

K_MIN = 3.0
MAX_ROUNDS = 10
VIEW_FRACTION = 0.25
# Above this share of corners rejected the "outliers" are more likely a model that does not fit: say so.
MANY_FRACTION = 0.02


def threshold(n_corners: int) -> float:
    """k such that a clean Gaussian set of `n_corners` loses 0.5 corners on average (module docstring)."""
    return max(K_MIN, math.sqrt(2.0 * math.log(2.0 * max(n_corners, 1))))


def noise_sigma(residuals: np.ndarray, inliers: np.ndarray, n_params: int) -> float:
    """Per-coordinate noise estimate (px) from the inlier residuals (V, n, 2) and the free parameter count."""
    dof = 2 * int(inliers.sum()) - n_params
    sse = float(np.sum(np.sum(residuals ** 2, axis=2) * inliers))
    return math.sqrt(sse / dof) if dof > 0 else float("nan")


def inlier_mask(residuals: np.ndarray, sigma: float, k: float) -> np.ndarray:
    """(V, n) bool: corners whose residual is within k sigma."""
    return np.linalg.norm(residuals, axis=2) <= k * sigma


@dataclass
class OutlierReport:
    """What rejection removed; `corners` rows are (image, corner index, residual px, residual / sigma)."""

    enabled: bool
    k: float = float("nan")
    sigma: float = float("nan")  # final inlier noise estimate (px per coordinate)
    rounds: int = 0
    n_corners: int = 0  # corners tested (all views)
    corners: list[tuple[str, int, float, float]] = field(default_factory=list)
    views: list[tuple[str, float]] = field(default_factory=list)  # (image, share of its corners rejected)
    rms_before: float = float("nan")
    rms_after: float = float("nan")

    def summary(self) -> str:
        if not self.enabled:
            return "outlier rejection off (--no-outlier-rejection)"
        text = (f"outlier rejection (|r| > {self.k:.2f} sigma, sigma = {self.sigma:.3f} px, {self.rounds} "
                f"round(s)): {len(self.corners)} of {self.n_corners} corners")
        if self.views:
            text += f" and {len(self.views)} view(s) ({', '.join(v for v, _ in self.views)})"
        return text + f" rejected; RMS {self.rms_before:.4f} -> {self.rms_after:.4f} px"

    def warnings(self) -> list[str]:
        out = [f"view {name} rejected whole: {share:.0%} of its corners are outliers (> {VIEW_FRACTION:.0%}); "
               "check its detection" for name, share in self.views]
        if self.enabled and len(self.corners) > MANY_FRACTION * max(self.n_corners, 1):
            out.append(f"outlier rejection removed {len(self.corners)} of {self.n_corners} corners "
                       f"(> {MANY_FRACTION:.0%}): more than stray corners; the lens model may not fit "
                       "(see the residual-pattern check) or the board may be damaged")
        return out

    def as_dict(self) -> dict:
        return {
            "enabled": self.enabled, "k_sigma": self.k, "sigma_px": self.sigma, "rounds": self.rounds,
            "corners_tested": self.n_corners, "rms_before_px": self.rms_before, "rms_after_px": self.rms_after,
            "corners": [{"image": i, "corner": c, "residual_px": r, "residual_sigma": z}
                        for i, c, r, z in self.corners],
            "views": [{"image": i, "rejected_share": s} for i, s in self.views],
        }


def reject_outliers(obj, obs, image_size, free, names: list[str], first, k: float | None = None,
                    alone: bool = False):
    """(solution, kept view indices, OutlierReport) after iterative k-sigma rejection of corners and views.

    `first` is the solve of all corners of all views (`mono.calibrate_full`); the returned solution is the
    solve on the kept views with their inlier corners (its `inliers` mask carries into the subsets). `alone`:
    as `mono.calibrate_full`'s (no masked subsets follow)."""
    from dstereo.calib.mono import calibrate_full

    obs = np.asarray(obs, float)
    k = threshold(obs.shape[0] * obs.shape[1]) if k is None else float(k)
    n_params = lambda m: len(first.values) + 6 * int(m.any(axis=1).sum())  # noqa: E731
    sol, mask, rounds = first, np.ones(obs.shape[:2], bool), 0
    seen = {mask.tobytes()}
    while rounds < MAX_ROUNDS:
        residuals = sol.residuals[:, 0]  # one camera: its views are the frames
        new = inlier_mask(residuals, noise_sigma(residuals, mask, n_params(mask)), k)
        # A view that loses too many corners is out whole, for good: its bad corners must not steer the fit
        gone = (1.0 - new.mean(axis=1) > VIEW_FRACTION) | ~mask.any(axis=1)
        new[gone] = False
        if (new == mask).all():
            break
        cycle = new.tobytes() in seen  # masks alternating: stop at this one
        seen.add(new.tobytes())
        rounds, mask = rounds + 1, new
        sol = calibrate_full(obj, obs, image_size, free=free, inliers=mask, start=(sol.values, sol.poses), alone=alone)
        if cycle:
            break
    share = 1.0 - mask.mean(axis=1)
    keep = np.flatnonzero(mask.any(axis=1))
    if len(keep) < 3:
        raise DstereoError(f"outlier rejection: only {len(keep)} of {len(obs)} views keep their corners; the "
                           "lens model does not fit these views (try another `model`) or the pattern is wrong")
    if len(keep) < len(obs):  # the rest without the rejected views (their shape: one more compile)
        sol = calibrate_full(obj, obs[keep], image_size, free=free, inliers=mask[keep],
                             start=(sol.values, sol.poses[keep]), alone=alone)
    sigma = noise_sigma(sol.residuals[:, 0], mask[keep], len(sol.values) + 6 * len(keep))
    dropped = sorted(set(range(len(obs))) - set(keep.tolist()))
    norm = np.linalg.norm(sol.residuals[:, 0], axis=2)
    corners = [(names[keep[v]], int(c), float(norm[v, c]), float(norm[v, c] / sigma))
               for v, c in zip(*np.nonzero(~mask[keep]))]  # the rejected views are listed as views
    report = OutlierReport(True, k, sigma, rounds, int(obs.shape[0] * obs.shape[1]), corners,
                           [(names[i], float(share[i])) for i in dropped], first.rms, sol.rms)
    return sol, keep, report
