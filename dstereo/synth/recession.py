"""Surface recession of the sample's front face: a known profile in time and radius.

The front face recedes along the sample axis by

    r(t, rho) = uniform_rate * t + peak_rate * t * exp(-rho^2 / (2 sigma^2))        [mm; t in s, rho in mm]

a uniform ablation plus a centre-peaked component, largest at the stagnation point (rho = 0), where
r(t, 0) = (uniform_rate + peak_rate) * t.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import equinox as eqx
import numpy as np

from dstereo.errors import DstereoError
from dstereo.synth.objects import Sample


@dataclass(frozen=True)
class RecessionProfile:
    """Rates in mm/s, `sigma` (mm) the width of the centre-peaked part."""

    uniform_rate: float = 0.02
    peak_rate: float = 0.03
    sigma: float = 8.0

    def __post_init__(self):
        if self.sigma <= 0:
            raise DstereoError(f"RecessionProfile sigma={self.sigma}: need a positive width in mm")

    def depth(self, t: float, rho) -> np.ndarray:
        """r(t, rho) in mm."""
        rho = np.asarray(rho, float)
        return self.uniform_rate * t + self.peak_rate * t * np.exp(-(rho**2) / (2.0 * self.sigma**2))

    def at_stagnation(self, t: float) -> float:
        return float((self.uniform_rate + self.peak_rate) * t)

    def to_truth(self) -> dict:
        return asdict(self) | {"formula": "r(t, rho) = uniform_rate*t + peak_rate*t*exp(-rho^2/(2 sigma^2))"}


def profile_for_total(
    total_mm: float, duration_s: float, peak_share: float = 0.6, sigma: float = 8.0
) -> RecessionProfile:
    """Profile whose stagnation-point recession reaches `total_mm` at `duration_s`, `peak_share` of it peaked."""
    if duration_s <= 0:
        raise DstereoError(f"recession duration {duration_s} s: need > 0")
    rate = total_mm / duration_s
    return RecessionProfile((1.0 - peak_share) * rate, peak_share * rate, sigma)


def receded(sample: Sample, profile: RecessionProfile, t: float) -> Sample:
    """The sample at time t: its front face moved back by the profile (the side and texture stay put)."""
    sample = eqx.tree_at(lambda s: s.recession_uniform, sample, float(profile.uniform_rate * t))
    sample = eqx.tree_at(lambda s: s.recession_peak, sample, float(profile.peak_rate * t))
    return eqx.tree_at(lambda s: s.recession_sigma, sample, float(profile.sigma))


def frame_times(n_frames: int, duration_s: float) -> np.ndarray:
    """Timestamps 0, ..., duration_s (s), evenly spaced."""
    if n_frames < 2:
        raise DstereoError(f"recession sequence n_frames={n_frames}: need at least 2")
    return np.linspace(0.0, duration_s, n_frames)
