"""`dstereo diff A B`: two calibrations of one camera compared, with what their uncertainties predict.

Reads both cameras and their uncertainty files (`io.diff_files`), compares them by
`uncertainty.camera_diff.projection_diff` (the statistic each split of `--cross-validate` computes) and writes
the results folder. The range defaults to A's projection-uncertainty map's (the mean board distance of A's
calibration), the grid to that map's; both cameras must describe one image size and use one length unit (the
range is in it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.diff_files import DiffInput, read_diff_input
from dstereo.uncertainty.camera_diff import GRID, LensCamera, ProjectionDiff, projection_diff
from dstereo.uncertainty.projection import model_key

# Above this many sigma (the covariance's own) between a camera file's values and the values its covariance file
# belongs to, the two are different solves (--per-set's survivors, --final mean, or files from two runs): said.
VALUES_SIGMA = 0.1
MAP_CHECK_RTOL = 1e-6  # a recomputed pose-compensated map against the written one (the same numbers, rounding)


@dataclass
class DiffResult:
    projection: ProjectionDiff
    inputs: tuple[DiffInput, DiffInput]
    range_source: str
    notes: list[str]

    def summary(self) -> dict:
        d = self.projection
        predicted = d.cov is not None
        out = {"a": self.inputs[0].label[3:], "b": self.inputs[1].label[3:],
               "files_read": self.inputs[0].files + self.inputs[1].files,
               "distance": None if np.isinf(d.range_) else d.range_, "distance_source": self.range_source,
               "unit": self.inputs[0].unit, "grid": [len(d.u), len(d.v)],
               "pixels": int(d.ok.sum()), "pixels_left_out": int(d.ok.size - d.ok.sum()),
               "weighting": d.weighting,
               "implied_transform": {"rvec": d.transform[:3].tolist(), "rotation_deg": float(
                   np.degrees(np.linalg.norm(d.transform[:3]))), "translation": d.transform[3:].tolist()},
               "observed_rms_px": d.rms, "observed_max_px": float(np.nanmax(np.hypot(d.diff[..., 0], d.diff[..., 1]))),
               "prediction": None}
        if predicted:
            band = d.band()
            inside = band["ratio"][0] <= d.ratio <= band["ratio"][1]
            out["prediction"] = {
                "predicted_rms_px": d.predicted_rms, "ratio": d.ratio, "ratio_raw": d.ratio_raw,
                "typical_raw_ratio_if_right": d.typical, "effective_modes": d.modes,
                "mahalanobis_median": d.mahalanobis_median, "band_if_right": band,
                "inside_band": bool(inside and band["mahalanobis_median"][0] <= d.mahalanobis_median
                                    <= band["mahalanobis_median"][1]),
                "ratio_vs_pose_compensated_maps": None if np.isnan(d.ratio_vs_maps) else d.ratio_vs_maps,
                "corner_field": d.field_figures(),
                "note": ("ratio: the weighted rms difference over the rms the two covariances predict after the "
                         "transform fit, divided by its typical value if right (1 if right, in the log); "
                         "band_if_right: where a right prediction's ratio and median Mahalanobis fall on this grid; "
                         "both over the pixels inside both cameras' corners' fields where the files give them "
                         "(corner_field: the pooled ratio inside and outside, where the lens model is extrapolated)")}
        out["verdict"] = self.verdict()
        out["notes"] = self.notes
        return out

    def verdict(self) -> str:
        d = self.projection
        head = (f"observed rms difference {d.rms:.3g} px over {int(d.ok.sum())} grid pixels at "
                f"{'infinity' if np.isinf(d.range_) else f'{d.range_:.4g}'}")
        if d.cov is None:
            return head + "; no prediction (a camera has no covariance)"
        band = d.band()
        lo, hi = band["ratio"]
        text = (f"{head}, predicted {d.predicted_rms:.3g} px: ratio {d.ratio:.2f} (1 if right; a right prediction "
                f"reads {lo:.2f}-{hi:.2f} here, {BAND_TEXT}), median Mahalanobis {d.mahalanobis_median:.2f} "
                f"(1.18 if right; {band['mahalanobis_median'][0]:.2f}-{band['mahalanobis_median'][1]:.2f})")
        f = d.field_figures()
        if f is not None:
            text += f" over the {f['pixels_inside']} pixels inside both corners' fields"
        if d.ratio > hi:
            text += (": the cameras differ more than their uncertainties allow (optimistic +-, or not the same "
                     "camera: a knock, a refocus, temperature)")
        elif d.ratio < lo:
            text += ": the cameras agree better than their uncertainties say (pessimistic +-)"
        else:
            text += ": consistent with their uncertainties"
        if f is not None and np.isfinite(f["ratio_pooled_outside"]) and "outside_over_inside_band_if_right" in f:
            blo, bhi = f["outside_over_inside_band_if_right"]
            text += (f"; outside the fields ({f['pixels_outside']} pixels, the lens model extrapolated: the maps there "
                     f"are a lower bound) the pooled ratio reads {f['ratio_pooled_outside']:.2f}, "
                     f"{f['outside_over_inside']:.2f}x inside (a right prediction {blo:.2f}-{bhi:.2f}x)")
        return text


BAND_TEXT = "5-95 %"


def _camera(inp: DiffInput, notes: list[str]) -> LensCamera:
    """The LensCamera of an input: the camera file's values; its covariance file's covariance (the values it
    belongs to checked against the file's)."""
    k = np.array([inp.K[0, 0], inp.K[1, 1], inp.K[0, 2], inp.K[1, 2]], float)
    names: tuple[str, ...] = ()
    if inp.model == "splined":
        from dstereo.models.camera import INTRINSIC_NAMES

        names = INTRINSIC_NAMES + tuple(inp.free)
    model = model_key(names) if inp.model == "splined" else inp.model
    params = np.concatenate([k, np.asarray(inp.coeffs, float)])
    cov = inp.covariance
    if cov is None:
        return LensCamera(model, params, image_size=inp.image_size, label=inp.label)
    from dstereo.uncertainty.camera_diff import slot_names

    slots = slot_names(model)
    unknown = [n for n in cov["names"] if n not in slots]
    if unknown:
        raise DstereoError(f"camera {inp.label}: its covariance names {unknown}, not parameters of its {model} lens; "
                           "the covariance file belongs to another camera (remove it or calibrate again)")
    idx = [slots.index(n) for n in cov["names"]]
    std = np.sqrt(np.maximum(np.diag(cov["cov"]), 1e-300))
    off = (np.zeros(len(idx)) if cov.get("values") is None else
           np.abs(params[idx] - np.asarray(cov["values"], float)) / std)
    if np.max(off) > VALUES_SIGMA:
        worst = int(np.argmax(off))
        notes.append(f"camera {inp.label}: its values differ from those its covariance belongs to ({cov['solve']}) "
                     f"by up to {off[worst]:.2g} sigma ({cov['names'][worst]}): the camera file holds another solve "
                     "(--per-set's survivors or --final mean); the prediction is that of the covariance's solve")
    return LensCamera(model, params, tuple(cov["names"]), cov["cov"], inp.image_size, inp.label,
                      joint=cov.get("joint"), poses=cov.get("poses"))


def _map_trace(inp: DiffInput, range_: float, grid) -> np.ndarray | None:
    """(gh, gw) trace of the camera's written map when it is on this grid at this range, else None."""
    m = inp.written_map
    if m is None or m["cov"].shape[:2] != (grid[1], grid[0]) or not np.isclose(m["range"], range_, rtol=1e-9):
        return None
    return np.trace(m["cov"], axis1=-2, axis2=-1)


def compute_diff(a_spec: str, b_spec: str, distance: float | None = None,
                 grid: tuple[int, int] | None = None) -> DiffResult:
    """Read and compare (module docstring); `distance` in the calibrations' unit (inf: rotation only)."""
    inputs = (read_diff_input(a_spec, "A"), read_diff_input(b_spec, "B"))
    a_in, b_in = inputs
    notes = [n for i in inputs for n in i.notes]
    if a_in.image_size is None or b_in.image_size is None:
        raise DstereoError("a camera file names no image size (image_width, image_height); add it to the file")
    if tuple(a_in.image_size) != tuple(b_in.image_size):
        raise DstereoError(f"image sizes differ: A {tuple(a_in.image_size)}, B {tuple(b_in.image_size)}; dstereo diff "
                           "compares two calibrations of one camera at one resolution")
    if a_in.unit and b_in.unit and a_in.unit != b_in.unit:
        raise DstereoError(f"units differ: A in {a_in.unit}, B in {b_in.unit}; the distance is a length in both "
                           "calibrations' unit: calibrate both with the same --square unit")
    source = "--distance"
    if distance is None:
        for inp, which in ((a_in, "A"), (b_in, "B")):
            found = (inp.covariance or {}).get("range") or (inp.written_map or {}).get("range")
            if found:
                distance, source = float(found), f"{which}'s projection-uncertainty map (its mean board distance)"
                break
        else:
            raise DstereoError("no distance: neither camera has a projection-uncertainty map to take it from; give "
                               "--distance (in the calibrations' unit, or inf)")
    if not (distance > 0):
        raise DstereoError(f"--distance {distance}: give a positive distance (the calibrations' unit) or inf")
    if grid is None:
        grid = next((tuple(inp.covariance["grid"]) for inp in inputs
                     if inp.covariance is not None and inp.covariance.get("grid")), GRID)
    if grid[0] < 2 or grid[1] < 2:
        raise DstereoError(f"--grid {grid[0]}x{grid[1]}: give at least 2x2 pixels (columns x rows)")
    cams = [_camera(inp, notes) for inp in inputs]
    cams = [c if c.joint is not None else _with_written_map(c, inp, distance, grid) for c, inp in zip(cams, inputs)]
    field = _field(inputs, grid, notes)
    d = projection_diff(cams[0], cams[1], float(distance), tuple(grid), tuple(a_in.image_size), field=field)
    notes += _check_written_maps(cams, inputs, distance, grid)
    if d.weighting != "pose-compensated maps":
        notes.append(f"the transform fit weights every pixel alike: {d.weighting}; image corners the calibrations "
                     "extrapolate then pull the fit (the ratio stays right, its band wider)")
    return DiffResult(d, inputs, source, notes)


def _field_of(inp: DiffInput, grid) -> np.ndarray | None:
    """(gh, gw) bool: the camera's corners' field as its files give it on this grid (its covariance file's, else
    its written map's), or None."""
    shape = (grid[1], grid[0])
    for f in ((inp.covariance or {}).get("field"), (inp.written_map or {}).get("field")):
        if f is not None and np.shape(f) == shape:
            return np.asarray(f, bool)
    return None


def _field(inputs, grid, notes: list[str]) -> np.ndarray | None:
    """The pixels inside both cameras' corners' fields, where the maps claim something and the statistic is taken
    (`camera_diff` module docstring); None, with a note, when a camera's files carry no field on this grid."""
    fields = [_field_of(inp, grid) for inp in inputs]
    if any(f is None for f in fields):
        missing = ", ".join(inp.label for inp, f in zip(inputs, fields) if f is None)
        notes.append(f"no corners' field on this grid for {missing} (a folder written before it existed, another "
                     "program's file, or another --grid): the statistic spans every grid pixel, including where the "
                     "lens model is extrapolated")
        return None
    return fields[0] & fields[1]


def _with_written_map(cam: LensCamera, inp: DiffInput, range_: float, grid) -> LensCamera:
    from dataclasses import replace

    trace = _map_trace(inp, range_, grid)
    return cam if trace is None else replace(cam, map_trace=trace)


def _check_written_maps(cams, inputs, range_: float, grid) -> list[str]:
    """Where a camera has both its joint covariance and a written map at this range and grid: the same numbers
    (they come from one solve), else a note."""
    out = []
    for cam, inp in zip(cams, inputs):
        written = _map_trace(inp, range_, grid)
        if cam.joint is None or written is None:
            continue
        mine = cam.pose_compensated_trace(range_, grid, inp.image_size)
        good = np.isfinite(mine) & np.isfinite(written)
        if good.any() and not np.allclose(mine[good], written[good], rtol=MAP_CHECK_RTOL):
            out.append(f"camera {inp.label}: its projection_uncertainty.npz differs from the map its "
                       "calibration_covariance.npz gives (files from different runs?); the covariance file's is used")
    return out


def run_diff(a_spec: str, b_spec: str, out: Path | None = None, distance: float | None = None,
             grid: tuple[int, int] | None = None, force: bool = False) -> DiffResult:
    """`compute_diff`, then the results folder `out` (None: none)."""
    if out is not None:
        from dstereo.io.output_location import check_not_inputs
        from dstereo.io.results import check_output

        check_output(out, force)  # before any work
        check_not_inputs(out, [s.rsplit(":", 1)[0] if ":" in Path(s).name else s for s in (a_spec, b_spec)])
    result = compute_diff(a_spec, b_spec, distance, grid)
    if out is not None:
        from functools import partial

        from dstereo.io.diff_files import diff_png, write_diff

        d = result.projection
        arrays = {"u": d.u, "v": d.v, "distance": d.range_, "diff": d.diff, "ok": d.ok, "weight": d.weight,
                  "transform": d.transform}
        predicted = None
        if d.cov is not None:
            arrays.update(cov=d.cov, mahalanobis=d.mahalanobis)
            predicted = np.sqrt(np.trace(d.cov, axis1=-2, axis2=-1))
        if d.map_trace is not None:
            arrays["map_trace"] = d.map_trace
        verdict = result.verdict()
        write_diff(Path(out), force, result.summary(), arrays,
                   partial(diff_png, u=d.u, v=d.v, diff=d.diff, predicted=predicted, maha=d.mahalanobis,
                           title=verdict))
    return result
