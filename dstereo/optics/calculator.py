"""Depth of field, diffraction and stereo resolution for planning a capture (thesis sections 2.2.2 and 5.1).

All lengths are in mm, angles in degrees. The depth-of-field equations (5.1-5.3) are the exact thin-lens
ones for a focal length `f`, f-number `N` and circle of confusion `c`, with the focus distance `s` measured
from the lens. Which `f` goes into them is a choice (`OpticsConfig.dof_focal_length`):

* ``"effective"`` (default, the thesis's Tables 5.2-5.3 and Figures 5.1-5.3): the effective
  (35 mm-equivalent) focal length of eq. 2.2 together with the CoC of the actual sensor;
* ``"lens"``: the lens's own focal length with the CoC of the actual sensor, which is the thin-lens blur
  geometry of the camera as built (a larger depth of field than the thesis's convention, by about crop^2
  in the hyperfocal distance).

Field of view, footprint and stereo depth resolution always use the lens focal length and the actual sensor
(pinhole model: the principal distance is taken as `f`).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dstereo.errors import DstereoError

FULL_FRAME_MM = (36.0, 24.0)  # eq. 2.3, 2.5
PRINT_MM = (250.0, 200.0)  # 8 x 10 inch print, eq. 2.4
PRINT_COC_MM = 0.25  # smallest blur the eye sees on that print at 1 foot, eq. 2.6
DEFAULT_WAVELENGTH_MM = 0.00055  # eq. 2.1 nominal green light
DOF_FOCAL_CHOICES = ("effective", "lens")
PLOT_NAMES = ("dof_vs_focal_length.png", "dof_vs_f_number.png", "dof_contour.png")


@dataclass(frozen=True)
class OpticsConfig:
    """Capture set-up. Lengths in mm; `sensor` is (width, height); give `sensor` or `crop_factor`.

    `coc` defaults to the value derived from the sensor diagonal (eq. 2.4-2.6). `pixel_size` enables the
    3 x pixel diffraction check and the stereo figures; `baseline` (distance between the two camera centres)
    enables the stereo depth resolution, at `disparity_precision` pixels of matcher precision.
    """

    focus_distance: float
    focal_length: float
    f_number: float
    sensor: tuple[float, float] | None = None
    crop_factor: float | None = None
    coc: float | None = None
    pixel_size: float | None = None
    wavelength: float = DEFAULT_WAVELENGTH_MM
    baseline: float | None = None
    disparity_precision: float = 1.0
    dof_focal_length: str = "effective"


CONFIG_KEYS = tuple(f.name for f in fields(OpticsConfig))
REQUIRED_KEYS = ("focus_distance", "focal_length", "f_number")


def describe(key: str) -> str:
    """Parameter `key` as errors name it (the CLI shows its flag: dstereo.config.messages)."""
    return f"`{key}`"


# --- eq. 2.1-2.7 and 5.1-5.3 -----------------------------------------------------------------------------
def diagonal(size: tuple[float, float]) -> float:
    """Diagonal (mm) of a (width, height) rectangle in mm."""
    return math.hypot(*size)


def crop_factor_from_sensor(sensor: tuple[float, float]) -> float:
    """Crop factor (eq. 2.3): full-frame diagonal over the sensor diagonal. `sensor` is (w, h) in mm."""
    return diagonal(FULL_FRAME_MM) / diagonal(sensor)


def sensor_from_crop_factor(crop_factor: float, aspect: tuple[float, float] = (3.0, 2.0)) -> tuple[float, float]:
    """Sensor (width, height) in mm with the full-frame diagonal / `crop_factor` and the given aspect ratio."""
    scale = diagonal(FULL_FRAME_MM) / crop_factor / diagonal(aspect)
    return (aspect[0] * scale, aspect[1] * scale)


def coc_from_sensor(sensor: tuple[float, float]) -> float:
    """Circle of confusion (mm) on a sensor of (w, h) mm: the 0.25 mm print CoC scaled by diagonals (eq. 2.4-2.6)."""
    return PRINT_COC_MM * diagonal(sensor) / diagonal(PRINT_MM)


def effective_focal_length(focal_length, crop_factor):
    """35 mm-equivalent focal length (eq. 2.2), mm."""
    return crop_factor * focal_length


def hyperfocal_distance(focal_length, f_number, coc):
    """Hyperfocal distance H = f^2 / (N c) + f (eq. 2.7 / 5.1), mm; f and c in mm."""
    f = np.asarray(focal_length, float)
    return f * f / (np.asarray(f_number, float) * coc) + f


def near_limit(focus_distance, focal_length, hyperfocal):
    """Near limit of acceptable sharpness D_n = s (H - f) / (H + s - 2 f) (eq. 5.3), mm."""
    s = np.asarray(focus_distance, float)
    return s * (hyperfocal - focal_length) / (hyperfocal + s - 2.0 * focal_length)


def far_limit(focus_distance, focal_length, hyperfocal):
    """Far limit D_f = s (H - f) / (H - s) (eq. 5.2), mm; infinite when the focus is at or beyond H."""
    s = np.asarray(focus_distance, float)
    h = np.asarray(hyperfocal, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        far = s * (h - focal_length) / (h - s)
    return np.where(s < h, far, np.inf)


def total_depth_of_field(focus_distance, focal_length, f_number, coc):
    """Far minus near limit, mm (infinite beyond the hyperfocal distance); broadcasts over arrays."""
    h = hyperfocal_distance(focal_length, f_number, coc)
    return far_limit(focus_distance, focal_length, h) - near_limit(focus_distance, focal_length, h)


def depth_of_field(focus_distance: float, focal_length: float, f_number: float, coc: float) -> dict[str, float]:
    """Hyperfocal, near/far limits, total and the parts in front of/behind the subject (mm, and % of total)."""
    h = float(hyperfocal_distance(focal_length, f_number, coc))
    near = float(near_limit(focus_distance, focal_length, h))
    far = float(far_limit(focus_distance, focal_length, h))
    front, behind = focus_distance - near, far - focus_distance
    finite = math.isfinite(far)
    return {
        "hyperfocal_mm": h,
        "near_mm": near,
        "far_mm": far,
        "far_is_infinite": not finite,
        "total_dof_mm": far - near,
        "front_mm": front,
        "behind_mm": behind,
        "front_percent": 100.0 * front / (far - near) if finite else 0.0,
        "behind_percent": 100.0 * behind / (far - near) if finite else 100.0,
    }


def airy_disk_diameter(f_number, wavelength=DEFAULT_WAVELENGTH_MM):
    """Airy disk diameter 2.44 N lambda (eq. 2.1), mm; wavelength in mm."""
    return 2.44 * f_number * wavelength


def diffraction_check(airy_disk: float, coc: float, pixel_size: float | None) -> dict[str, Any]:
    """Table 5.1 logic: diffraction does not limit resolution while the Airy disk (mm) is below the CoC and
    below 3 x the pixel size (mm); below one pixel is better still. Pixel checks are None without a pixel."""
    three_px = None if pixel_size is None else 3.0 * pixel_size
    below_px = None if pixel_size is None else airy_disk < three_px
    return {
        "three_pixels_mm": three_px,
        "airy_over_pixel": None if pixel_size is None else airy_disk / pixel_size,
        "airy_below_coc": airy_disk < coc,
        "airy_below_three_pixels": below_px,
        "diffraction_limited": not (airy_disk < coc and below_px is not False),
    }


def field_of_view(sensor: tuple[float, float], focal_length: float) -> dict[str, float]:
    """Horizontal, vertical and diagonal angle of view (degrees) of a pinhole of focal length f (mm)."""
    def angle(size):
        return math.degrees(2.0 * math.atan(size / (2.0 * focal_length)))

    w, h = sensor
    return {"fov_horizontal_deg": angle(w), "fov_vertical_deg": angle(h), "fov_diagonal_deg": angle(diagonal(sensor))}


def footprint(sensor: tuple[float, float], focal_length: float, distance: float) -> dict[str, float]:
    """Width and height (mm) of the plane seen at `distance` (mm) by a pinhole of focal length f (mm)."""
    scale = distance / focal_length
    return {"footprint_width_mm": sensor[0] * scale, "footprint_height_mm": sensor[1] * scale}


def stereo_depth_resolution(
    depth: float, focal_length: float, baseline: float, pixel_size: float, precision_px: float = 1.0
) -> dict[str, float]:
    """Depth change per pixel of disparity dZ = Z^2 p / (f B) at depth Z, and at the matcher's precision.

    Z, f, B, p in mm; the disparity at Z is f B / (Z p) pixels.
    """
    per_px = depth * depth * pixel_size / (focal_length * baseline)
    return {
        "disparity_at_focus_px": focal_length * baseline / (depth * pixel_size),
        "depth_per_pixel_mm": per_px,
        "depth_resolution_mm": per_px * precision_px,
    }


# --- configuration -----------------------------------------------------------------------------------------
def parse_sensor(value: Any) -> tuple[float, float]:
    """Sensor size from "WxH" (mm, e.g. "22.5x16.9") or a two-number list."""
    if isinstance(value, str):
        parts = value.lower().replace("\u00d7", "x").split("x")
    elif isinstance(value, (list, tuple)):
        parts = list(value)
    else:
        parts = []
    try:
        width, height = (float(p) for p in parts)
    except (TypeError, ValueError):
        raise DstereoError(f"sensor ({describe('sensor')}) must be WIDTHxHEIGHT in mm, e.g. 22.5x16.9; got {value!r}")
    return (width, height)


def _positive(key: str, value: Any) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        raise DstereoError(f"{key.replace('_', ' ')} ({describe(key)}) must be a positive number; got {value!r}")
    return float(value)


def make_config(settings: Mapping[str, Any]) -> OpticsConfig:
    """Checked `OpticsConfig` from a dict of config keys; every problem is a `DstereoError` naming the key."""
    unknown = sorted(set(settings) - set(CONFIG_KEYS))
    if unknown:
        raise DstereoError(f"unknown optics parameter(s) {', '.join(unknown)}; allowed: {', '.join(CONFIG_KEYS)}")
    for key in REQUIRED_KEYS:
        if settings.get(key) is None:
            raise DstereoError(f"missing {key.replace('_', ' ')}: pass {describe(key)}")
    values = {k: v for k, v in settings.items() if v is not None}
    if ("sensor" in values) == ("crop_factor" in values):
        raise DstereoError(f"give exactly one of the sensor size ({describe('sensor')}) "
                           f"or the crop factor ({describe('crop_factor')})")
    if "sensor" in values:
        values["sensor"] = tuple(_positive("sensor", v) for v in parse_sensor(values["sensor"]))
    choice = values.get("dof_focal_length", "effective")
    if choice not in DOF_FOCAL_CHOICES:
        raise DstereoError(f"dof focal length ({describe('dof_focal_length')}) must be one of "
                           f"{', '.join(DOF_FOCAL_CHOICES)}; got {choice!r}")
    for key in set(values) - {"sensor", "dof_focal_length"}:
        values[key] = _positive(key, values[key])
    config = OpticsConfig(**values)
    return _check_geometry(config, explicit_dof="dof_focal_length" in values)


def _check_geometry(config: OpticsConfig, explicit_dof: bool = True) -> OpticsConfig:
    """Refuse what no thin lens can do; where only the thesis's DoF convention fails, fall back to the lens's own
    focal length unless that convention was asked for by name (the notes then say so)."""
    _check_units(config)
    s, f = config.focus_distance, config.focal_length
    if s <= f:
        raise DstereoError(
            f"focus distance ({describe('focus_distance')}) {s:g} mm must exceed the lens focal length {f:g} mm; a "
            "thin lens forms no real image of a subject at or inside its focal length")
    f_dof = dof_focal_length_mm(config)
    if s <= f_dof:
        if explicit_dof:
            raise DstereoError(
                f"focus distance ({describe('focus_distance')}) {s:g} mm is possible with the {f:g} mm lens, but "
                f"`dof_focal_length` effective puts the 35 mm-equivalent focal length {f_dof:g} mm into the thin-lens "
                f"DoF equations, which then need a focus distance above {f_dof:g} mm; set `dof_focal_length` lens "
                "for the depth of field of the lens itself")
        config = replace(config, dof_focal_length="lens")
    if config.baseline is not None and config.pixel_size is None:
        raise DstereoError(
            f"the stereo depth resolution needs the pixel size: pass {describe('pixel_size')} with the baseline")
    return config


# Light dstereo's cameras see: 100 nm (UV) to 2 um (short-wave IR); a value outside is a unit slip (um for mm).
WAVELENGTH_RANGE_MM = (1e-4, 2e-3)


def _check_units(config: OpticsConfig) -> None:
    """Values a unit slip produces (micrometres given as mm, a CoC or pixel as large as the sensor): refused."""
    lo, hi = WAVELENGTH_RANGE_MM
    if not lo <= config.wavelength <= hi:
        raise DstereoError(f"wavelength ({describe('wavelength')}) {config.wavelength:g} mm is outside {lo:g}..{hi:g} "
                           "mm (100 nm to 2 um); lengths are in mm: 550 nm is 0.00055")
    sensor = sensor_of(config)[0]
    for key, value in (("coc", config.coc), ("pixel_size", config.pixel_size)):
        if value is not None and value >= min(sensor) / 10:
            raise DstereoError(f"{key.replace('_', ' ')} ({describe(key)}) {value:g} mm is at least a tenth of the "
                               f"{min(sensor):g} mm sensor side; lengths are in mm (a 5 um pixel is 0.005)")


def image_distance(focus_distance: float, focal_length: float) -> float:
    """Thin-lens image distance v = 1 / (1/f - 1/s), mm: the principal distance when focused at s."""
    return 1.0 / (1.0 / focal_length - 1.0 / focus_distance)


# --- the whole calculation ---------------------------------------------------------------------------------
def sensor_of(config: OpticsConfig) -> tuple[tuple[float, float], bool]:
    """Sensor (w, h) in mm and whether it was derived from the crop factor (3:2 aspect)."""
    if config.sensor is not None:
        return config.sensor, False
    return sensor_from_crop_factor(config.crop_factor), True


def crop_factor_of(config: OpticsConfig) -> float:
    """The given crop factor, or eq. 2.3 on the given sensor (not rounded)."""
    return config.crop_factor if config.crop_factor is not None else crop_factor_from_sensor(config.sensor)


def coc_of(config: OpticsConfig) -> float:
    """The given CoC (mm), or eq. 2.4-2.6 on the sensor diagonal (not rounded)."""
    return config.coc if config.coc is not None else coc_from_sensor(sensor_of(config)[0])


def dof_focal_length_mm(config: OpticsConfig) -> float:
    """Focal length (mm) put into eq. 5.1-5.3: effective (thesis) or the lens's own."""
    if config.dof_focal_length == "lens":
        return config.focal_length
    return effective_focal_length(config.focal_length, crop_factor_of(config))


