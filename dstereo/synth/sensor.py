"""From scene radiance to an 8-bit image: defocus blur, vignetting, shot and read noise, quantisation (numpy)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from dstereo.errors import DstereoError


@dataclass(frozen=True)
class RenderOptions:
    """How a render is sampled and exposed.

    supersample: s x s samples per pixel (anti-aliasing); defocus_sigma_px: Gaussian blur (px) standing in for
    defocus; vignetting: relative fall-off at the farthest image corner, gain = 1 - v (r / r_corner)^2 about the
    principal point; full_well: electrons at radiance 1 for Poisson shot noise (0: none); read_noise_dn: Gaussian
    read noise in 8-bit digital numbers; exposure: digital numbers at radiance 1 are 255 * exposure.
    blank_beyond_field: a fisheye pixel with no ray in front of the camera (90 degrees or more off its axis, or
    past the fold of its polynomial) sees nothing (the background) instead of refusing the render: for lenses
    that see 180 degrees or more across the sensor (nothing of the scene lies behind the camera's plane).
    """

    supersample: int = 4
    defocus_sigma_px: float = 0.0
    vignetting: float = 0.0
    full_well: float = 0.0
    read_noise_dn: float = 0.0
    exposure: float = 1.0
    blank_beyond_field: bool = False

    def __post_init__(self):
        if self.supersample < 1:
            raise DstereoError(f"RenderOptions.supersample={self.supersample}: need >= 1")
        if not 0.0 <= self.vignetting < 1.0:
            raise DstereoError(f"RenderOptions.vignetting={self.vignetting}: need 0 <= v < 1")
        if self.defocus_sigma_px < 0 or self.full_well < 0 or self.read_noise_dn < 0 or self.exposure <= 0:
            raise DstereoError(f"RenderOptions {self}: blur, full well and noise must be >= 0, exposure > 0")

    def to_truth(self) -> dict:
        return asdict(self)


def vignetting_gain(image_size: tuple[int, int], principal_point: np.ndarray, strength: float) -> np.ndarray:
    """(height, width) gain 1 - strength * (r / r_corner)^2, r measured from the principal point."""
    w, h = image_size
    v, u = np.mgrid[0:h, 0:w].astype(float)
    cx, cy = principal_point
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    r_corner = np.max(np.hypot(corners[:, 0] - cx, corners[:, 1] - cy))
    return 1.0 - strength * ((u - cx) ** 2 + (v - cy) ** 2) / r_corner**2


def expose(radiance: np.ndarray, principal_point: np.ndarray, options: RenderOptions,
           rng: np.random.Generator) -> np.ndarray:
    """(height, width) radiance in [0, 1] -> uint8 image. Deterministic for a given `rng` state."""
    img = np.asarray(radiance, float)
    if options.defocus_sigma_px > 0:
        img = gaussian_filter(img, options.defocus_sigma_px, mode="nearest")
    if options.vignetting > 0:
        h, w = img.shape
        img = img * vignetting_gain((w, h), principal_point, options.vignetting)
    img = np.clip(img * options.exposure, 0.0, None)
    if options.full_well > 0:
        img = rng.poisson(img * options.full_well) / options.full_well
    dn = 255.0 * img
    if options.read_noise_dn > 0:
        dn = dn + rng.normal(0.0, options.read_noise_dn, dn.shape)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)
