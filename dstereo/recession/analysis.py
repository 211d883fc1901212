"""Recession of the front face over a sequence of stereo pairs: a surface per frame, heights per grid cell along
the sample axis, recession against the reference frame, its value at the stagnation point and the rates.

The reference is the first frame (the first one that reconstructs, if earlier ones fail). A frame that fails
(unreadable image, no disparity, too little of the face) is recorded with its reason and left out of every
fit and map: nothing is interpolated. Library code: progress goes to a callback, nothing is printed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from dstereo.errors import DstereoError
from dstereo.recession.cell_scatter import CellScatter, cell_scatter
from dstereo.recession.fits import LineFit, PointValue, at_stagnation, line_band, line_fit, rate_map, with_common_part
from dstereo.recession.frame import Frame
from dstereo.recession.surface import Grid, SampleFrame, cell_heights, face_points, fit_face, frame_from_axis
from dstereo.recession.surface import grid_over, valid_points


LINE_BAND_POINTS = 200  # times at which the recession figure draws the line's band
STAGNATION_CELLS_ACROSS = 4  # radius in grid cells: ~50 cells in the disc for the 4-parameter quadratic


def stagnation_radius_for(grid_mm: float) -> float:
    """Default stagnation disc radius (mm): 2 mm, or 4 grid cells on a coarser grid. A fixed 2 mm disc holds 13
    cells of 1 mm, barely more than the quadratic's 4 parameters: measured on the tilted rendered sample at
    320x240 (1 mm grid; the since-removed experiments/range_stagnation.py), the stagnation RMS over seeds 0-4 was
    0.020-0.034 mm with 2 mm and 0.021-0.027 mm with 4 mm; at 640x480 (0.5 mm grid) 2 mm is 4 cells already."""
    return max(2.0, STAGNATION_CELLS_ACROSS * float(grid_mm)) if grid_mm > 0 else 2.0


@dataclass(frozen=True)
class RecessionConfig:
    """Analysis settings (mm unless stated). `axis`/`point`: the sample axis and stagnation point in the left
    camera frame (None: estimated from the reference frame; a given axis without a point keeps the estimated
    face centre). `slab_mm` (in front, behind): points this far in front of the reference face or behind it are
    not the face. A frame whose valid cells fall below `min_face_fraction` of the reference's fails.
    `refine_subpixel`: refine SGBM's pixel-locked disparity (`dstereo.stereo.subpixel`) before triangulating
    (sets the reconstruction's `refine`). `stagnation_radius_mm` None: max(2 mm, STAGNATION_CELLS_ACROSS grid
    cells), so the stagnation disc holds ~50 cells whatever the grid (`stagnation_radius_for`)."""

    grid_mm: float = 0.5
    stagnation_radius_mm: float | None = None
    stagnation_model: str = "quadratic"
    axis: tuple[float, float, float] | None = None
    point: tuple[float, float, float] | None = None
    min_points_per_cell: int = 8
    min_face_fraction: float = 0.3
    slab_mm: tuple[float, float] = (5.0, 30.0)
    refine_subpixel: bool = True

    def __post_init__(self):
        if self.stagnation_radius_mm is None:
            object.__setattr__(self, "stagnation_radius_mm", stagnation_radius_for(self.grid_mm))
        if not self.stagnation_radius_mm > 0:
            raise DstereoError(f"`stagnation_radius` {self.stagnation_radius_mm}: need a positive radius in mm")
        if self.stagnation_radius_mm < 2 * self.grid_mm:
            raise DstereoError(f"`stagnation_radius` {self.stagnation_radius_mm} mm is under two grid cells "
                               f"({self.grid_mm} mm); use a larger radius or a finer `grid`")
        if self.point is not None and self.axis is None:
            raise DstereoError("`point` needs `axis` too (the point alone does not fix the axis)")


@dataclass
class FrameResult:
    """One frame: its time, status ('ok' or 'skipped') with the reason, and its stagnation values (mm)."""

    index: int
    name: str
    time_s: float
    status: str = "ok"
    reason: str = ""
    recession: PointValue = PointValue(float("nan"), float("nan"), 0)
    height: PointValue = PointValue(float("nan"), float("nan"), 0)
    valid_cells: int = 0
    valid_fraction: float = float("nan")

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass
class RecessionResult:
    """Everything `run_recession` found. Maps are (frames, ny, nx) over `grid`, NaN where a cell had too few
    points or its frame was skipped."""

    frames: list[FrameResult]
    sample: SampleFrame
    grid: Grid
    reference: int
    heights: np.ndarray
    height_se: np.ndarray
    recession: np.ndarray
    fit: LineFit
    weighted_fit: LineFit | None
    rates: dict[str, np.ndarray]
    config: RecessionConfig
    warnings: list[str] = field(default_factory=list)
    random_sigma: np.ndarray | None = None  # (frames, ny, nx) RMS per-point random height std per cell, mm
    random_se: np.ndarray | None = None  # (frames, ny, nx) the cell height's random standard error it implies
    noise_checks: dict = field(default_factory=dict)  # frame index -> summary['disparity_noise'] plane check
    search_ranges: dict[int, dict] = field(default_factory=dict)  # frame index -> summary['search_range']
    fit_band: tuple | None = None  # (times, half-width) of the fitted line's 95 % band (None: <= 2 frames)
    common_part: CellScatter | None = None  # the rate's error common to all frames (`cell_scatter`), in fit's interval

    @property
    def times(self) -> np.ndarray:
        return np.array([f.time_s for f in self.frames])

    @property
    def ok(self) -> np.ndarray:
        return np.array([f.ok for f in self.frames])

    def summary(self) -> dict:
        ok = [f for f in self.frames if f.ok]
        u, v = self.grid.centres()
        stag = at_stagnation(self.rates["rate"], u, v, self.config.stagnation_radius_mm, self.config.stagnation_model)
        return {
            "units": {"length": "mm", "time": "s", "rate": "mm/s"},
            "frames": len(self.frames), "frames_used": len(ok),
            "reference_frame": self.frames[self.reference].name,
            "skipped": [{"frame": f.index, "name": f.name, "time_s": f.time_s, "reason": f.reason}
                        for f in self.frames if not f.ok],
            "rate": self.fit.as_dict(),
            "rate_weighted": self.weighted_fit.as_dict() if self.weighted_fit is not None else None,
            "rate_map_at_stagnation": {"rate": stag.value, "se": stag.se, "cells": stag.cells},
            "final_recession_mm": ok[-1].recession.value if ok else None,
            "sample": self.sample.as_dict(),
            "grid": {"spacing_mm": self.grid.spacing, "nx": len(self.grid.u), "ny": len(self.grid.v),
                     "u_range_mm": [float(self.grid.u[0]), float(self.grid.u[-1])],
                     "v_range_mm": [float(self.grid.v[0]), float(self.grid.v[-1])]},
            "config": asdict(self.config),
            "method": "per grid cell: local plane through the cell's points along the axis, at the cell centre "
                      "(robust, MAD-trimmed); recession = height - reference height; stagnation value: "
                      f"{self.config.stagnation_model} fit over the cells within "
                      f"{self.config.stagnation_radius_mm:g} mm; rate: least-squares line over time, 95 % "
                      "interval from the fit residuals (the frames' scatter, n - 2 dof) and the part common to all "
                      "frames (the disc cells' own rate errors, rate_common_part), in quadrature, Student's t on "
                      "their Welch-Satterthwaite dof",
            "rate_common_part": self.common_part.as_dict() if self.common_part is not None else None,
            "search_range": _range_summary(self.search_ranges, self.reference),
            "warnings": list(self.warnings),
            "random_uncertainty": _random_summary(self),
        }


def _range_summary(ranges: dict[int, dict], reference: int) -> dict | None:
    """The reference frame's disparity search range, and the span over all frames (the first frame's range is
    used for the later ones, widened where one runs off it)."""
    if not ranges:
        return None
    ref = ranges.get(reference) or next(iter(ranges.values()))
    return ref | {"frames": {"min_disparity": min(r["min_disparity"] for r in ranges.values()),
                             "max_disparity": max(r["max_disparity"] for r in ranges.values()),
                             "widened": sum(bool(r["widened"]) for r in ranges.values()),
                             "note": "the first frame's range serves every later frame (widened where one runs "
                                     "off it); span over all frames"}}


def _sample_frame(points: np.ndarray, config: RecessionConfig) -> tuple[SampleFrame, np.ndarray | None]:
    """The sample frame, and the face points (mask over the valid points) when the auto fit found them."""
    if config.axis is None:
        fit = fit_face(points, config.grid_mm)
        return fit.frame, fit.keep
    if config.point is not None:
        frame = frame_from_axis(config.axis, config.point)
        return replace(frame, source="given axis and point"), None
    auto = fit_face(points, config.grid_mm).frame
    return replace(frame_from_axis(config.axis, auto.point), source="given axis, estimated face centre"), None


def _settled_face(uvh: np.ndarray, grid_mm: float, passes: int = 10) -> np.ndarray:
    """Face points in a given frame: `face_points` repeated from its own result until the set stops changing."""
    keep, _ = face_points(uvh, grid_mm)
    for _ in range(passes):
        new, _ = face_points(uvh, grid_mm, start=keep)
        if np.array_equal(new, keep):
            break
        keep = new
    return keep


class _Reference:
    """The reference frame's sample frame, grid, face slab, face cells and cell heights. Only the grid cells the
    reference face covers (its largest connected region on the quadric, `face_points`) carry heights: a side
    wall or a stray match outside the face never enters a map or the face centre."""

    def __init__(self, points: np.ndarray, config: RecessionConfig):
        self.sample, keep = _sample_frame(points, config)
        uvh = self.sample.coordinates(valid_points(points))
        if keep is None:
            keep = _settled_face(uvh, config.grid_mm)
        face = uvh[keep]
        self.grid = grid_over(face[:, :2], config.grid_mm)
        self.slab = (float(face[:, 2].min()) - config.slab_mm[0], float(face[:, 2].max()) + config.slab_mm[1])
        cells = self.grid.cell_index(face[:, :2])
        self.face_cells = np.zeros(self.grid.shape[0] * self.grid.shape[1], bool)
        self.face_cells[cells[cells >= 0]] = True
        self.face_cells = self.face_cells.reshape(self.grid.shape)


def _frame_heights(uvh: np.ndarray, ref: _Reference, config: RecessionConfig):
    """Cell heights of a frame from its valid points' face coordinates (`ref.sample.coordinates`)."""
    uvh = uvh[(uvh[:, 2] >= ref.slab[0]) & (uvh[:, 2] <= ref.slab[1])]
    height, se, count = cell_heights(uvh, ref.grid, config.min_points_per_cell)
    height[~ref.face_cells], se[~ref.face_cells], count[~ref.face_cells] = np.nan, np.nan, 0
    return height, se, count