def compute_optics(config: OpticsConfig) -> dict[str, Any]:
    """Every quantity of the calculator as a flat dict (lengths in mm, angles in degrees) plus `notes`."""
    sensor, sensor_derived = sensor_of(config)
    coc = coc_of(config)
    f_dof = dof_focal_length_mm(config)
    airy = airy_disk_diameter(config.f_number, config.wavelength)
    out: dict[str, Any] = {
        "focus_distance_mm": config.focus_distance,
        "focal_length_mm": config.focal_length,
        "f_number": config.f_number,
        "sensor_width_mm": sensor[0],
        "sensor_height_mm": sensor[1],
        "sensor_diagonal_mm": diagonal(sensor),
        "crop_factor": crop_factor_of(config),
        "effective_focal_length_mm": effective_focal_length(config.focal_length, crop_factor_of(config)),
        "dof_focal_length": config.dof_focal_length,
        "dof_focal_length_mm": f_dof,
        "coc_mm": coc,
        **depth_of_field(config.focus_distance, f_dof, config.f_number, coc),
        "wavelength_mm": config.wavelength,
        "pixel_size_mm": config.pixel_size,
        "airy_disk_mm": airy,
        **diffraction_check(airy, coc, config.pixel_size),
        **field_of_view(sensor, config.focal_length),
        **footprint(sensor, config.focal_length, config.focus_distance),
        "baseline_mm": config.baseline,
    }
    if config.baseline is not None:
        out["disparity_precision_px"] = config.disparity_precision
        out.update(stereo_depth_resolution(
            config.focus_distance, config.focal_length, config.baseline, config.pixel_size, config.disparity_precision))
    out["notes"] = _notes(config, sensor_derived, out)
    return out


