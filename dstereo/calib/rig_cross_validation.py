"""Cross-validation of a rig's uncertainty: random halves of the frames, each solved jointly, compared.

If the joint solve's +- is honest, two solves on disjoint halves of the frames differ by what their covariances
predict: for each camera c > 0, its placement in the reference (R_c as an axis-angle vector, T_c) differs by d with
d' (C_A + C_B)^-1 d ~ chi^2(6), C_X the half's covariance with the frames' effects (the +- cameras.yml and
stereo.yml's joint numbers carry); the same for each camera's intrinsics (chi^2 of its 4 + free coefficients).
The statistic reported is the mean over splits of chi^2 / dof, pooled over the cameras: 1 when the +- is right,
above when it is optimistic.

The splits share their frames, so their statistics are correlated and their mean is not much steadier than one
split's: the band a right prediction reads is taken as one split's, the 5 % and 95 % points of chi^2(dof) / dof
(at most this wide for the mean of correlated splits; a conservative band, stated as such). Halves have equal
sizes (an odd frame is left out of both) so all solves share one compiled program.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.camera import INTRINSIC_NAMES
from dstereo.models.rig import RIG_NAMES

MIN_HALF_VIEWS = 4  # a camera with fewer views in a half: its lens is not constrained there (as one camera's)
TRIES = 50  # random halvings tried per split before the frames are declared too few
BAND = (5.0, 95.0)


@dataclass
class RigSplit:
    rig_chi2: np.ndarray  # (K - 1,) each camera's placement difference
    intrinsics_chi2: np.ndarray  # (K,) each camera's intrinsics difference
    rotation_deg: np.ndarray  # (K - 1,) |rvec_A - rvec_B|
    baseline: np.ndarray  # (K - 1,) ||T_A| - |T_B||


@dataclass
class RigCrossValidation:
    labels: tuple[str, ...]
    splits: list[RigSplit]
    rig_dof: int  # 6 (K - 1) per split
    intrinsics_dof: int
    notes: list[str] = field(default_factory=list)

    def _mean(self, name: str, dof: int) -> float:
        return float(np.mean([getattr(s, name).sum() for s in self.splits]) / dof)

    @property
    def rig_ratio(self) -> float:
        """Mean over splits of the placements' chi^2 / dof: 1 when the rig's +- is right."""
        return self._mean("rig_chi2", self.rig_dof)

    @property
    def intrinsics_ratio(self) -> float:
        return self._mean("intrinsics_chi2", self.intrinsics_dof)

    def band(self, dof: int) -> tuple[float, float]:
        from scipy import stats

        return tuple(float(stats.chi2.ppf(p / 100.0, dof) / dof) for p in BAND)

    @property
    def trusted(self) -> bool:
        """The rig's and the intrinsics' statistics below their bands' upper ends (an optimistic +- fails; a
        pessimistic one, below the band, is reported but not a warning: it overstates what is not known)."""
        return (self.rig_ratio <= self.band(self.rig_dof)[1]
                and self.intrinsics_ratio <= self.band(self.intrinsics_dof)[1])

    def line(self) -> str:
        lo, hi = self.band(self.rig_dof)
        ilo, ihi = self.band(self.intrinsics_dof)
        return (f"rig cross-validation over {len(self.splits)} random halvings of the frames: placements "
                f"chi^2/dof {self.rig_ratio:.2f} (a right +- reads {lo:.2f}-{hi:.2f}), intrinsics "
                f"{self.intrinsics_ratio:.2f} ({ilo:.2f}-{ihi:.2f})")

    def verdict(self) -> str:
        if self.trusted:
            return self.line() + ": the rig's +- holds"
        return (self.line() + ": the halves differ by more than their +- predict, the rig's +- is optimistic "
                "(frames not simultaneous, a rig that moved, or errors the model does not describe: see the rig "
                "consistency test)")

    def as_dict(self) -> dict:
        return {
            "splits": len(self.splits), "trusted": self.trusted,
            "rig_ratio": self.rig_ratio, "rig_dof": self.rig_dof, "rig_band_if_right": list(self.band(self.rig_dof)),
            "intrinsics_ratio": self.intrinsics_ratio, "intrinsics_dof": self.intrinsics_dof,
            "intrinsics_band_if_right": list(self.band(self.intrinsics_dof)),
            "band_note": "one split's 5-95 % points of chi^2(dof)/dof: the splits share frames, so their mean is "
                         "at most this wide under a right +-",
            "per_split": [{"rig_chi2": s.rig_chi2.tolist(), "intrinsics_chi2": s.intrinsics_chi2.tolist(),
                           "rotation_difference_deg": s.rotation_deg.tolist(),
                           "baseline_difference": s.baseline.tolist()} for s in self.splits],
            "cameras": list(self.labels), "notes": list(self.notes),
        }


def _halves(visible: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two disjoint halves of equal size in which every camera keeps MIN_HALF_VIEWS views and every camera shares
    a frame with the reference through the others (tried TRIES times)."""
    from dstereo.calib.multiview import _placement_order

    n = len(visible) // 2
    for _ in range(TRIES):
        order = rng.permutation(len(visible))
        a, b = np.sort(order[:n]), np.sort(order[n:2 * n])
        if all(visible[h].sum(axis=0).min() >= MIN_HALF_VIEWS for h in (a, b)):
            try:
                for h in (a, b):
                    _placement_order(visible[h])
            except DstereoError:
                continue
            return a, b
    raise DstereoError(f"--cross-validate: {len(visible)} frames cannot be halved so that every camera keeps "
                       f"{MIN_HALF_VIEWS} views in each half; add frames or leave --cross-validate out")