@dataclass
class FrameOutcome:
    """One frame measured on the reference's grid (a task's result; stored as it finishes): status 'ok',
    'skipped' (a DstereoError: the frame is unusable) or 'failed' (its worker died: not measured), the cell
    heights and standard errors, the per-cell random sigmas, the noise check and the reconstructor's log entry
    (search range and warnings)."""

    status: str = "ok"
    reason: str = ""
    valid_fraction: float = float("nan")
    heights: np.ndarray | None = None
    se: np.ndarray | None = None
    sigma: np.ndarray | None = None
    sigma_se: np.ndarray | None = None
    check: dict | None = None
    log: dict | None = None

    ARRAYS = ("heights", "se", "sigma", "sigma_se")

    def to_store(self, key: str) -> tuple[dict, dict]:
        arrays = {k: getattr(self, k) for k in self.ARRAYS if getattr(self, k) is not None}
        meta = {"key": key, "status": self.status, "reason": self.reason, "valid_fraction": self.valid_fraction,
                "check": self.check, "log": self.log}
        return arrays, meta

    @classmethod
    def from_store(cls, arrays: dict, meta: dict) -> "FrameOutcome":
        return cls(meta["status"], meta["reason"], meta["valid_fraction"], check=meta["check"], log=meta["log"],
                   **{k: arrays.get(k) for k in cls.ARRAYS})