def _notes(config: OpticsConfig, sensor_derived: bool, out: Mapping[str, Any]) -> list[str]:
    notes = []
    if sensor_derived:
        notes.append("sensor size derived from the crop factor assuming a 3:2 aspect ratio")
    if config.coc is None:
        notes.append("circle of confusion derived from the sensor diagonal (thesis eq. 2.4-2.6)")
    if config.dof_focal_length == "effective":
        notes.append("depth of field uses the effective focal length with the sensor's CoC, as the thesis "
                     "does; --dof-focal-length lens gives the thin-lens value for the lens itself")
    effective = effective_focal_length(config.focal_length, crop_factor_of(config))
    if config.dof_focal_length == "lens" and config.focus_distance <= effective:
        notes.append(f"the thesis's DoF convention (effective focal length {effective:.4g} mm) needs a focus distance "
                     "beyond it; the depth of field uses the lens's own focal length")
    v = image_distance(config.focus_distance, config.focal_length)
    if v > 1.1 * config.focal_length:
        notes.append(f"close focus: the lens sits {v:.4g} mm from the sensor ({v / config.focal_length:.2f} x its "
                     "focal length, thin lens); field of view, footprint and depth resolution assume the principal "
                     "distance is the focal length and are off by that factor "
                     f"(magnification {v / config.focus_distance:.3g})")
    if out["far_is_infinite"]:
        notes.append("focus at or beyond the hyperfocal distance: everything from the near limit to infinity is sharp")
    if out["diffraction_limited"]:
        notes.append("diffraction limits resolution: open the aperture (smaller f-number)")
    return notes


