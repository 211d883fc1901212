"""What a demo run is: its size (full or quick), the thesis's stereo steps, the bounds every estimate is held to,
and the folders it writes."""

from __future__ import annotations

from dataclasses import dataclass

from dstereo.config.calibration import Step


# Thesis Figure 5.14: stereo_re <= 3 px, then Tnorm and RVnorm within 0.75 IQR.
THESIS_STEREO_STEPS = (Step(("stereo_re",), (3.0,)), Step(("Tnorm",), (0.75,)), Step(("RVnorm",), (0.75,)))


# Fixed acceptance bounds; principal points and rotation also pass within `sigmas` standard deviations.
BOUNDS = {"focal_percent": 0.1, "principal_px": 0.5, "baseline_percent": 0.1, "rotation_deg": 0.05, "sigmas": 3.0}


# Allowed SGBM sub-pixel disparity error on the speckle, px (about 0.13 px measured with the true calibration).
DISPARITY_NOISE_PX = 0.2


@dataclass(frozen=True)
class DemoSettings:
    """Sizes of one demo run: the rig (reduced Plasmatron), the calibration set and the subset analysis."""

    image_size: tuple[int, int] = (640, 480)
    focal_px: float = 4800.0
    baseline_mm: float = 100.0
    distance_mm: float = 600.0
    n_views: int = 14
    per_set: int = 12
    max_subsets: int = 200
    model: tuple[str, ...] = ("k1", "k2", "p1", "p2")  # free distortion (the lenses have k3 = 0)


FULL = DemoSettings()


QUICK = DemoSettings(n_views=8, per_set=6, max_subsets=28)


PATHS = {"scenes": "scenes", "calibration": "calibration", "joint_yml": "calibration_joint/stereo.yml",
         "thesis_yml": "calibration/stereo.yml", "reconstruction": "reconstruction",
         "points": "reconstruction/points.npy", "comparison": "comparison.md"}