def measure_frame(frame: Frame, reconstruct, ref: _Reference, config: RecessionConfig) -> FrameOutcome:
    """The task of one frame after the reference: reconstruct it and measure it on the reference's grid."""
    return _measure(frame, reconstruct, config, ref)[0]


def _measure(frame: Frame, reconstruct, config: RecessionConfig, ref: _Reference | None = None):
    """(outcome, reference): without `ref` the frame is tried as the reference (its own grid, checked)."""
    out = FrameOutcome()
    try:
        points, sigma_vectors, check = _points_and_sigmas(reconstruct(frame))
        flat = np.asarray(points, float).reshape(-1, 3)
        valid = np.all(np.isfinite(flat), axis=1)
        out.valid_fraction = float(valid.mean())
        current = ref if ref is not None else _Reference(points, config)
        uvh = current.sample.coordinates(flat[valid])  # the heights' and the random sigmas' points
        heights, se, _ = _frame_heights(uvh, current, config)
        if ref is None:
            _check_reference(heights, config)
    except DstereoError as exc:
        out.status, out.reason, current = "skipped", str(exc), None
    else:
        out.heights, out.se, out.check = heights, se, check
        if sigma_vectors is not None:
            out.sigma, out.sigma_se = _cell_random_sigma(flat, sigma_vectors, current, config, (valid, uvh))
    out.log = getattr(reconstruct, "log", {}).get(frame.key)
    return out, current