# --- the curves of figures 5.1-5.3 (drawn by dstereo.io.optics_figures) ---------------------------------------
def focal_axis(config: OpticsConfig, n: int = 200) -> np.ndarray:
    """Lens focal lengths (mm) from f/2 to 2 f, kept short enough for the DoF focal length to focus at s."""
    scale = dof_focal_length_mm(config) / config.focal_length
    top = min(2.0 * config.focal_length, 0.5 * config.focus_distance / max(scale, 1.0))
    return np.linspace(config.focal_length / 2.0, max(top, config.focal_length), n)


def f_number_axis(config: OpticsConfig, n: int = 200) -> np.ndarray:
    """f-numbers from 1 to 32 (or twice the chosen one, if larger)."""
    return np.linspace(1.0, max(32.0, 2.0 * config.f_number), n)


def total_dof_curve(config: OpticsConfig, focal, f_number) -> np.ndarray:
    """Total DoF (mm) for lens focal length(s) and f-number(s), NaN where it is infinite."""
    scale = dof_focal_length_mm(config) / config.focal_length
    total = total_depth_of_field(config.focus_distance, scale * np.asarray(focal), f_number, coc_of(config))
    return np.where(np.isfinite(total), total, np.nan)


@dataclass(frozen=True)
class DofCurves:
    """The curves of the thesis's figures 5.1-5.3 (`io.optics_figures` draws them): total DoF (mm, NaN where
    infinite) against the lens focal length at the chosen N, against N at the chosen f, over a (f, N) grid, and at
    the chosen set-up."""

    focal: np.ndarray  # (200,) mm
    total_vs_focal: np.ndarray
    f_number: np.ndarray  # (200,)
    total_vs_f_number: np.ndarray
    grid_focal: np.ndarray  # (120, 120) mm
    grid_f_number: np.ndarray
    grid_total: np.ndarray
    chosen: float


def dof_curves(config: OpticsConfig) -> DofCurves:
    focal, f_number = focal_axis(config), f_number_axis(config)
    grid_focal, grid_f_number = np.meshgrid(focal_axis(config, 120), f_number_axis(config, 120))
    return DofCurves(focal, total_dof_curve(config, focal, config.f_number), f_number,
                     total_dof_curve(config, config.focal_length, f_number), grid_focal, grid_f_number,
                     total_dof_curve(config, grid_focal, grid_f_number),
                     float(total_dof_curve(config, config.focal_length, config.f_number)))

