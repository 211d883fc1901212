"""What a camera's results folder shows beyond the solve itself, computed once when the job ends (the writers in
`dstereo.io` only write it): the reported +- with the views' effects, the projection-uncertainty map, the board the
written camera was solved on, the splined lens's valid spans."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

@dataclass(frozen=True)
class FinishedProjection:
    map: object  # uncertainty.projection map of the full-set solve
    range_source: str  # "given" or how the range was chosen
    fallback: bool  # pose-compensated asked for, but the solve kept no per-view blocks: intrinsics-only


@dataclass(frozen=True)
class LensCovariance:
    """The full-set solve's lens parameters and the covariance the tool reports for them (a solved board sag
    marginalised: its rows and columns dropped), as calibration_covariance.npz holds them for `dstereo diff`."""

    names: tuple[str, ...]
    values: np.ndarray  # (G,)
    cov: np.ndarray  # (G, G) with the views' effects where fitted
    jacobian: np.ndarray  # (G, G) sigma^2 S^-1 alone
    kind: str  # "per-view random effects" or "jacobian": which one `cov` is
    views: int  # the views the solve used
    joint: np.ndarray | None = None  # (G + 6V, G + 6V) with the V board poses (None: the solve kept no blocks)
    poses: np.ndarray | None = None  # (V, 6) rvec, tvec of T_cam_board


def lens_covariance(sol) -> LensCovariance:
    """`LensCovariance` of a one-camera `calib.solution.Solution` (a full-set solve)."""
    from dstereo.uncertainty.projection import solution_joint
    from dstereo.uncertainty.view_effects import reported_covariance, solution_effects

    lens = np.array([i for i, n in enumerate(sol.names) if not n.startswith("board_sag")], int)
    effects = solution_effects(sol)
    keep = np.ix_(lens, lens)
    joint = None if sol.normal is None else solution_joint(sol, effects)
    return LensCovariance(tuple(sol.names[i] for i in lens), np.asarray(sol.values, float)[lens],
                          np.asarray(reported_covariance(sol), float)[keep], np.asarray(sol.cov, float)[keep],
                          "per-view random effects" if effects is not None and effects.fitted else "jacobian",
                          int(len(sol.poses)), joint, None if joint is None else np.asarray(sol.poses, float))


@dataclass(frozen=True)
class FinishedCamera:
    std: np.ndarray  # the +- every file shows: with the views' effects (the Jacobian's when the views agree)
    view_scatter: object | None  # uncertainty.view_scatter of the full-set solve
    view_effects: object | None  # uncertainty.view_effects of the full-set solve
    projection: FinishedProjection
    board_sag: np.ndarray | None  # (2,) the sag the written camera was solved with (None: a flat board)
    solved_board: np.ndarray | None  # (n, 3) that board's points
    splined_spans: object | None  # models.splined.valid_spans of a splined lens
    valid_region: object | None = None  # calib.valid_region.ValidRegion: invertible and reached by the corners
    mrcal_conversion: object | None = None  # calib.mrcal_convert.Conversion (--mrcal-convert, a lens with no twin)
    covariance: LensCovariance | None = None  # the full-set solve's, for calibration_covariance.npz
    # (gh, gw) bool on the map's grid: within camera_diff.FIELD_STEPS grid steps of an observed corner (where the map is a claim;
    # beyond, the lens model is extrapolated and the map a lower bound)
    field: np.ndarray | None = None


def projection_of(cal, projection_range: float | None = None, method: str = "pose-compensated") -> FinishedProjection:
    """The full-set solve's projection-uncertainty map at `projection_range` (default: the mean board distance of
    the full-set solve; board unit) by `method`."""
    from dstereo.uncertainty.projection import METHODS, mean_board_distance, solution_map

    if method not in METHODS:
        raise ValueError(f"projection method {method!r}: one of {METHODS}")
    full, det = cal.full, cal.detection
    source = "given" if projection_range is not None else "mean board distance of the full-set solve"
    if projection_range is None:
        projection_range = mean_board_distance(full.poses, det.object_points)
    fallback = method == "pose-compensated" and full.normal is None
    pmap = solution_map(full, det.image_size, projection_range, "intrinsics-only" if fallback else method)
    return FinishedProjection(pmap, source, fallback)


def finish_camera(cal, projection_range: float | None = None, method: str = "pose-compensated") -> FinishedCamera:
    """The finished numbers of a `calib.calibrations.CameraCalibration` (module docstring); the map as
    `projection_of`."""
    from dstereo.calib.final_solution import written_camera_solution
    from dstereo.calib.problem import sagged_board
    from dstereo.uncertainty.view_effects import reported_std, solution_effects
    from dstereo.uncertainty.view_scatter import solution_view_scatter

    full, det = cal.full, cal.detection
    sag = written_camera_solution(cal).board_sag
    spans = None
    if full.camera().lens == "splined":
        from dstereo.models import splined

        K = cal.final_camera_matrix
        k4 = K[[0, 1, 0, 1], [0, 1, 2, 2]]
        spans = splined.valid_spans(k4, cal.observations, *splined.grid_of(tuple(full.camera().dist.free)))
    from dstereo.calib.valid_region import valid_region
    from dstereo.uncertainty.camera_diff import corner_field

    projection = projection_of(cal, projection_range, method)
    pmap = projection.map
    region = valid_region(pmap.u, pmap.v, pmap.mask, cal.observations) if pmap.mask is not None else None
    return FinishedCamera(
        std=np.asarray(reported_std(full)), view_scatter=solution_view_scatter(full),
        view_effects=solution_effects(full), projection=projection,
        board_sag=None if sag is None else np.asarray(sag),
        solved_board=None if sag is None else sagged_board(det.object_points, sag), splined_spans=spans,
        valid_region=region, mrcal_conversion=_conversion(cal, region, pmap), covariance=lens_covariance(full),
        field=corner_field(np.asarray(pmap.u), np.asarray(pmap.v), np.asarray(cal.observations, float)))


def _conversion(cal, region, pmap):
    """The nearest mrcal model of a lens mrcal has no twin for, when asked (`mrcal_convert`); else None."""
    from dstereo.calib.mrcal_convert import nearest_opencv8
    from dstereo.uncertainty.projection import model_key

    full = cal.full
    if not getattr(cal.config, "mrcal_convert", False) or full.camera().lens not in ("fisheye", "splined") or \
            region is None:
        return None
    K = cal.final_camera_matrix
    return nearest_opencv8(K[[0, 1, 0, 1], [0, 1, 2, 2]], cal.final_coefficients, model_key(full.names),
                           np.asarray(pmap.u), np.asarray(pmap.v), region.pixels, cal.observations)