def measure_recession(frames: list[Frame], reconstruct, config: RecessionConfig = RecessionConfig(),
                      progress=None, runner=None, store=None) -> RecessionResult:
    """Reconstruct every frame with `reconstruct` and measure the recession (module docstring).

    The reference (the first frame that gives a surface) is found here, frame after frame; it fixes the grid
    and the disparity search range, and the frames after it are independent tasks on `runner`
    (`dstereo.runtime.tasks.FrameRunner`; default: one after another in this process). `store`
    (`dstereo.io.partial_store.PartialStore`): each finished frame is saved at once and frames already there are reused.
    `progress(stage, done, total)` is called once per frame. `reconstruct(frame) -> points (h, w, 3)`, or
    (points, per-point sigma vectors, noise check): `dstereo.jobs.recession.FrameReconstructor` reads and matches
    the images (`dstereo.jobs.recession.run_recession`); tests and other matchers pass their own. It raises
    DstereoError for a failed frame.
    """
    from functools import partial

    from dstereo.runtime.blas_threads import one_blas_thread
    from dstereo.runtime.tasks import FrameRunner

    report = progress or (lambda stage, done, total: None)
    runner = runner or FrameRunner(workers=1)
    results = [FrameResult(i, f.key.strip("_-. ") or f.left.stem, f.time_s) for i, f in enumerate(frames)]
    outcomes: dict[int, FrameOutcome] = {}
    ref, ref_index = None, -1
    report("frames", 0, len(frames))
    with one_blas_thread():  # as the frames after it (`dstereo.runtime.blas_threads`)
        for i, frame in enumerate(frames):  # in order: the first frame that gives a surface is the reference
            outcomes[i], ref = _measure(frame, reconstruct, config)
            report("frames", i + 1, len(frames))
            if ref is not None:
                ref_index = i
                break
    if ref is None:
        raise DstereoError("no frame of the sequence gave a surface to measure from; first failure: "
                           f"{outcomes[0].reason}")
    todo = []
    for i in range(ref_index + 1, len(frames)):
        stored = store.load(f"{i:06d}") if store is not None else None
        if stored is not None and stored[1].get("key") == frames[i].key and stored[1]["status"] != "failed":
            outcomes[i] = FrameOutcome.from_store(*stored)
        else:
            todo.append((i, frames[i]))

    def finished(task):
        if task.failed:
            outcomes[task.index] = FrameOutcome("failed", task.failed)
            return
        outcomes[task.index] = task.value
        if store is not None:
            store.save(f"{task.index:06d}", *task.value.to_store(frames[task.index].key))

    done = len(frames) - len(todo)
    report("frames", done, len(frames))
    runner.map(partial(measure_frame, reconstruct=reconstruct, ref=ref, config=config), todo, finished, progress,
               "frames", done, len(frames))
    return _collect(results, outcomes, ref, ref_index, config)