def _rel_index(names, label: str, which: tuple[str, ...]) -> list[int]:
    return [names.index(f"{label}.{n}") for n in which]


def _chi2(d: np.ndarray, cov: np.ndarray) -> float:
    return float(d @ np.linalg.lstsq(cov, d, rcond=None)[0])


def cross_validate_rig(obj, obs, visible, image_sizes, cameras, labels, splits: int, seed: int = 0,
                       inliers=None, board_warp: bool = False) -> RigCrossValidation:
    """`splits` random halvings of the frames (obs (F, K, n, 2), visible (F, K)), each half solved jointly from
    `cameras` (the rig's own), compared as the module docstring says."""
    from dstereo.calib.multiview import calibrate_views

    if splits < 1:
        raise DstereoError(f"--cross-validate {splits}: give 1 or more splits (6 or more recommended)")
    obs, visible = np.asarray(obs, float), np.asarray(visible, bool)
    rng = np.random.default_rng(seed)
    k = visible.shape[1]
    out = []
    for _ in range(splits):
        sols = []
        for half in _halves(visible, rng):
            sols.append(calibrate_views(obj, obs[half], visible[half], image_sizes, mode="joint", cameras=cameras,
                                        labels=labels, board_warp=board_warp,
                                        inliers=None if inliers is None else inliers[half]))
        a, b = sols
        rig, rot, base = [], [], []
        for c in range(1, k):
            idx = _rel_index(a.names, labels[c], RIG_NAMES)
            d = a.values[idx] - b.values[idx]
            rig.append(_chi2(d, a.cov[np.ix_(idx, idx)] + b.cov[np.ix_(idx, idx)]))
            rot.append(float(np.degrees(np.linalg.norm(d[:3]))))
            base.append(float(abs(np.linalg.norm(a.values[idx][3:]) - np.linalg.norm(b.values[idx][3:]))))
        intr = []
        for c in range(k):
            idx = _rel_index(a.names, labels[c], INTRINSIC_NAMES + tuple(cameras[c].dist.free))
            intr.append(_chi2(a.values[idx] - b.values[idx], a.cov[np.ix_(idx, idx)] + b.cov[np.ix_(idx, idx)]))
        out.append(RigSplit(np.array(rig), np.array(intr), np.array(rot), np.array(base)))
    n_intr = sum(4 + len(c.dist.free) for c in cameras)
    return RigCrossValidation(tuple(labels), out, 6 * (k - 1), n_intr)