def _collect(results, outcomes: dict, ref: _Reference, ref_index: int, config) -> RecessionResult:
    """The per-frame outcomes (in frame order, wherever they ran) into the result: maps, fits, warnings."""
    maps, ses, sigmas, checks, log = {}, {}, {}, {}, {}
    for i, res in enumerate(results):
        o = outcomes[i]
        res.status, res.reason, res.valid_fraction = o.status, o.reason, o.valid_fraction
        if o.log is not None:
            log[i] = o.log
        if not res.ok:
            continue
        maps[i], ses[i] = o.heights, o.se
        if o.sigma is not None:
            sigmas[i] = (o.sigma, o.sigma_se)
        if o.check is not None:
            checks[i] = o.check
    failed = [r for r in results if r.status == "failed"]
    out = _assemble(results, ref, ref_index, maps, ses, config)
    if failed:
        out.warnings.append(f"{len(failed)} frame(s) failed (their worker process died): "
                            + ", ".join(r.name for r in failed[:10]) + "; they are left out of every fit and "
                            "map; rerun with --resume to measure them")
    out.noise_checks = checks
    off = {results[i].name: c["ratio"] for i, c in checks.items()
           if c.get("ratio") is not None and not 0.67 <= c["ratio"] <= 1.5}
    if off:
        out.warnings.append(f"the disparity noise model was off on {len(off)} frame(s) (observed / predicted scatter "
                            + ", ".join(f"{k}: {v:.2f}" for k, v in list(off.items())[:5])
                            + "); their per-point random sigmas are scaled to the observed level")
    if sigmas:
        out.random_sigma, out.random_se = np.full(out.heights.shape, np.nan), np.full(out.heights.shape, np.nan)
        for i, (m, se) in sigmas.items():
            out.random_sigma[i] = np.where(np.isfinite(out.heights[i]), m, np.nan)
            out.random_se[i] = np.where(np.isfinite(out.heights[i]), se, np.nan)
    out.search_ranges = {i: entry["search_range"] for i, entry in sorted(log.items())}
    out.warnings += [w for i in sorted(log) for w in log[i]["warnings"]]
    return out


# --- random (disparity-noise) uncertainty per cell, from the per-point sigmas (dstereo.stereo.disparity_noise) --------

CORRELATION_AREA_PX = 14.0  # (sum F)^2 / sum F^2 of the refinement's iterated kernel: pixels per independent error


def _points_and_sigmas(out):
    """A reconstructor returns points (h, w, 3), or (points, per-point random displacement vectors (h, w, 3),
    the frame's disparity-noise check (summary['disparity_noise']['plane_check']) or None)."""
    if not isinstance(out, tuple):
        return out, None, None
    return (*out, None)[:3] if len(out) == 2 else out


def _cell_random_sigma(points: np.ndarray, vectors: np.ndarray, ref: "_Reference", config, known=None):
    """(ny, nx) RMS over each cell's points of the random height std (the displacement along the sample axis),
    and the standard error of the cell's mean height it implies (count / CORRELATION_AREA_PX independent
    errors); cells of the face slab only, as `_frame_heights`. `known` (valid mask, face coordinates of the
    valid points): the coordinates already computed, reused when the vectors are finite on the same points."""
    p = np.asarray(points, float).reshape(-1, 3)
    vec = np.asarray(vectors, float).reshape(-1, 3)
    valid = known[0] if known is not None else np.all(np.isfinite(p), axis=1)
    ok = valid & np.all(np.isfinite(vec), axis=1)
    uvh = known[1] if known is not None and np.array_equal(ok, valid) else ref.sample.coordinates(p[ok])
    s_h = np.abs(vec[ok] @ ref.sample.axis)
    slab = (uvh[:, 2] >= ref.slab[0]) & (uvh[:, 2] <= ref.slab[1])
    idx = ref.grid.cell_index(uvh[slab, :2])
    inside = idx >= 0
    n_cells = ref.grid.shape[0] * ref.grid.shape[1]
    total = np.bincount(idx[inside], weights=s_h[slab][inside] ** 2, minlength=n_cells)
    count = np.bincount(idx[inside], minlength=n_cells)
    rms = np.where(count >= config.min_points_per_cell, np.sqrt(total / np.maximum(count, 1)), np.nan)
    se = rms / np.sqrt(np.maximum(count / CORRELATION_AREA_PX, 1.0))
    return rms.reshape(ref.grid.shape), se.reshape(ref.grid.shape)


def _random_summary(result) -> dict | None:
    """Median per-point random height std and the standard error of a cell height it implies (neighbours
    share errors over CORRELATION_AREA_PX pixels), beside the cells' own fit standard errors."""
    if result.random_sigma is None or not np.isfinite(result.random_sigma).any():
        return None
    sig = result.random_sigma[np.isfinite(result.random_sigma)]
    ratios = [c.get("ratio") for c in result.noise_checks.values()]
    return {"per_point_height_sigma_mm_median": float(np.median(sig)),
            "noise_check_ratio_per_frame": {result.frames[i].name: c.get("ratio")
                                            for i, c in sorted(result.noise_checks.items())},
            "noise_check_ratio_range": [min(r for r in ratios if r is not None),
                                        max(r for r in ratios if r is not None)] if any(
                                            r is not None for r in ratios) else None,
            "correlation_area_px": CORRELATION_AREA_PX,
            "cell_random_se_mm_median": float(np.nanmedian(result.random_se)),
            "cell_fit_se_mm_median": float(np.nanmedian(result.height_se)),
            "note": "per-point random std along the sample axis from the per-pixel disparity noise "
                    "(dstereo.stereo.disparity_noise, level checked on each frame); per cell: recession_maps.npz random_sigma_mm and "
                    "random_se_mm (the cell height's random standard error), beside the fit's own height_se_mm"}


def _check_reference(heights: np.ndarray, config: RecessionConfig, min_cells: int = 20) -> None:
    n = int(np.isfinite(heights).sum())
    if n < min_cells:
        raise DstereoError(f"only {n} grid cells of {config.grid_mm:g} mm hold {config.min_points_per_cell} or more "
                           "points in the reference frame; use a coarser `grid` (cells of ~4 x 4 pixels or more) or "
                           "a lower `min_points`")


def _assemble(results, ref: _Reference, ref_index: int, maps: dict, ses: dict, config) -> RecessionResult:
    shape = (len(results), *ref.grid.shape)
    heights, height_se = np.full(shape, np.nan), np.full(shape, np.nan)
    for i in maps:
        heights[i], height_se[i] = maps[i], ses[i]
    recession = heights - heights[ref_index]
    u, v = ref.grid.centres()
    ref_cells = int(np.isfinite(heights[ref_index]).sum())
    radius, model = config.stagnation_radius_mm, config.stagnation_model
    for i, res in enumerate(results):
        if not res.ok:
            continue
        res.valid_cells = int(np.isfinite(recession[i]).sum())
        res.recession = at_stagnation(recession[i], u, v, radius, model)
        res.height = at_stagnation(heights[i], u, v, radius, model)
        if res.valid_cells < config.min_face_fraction * ref_cells:
            res.status, res.reason = "skipped", (
                f"only {res.valid_cells} of the reference's {ref_cells} grid cells have a surface "
                f"(< {config.min_face_fraction:.0%}); the face is not seen well enough in this frame")
        elif not np.isfinite(res.recession.value):
            res.status, res.reason = "skipped", (
                f"{res.recession.cells} grid cells with a surface within {radius:g} mm of the stagnation point; "
                "too few for a value there")
        if not res.ok:
            heights[i] = height_se[i] = recession[i] = np.nan
    ok = np.array([r.ok for r in results])
    t = np.array([r.time_s for r in results])[ok]
    stag = np.array([r.recession.value for r in results])[ok]
    warnings = []
    if ok.sum() < 2:
        raise DstereoError(f"only {int(ok.sum())} frame(s) gave a recession; need at least 2 for a rate. Skipped: "
                           + "; ".join(f"{r.name}: {r.reason}" for r in results if not r.ok))
    if ok.sum() < 3:
        warnings.append("only 2 frames gave a recession: the rate has no confidence interval (needs >= 3)")
    rates = rate_map(np.array([r.time_s for r in results]), recession)
    # the frames' scatter about the line, and the cells' own rate errors that no frame shows (`cell_scatter`)
    common = cell_scatter(rates["rate"], rates["rate_se"], u, v, radius, ref.grid.spacing, model)
    fit = line_fit(t, stag)
    if common is not None:
        fit = with_common_part(fit, common.se, common.dof)
    sig = np.array([r.height.se for r in results])[ok]
    weighted = line_fit(t, stag, sig) if np.all(np.isfinite(sig) & (sig > 0)) and ok.sum() > 2 else None
    every_t = np.array([r.time_s for r in results])
    line_t = np.linspace(every_t.min(), every_t.max(), LINE_BAND_POINTS)  # the figure's band of the line
    band = line_band(fit, t, stag, line_t)
    return RecessionResult(results, ref.sample, ref.grid, ref_index, heights, height_se, recession, fit, weighted,
                           rates, config, warnings, fit_band=None if band is None else (line_t, band),
                           common_part=common)
