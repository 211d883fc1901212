"""A camera's results folder (the thesis's "Results" folder): `fill_camera_folder`. The one writer of every
calibration (`io.cameras_files.write_results`) fills the results folder itself so for one camera, and one such
folder per camera of a rig.

Layout of `fill_camera_folder(folder, cal)`:
    report.md            what was done and what came out, with links to everything below
    report.html          the same in one page a browser opens: figures embedded, summary at the top
    summary.json         machine-readable: full_set, subsets (steps, survivors), final, images, coverage, ...
    camera.yml/.json     the result for OpenCV (FileStorage) and for anything else
    subsets.csv          one row per subset: image indices, every parameter, rms, fate
    corners.npz          detected corners per usable image + object_points: re-run a solve on them
    config.toml          the configuration as run (files and flags merged)
    stats/step_K.txt     thesis section 5.2.1.3: mean, std, error % per parameter, reprojection error, count
    stats/parameter_P.txt  one parameter through the steps, as the thesis prints f_x
    plots/<param>.png    thesis Figure 5.9: histogram with its KDE, box plot of initial and final subsets (drawn
                         as soon as the steps end, `EarlyFigures`, while the survivors' solve runs)
    plots/coverage.png, per_image_rms.png, residuals.png
    plots/projection_uncertainty.png, projection_uncertainty.npz   std (px) of the projection of a point at a
                         given range (default the mean board distance, board unit), pose-compensated (fixed in
                         the boards' frame; --projection-method intrinsics-only for the camera frame); npz keys u, v,
                         std, cov, range, mask (False: model not invertible there, NaN), method
    calibration_covariance.npz   the lens parameters and their covariance (io/covariance_file.py), for dstereo diff
    cross_validation.npz, plots/cross_validation.png   with --cross-validate N: half-split differences vs predicted
    undistorted/*.jpg    original | undistorted side by side (thesis Figure 5.8)
The folder is filled under a temporary name in the same parent and renamed at the end: an error leaves no
partial folder, and an existing folder is replaced only with `force`.
"""

from __future__ import annotations

import csv
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from dstereo.calib.robust_steps import SURVIVES, UNUSABLE, FilterResult
from dstereo.config.calibration import ABSOLUTE_PARAMETERS, as_dict, to_toml
from dstereo.errors import DstereoError
from dstereo.io.json_files import json_default, write_json  # noqa: F401 - the writers' names, importable here
from dstereo.io.atomic_files import follow_umask

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the finished result this module writes
    from dstereo.calib.calibrations import CameraCalibration

UNITS = {"fx": "px", "fy": "px", "cx": "px", "cy": "px", "re": "px", "stereo_re": "px"}
N_UNDISTORTED = 3
LIST_SURVIVORS = 100_000  # summary.json lists the surviving subsets' numbers up to this many subsets


def check_output(out: str | Path, force: bool) -> Path:
    """Refuse an existing results folder unless `force`, or one that cannot be created; call before any long work."""
    from dstereo.io.output_location import check_creatable

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DstereoError(f"results: {out} exists and is not a folder; choose another `out`")
    if out.exists() and not force:
        raise DstereoError(f"results folder {out} already exists; choose another `out` or pass `force` to replace it")
    return check_creatable(out)


@contextmanager
def atomic_folder(out: str | Path, force: bool) -> Iterator[Path]:
    """Yield a temporary folder next to `out`; on success it replaces `out`, on error it is removed."""
    from dstereo.runtime import interrupts
    from dstereo.io import staging

    out = check_output(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging.clean_stale(out.parent, out.name)  # what a killed run (kill -9) of this folder left
    tmp = staging.make(out.parent, out.name, "tmp")
    try:
        follow_umask(tmp, folder=True)  # the results folder is this one renamed
        yield tmp
        # A signal whose exception was swallowed (raised inside a weakref callback or a __del__, which Python
        # reports and ignores) must still keep the results out: this is the last moment they can be.
        interrupts.check()
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
        interrupts.completed(out)
    except BaseException as exc:
        if isinstance(exc, interrupts.Interrupted):  # a figure worker still drawing would write into it again
            from dstereo.runtime import figure_pool

            figure_pool.kill()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        staging.done(tmp)


# --- generic tables (reused per camera and by the stereo results) -------------------------------------------


def stats_text(filtering: FilterResult, k: int, total: int, title: str = "CALIBRATION PARAMETERS") -> str:
    """The thesis's statistics file for the survivors of steps 1..k (k = 0: before optimisation)."""
    stats = filtering.stats(k)
    if k == 0:
        head = ["STEP 0 (before optimization)"]
    else:
        s = filtering.steps[k - 1]
        limits = ", ".join(f"{p} {e:g}" + (" px" if p in ABSOLUTE_PARAMETERS else " IQR")
                           for p, e in zip(s.parameters, s.max_error))
        head = [f"STEP {k} (max error: {limits})", s.message]
    lines = [*head, f"Subsets = {stats[filtering.columns[0]]['count']} (of {total} solved; "
                   f"{int(filtering.usable.sum())} converged)",
             "Error = standard deviation / |average| * 100 (%); standard deviation over subsets (numpy std)", ""]
    for name in filtering.columns:
        if name in ABSOLUTE_PARAMETERS:
            continue
        s = stats[name]
        lines += [f"[{title}] = [[{name} ]]", f"Average = {s['mean']!r}", f"Standard deviation = {s['std']!r}",
                  f"Error = {s['error_percent']!r}", ""]
    for name in filtering.columns:
        if name in ABSOLUTE_PARAMETERS:
            s = stats[name]
            lines += [f"[REPROJECTION ERROR] = [[{name} ]] (RMS per subset, px)", f"Average = {s['mean']!r}",
                      f"Minimum = {s['min']!r}", f"Maximum = {s['max']!r}", ""]
    return "\n".join(lines)


def history_text(filtering: FilterResult, name: str, title: str = "CALIBRATION PARAMETERS") -> str:
    """One parameter through the steps, laid out as the thesis prints f_x in section 5.2.1.3."""
    absolute = name in ABSOLUTE_PARAMETERS
    lines = [f"[REPROJECTION ERROR] = [[{name} ]] (RMS per subset, px)" if absolute else f"[{title}] = [[{name} ]]"]
    for k in range(len(filtering.steps) + 1):
        s = filtering.stats(k)[name]
        lines.append("STEP 0 (before optimization)" if k == 0 else f"STEP {k}")
        if absolute:
            lines += [f"Average = {s['mean']!r}", f"Minimum = {s['min']!r}", f"Maximum = {s['max']!r}"]
        else:
            lines += [f"Average = {s['mean']!r}", f"Standard deviation = {s['std']!r}",
                      f"Error = {s['error_percent']!r}"]
        lines.append(f"Subsets = {s['count']}")
    return "\n".join(lines) + "\n"


def write_stats_files(folder: Path, filtering: FilterResult, title: str = "CALIBRATION PARAMETERS") -> list[str]:
    """stats/step_0_initial.txt, stats/step_1.txt, ... (one per step) and stats/parameter_<name>.txt (one per
    column, through the steps); returns the file names written."""
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for k in range(len(filtering.steps) + 1):
        name = "step_0_initial.txt" if k == 0 else f"step_{k}.txt"
        (folder / name).write_text(stats_text(filtering, k, len(filtering.table), title))
        names.append(name)
    for column in filtering.columns:
        name = f"parameter_{column}.txt"
        (folder / name).write_text(history_text(filtering, column, title))
        names.append(name)
    return names


CSV_BLOCK = 65536  # rows formatted at a time: the CSV is written block by block, never held whole


def write_subsets_csv(path: Path, plan, filtering: FilterResult, status: np.ndarray | None = None) -> None:
    """One row per subset: image indices (space separated), parameters, reprojection error(s), fate.
    `plan` is the SubsetPlan (or an (C, m) index array); rows are read and written a block at a time."""
    params = [c for c in filtering.columns if c not in ABSOLUTE_PARAMETERS]
    errors = [c for c in filtering.columns if c in ABSOLUTE_PARAMETERS]
    order = [filtering.columns.index(c) for c in params + errors]
    header = ["subset", "images", *params, *("rms" if c == "re" else c for c in errors), "converged", "survives",
              "removed_at_step"]
    rows_of = plan.rows if hasattr(plan, "rows") else (lambda a, b: np.asarray(plan)[a:b])
    with open(path, "w", newline="") as fh:
        csv.writer(fh).writerow(header + (["solver_status"] if status is not None else []))
        # Lines built by hand, as csv.writer writes them (no cell needs quoting; "\r\n"): 154 -> 99 s per 1e7 rows.
        for a in range(0, len(filtering), CSV_BLOCK):
            table, index = filtering.table.rows(a, a + CSV_BLOCK)[:, order], rows_of(a, a + CSV_BLOCK)
            fates = filtering.removed_at[a: a + len(table)].tolist()
            codes = [""] * len(table) if status is None else [f",{c}" for c in status[a: a + len(table)].tolist()]
            images = [" ".join(map(str, r)) for r in index.tolist()]
            fh.write("".join(
                f"{a + i},{images[i]},{','.join(map(repr, row))},{int(fate != UNUSABLE)},{int(fate == SURVIVES)},"
                f"{fate if fate > 0 else ''}{codes[i]}\r\n"
                for i, (row, fate) in enumerate(zip(table.tolist(), fates))))


def steps_summary(filtering: FilterResult) -> list[dict]:
    return [{"step": s.number, "parameters": list(s.parameters), "max_error": list(s.max_error),
             "kind": ["absolute (px)" if p in ABSOLUTE_PARAMETERS else "IQR multiple" for p in s.parameters],
             "before": s.before, "survivors": s.after, "removed": s.removed, "passes": s.passes,
             "bounds": {p: list(b) for p, b in s.bounds.items()}, "stopped_by_minimum": s.stopped_by_minimum,
             "message": s.message} for s in filtering.steps]


# --- one camera ---------------------------------------------------------------------------------------------


def distortion_vector(coeffs8: np.ndarray, free: Sequence[str]) -> np.ndarray:
    """OpenCV's 5-vector (k1 k2 p1 p2 k3), or all 8 when a rational coefficient is free; for the fisheye model
    cv2.fisheye's D (k1 k2 k3 k4)."""
    from dstereo.models.distortion import lens_model

    if lens_model(tuple(free)) == "fisheye":
        return np.asarray(coeffs8, float)[:4]
    if lens_model(tuple(free)) == "splined":  # no OpenCV vector: its knots are in the file's splined section
        return np.zeros(0)
    return np.asarray(coeffs8, float)[: 8 if set(free) & {"k4", "k5", "k6"} else 5]


def distortion_names(free: Sequence[str], n: int) -> list[str]:
    """Names of the written distortion vector's entries (fisheye: cv2.fisheye's k1..k4)."""
    from dstereo.models.distortion import lens_model

    if lens_model(tuple(free)) == "fisheye":
        return ["k1", "k2", "k3", "k4"]
    if lens_model(tuple(free)) == "splined":
        return []
    return ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][:n]


def write_camera_files(folder: Path, K: np.ndarray, D: np.ndarray, image_size: tuple[int, int], extra: dict,
                       model: str = "pinhole", splined=None, comment: str | None = None, *, unit: str = "mm") -> None:
    """camera.yml (cv2.FileStorage) and camera.json with the same numbers. A fisheye camera adds
    `distortion_model: fisheye` (D is then cv2.fisheye's 4-vector); without the field the camera is OpenCV's
    pinhole + distortion model, as before. A splined camera: `splined` = (knots, free, valid spans), written as
    the file's splined section (`camera_file.write_splined_section`)."""
    import cv2

    fs = cv2.FileStorage(str(folder / "camera.yml"), cv2.FILE_STORAGE_WRITE)
    try:
        if comment is not None:
            fs.writeComment(comment)
        fs.write("image_width", int(image_size[0]))
        fs.write("image_height", int(image_size[1]))
        fs.write("unit", unit)  # the board's length unit: K and D are in px, the board poses and sag in this
        if model != "pinhole":
            fs.write("distortion_model", model)
        fs.write("camera_matrix", np.asarray(K, np.float64))
        if splined is not None:
            from dstereo.io.camera_file import write_splined_section

            write_splined_section(fs, *splined)
        else:
            fs.write("distortion_coefficients", np.asarray(D, np.float64).reshape(1, -1))
    finally:
        fs.release()
    flag = {} if model == "pinhole" else {"distortion_model": model}
    write_json(folder / "camera.json", {"image_width": int(image_size[0]), "image_height": int(image_size[1]),
                                        "unit": unit, **flag, "camera_matrix": np.asarray(K).tolist(),
                                        "distortion_coefficients": np.asarray(D).ravel().tolist(), **extra})


def summary_dict(cal: CameraCalibration) -> dict:
    """summary.json of a `CameraCalibration`."""
    full, det, done = cal.full, cal.detection, finished(cal)
    names = list(full.names)
    scatter, std, effects = done.view_scatter, done.std, done.view_effects
    summary = {
        "config": as_dict(cal.config),
        "image_size": list(det.image_size),
        "pattern": {"columns": det.board.cols, "rows": det.board.rows, "square": det.board.square,
                    "unit": cal.config.unit},
        "model": list(full.camera().dist.free),
        "images": {"folder": str(cal.folder), "used": list(cal.used), "rejected": dict(det.rejected),
                   "considered": list(det.names)},
        "full_set": {**dict(zip(names, map(float, full.values))), "rms": float(full.rms),
                     "std": dict(zip(names, map(float, std))),
                     "std_jacobian": dict(zip(names, map(float, full.std))),
                     "view_scatter": None if scatter is None else scatter.summary(names),
                     "view_effects": None if effects is None else effects.summary(names),
                     "per_image_rms": dict(zip(cal.used, map(float, full.per_view_rms[:, 0]))),
                     "iterations": int(full.iterations), "status": full.status_text, "converged": bool(full.converged),
                     "conditioning": {"identifiable": bool(full.conditioning.identifiable),
                                      "condition_number": float(full.conditioning.condition_number),
                                      "weak_parameters": list(full.conditioning.weak_parameters),
                                      "wild_parameters": [{"parameter": n, "value": v, "std": sd, "why": why}
                                                          for n, v, sd, why in full.conditioning.wild],
                                      "message": full.conditioning.message()}},
        "subsets": None,
        "final": dict(cal.final),
        "final_source": "full-set solve (no subsets: set images per set to run the subset analysis)",
        "comparison": [{"parameter": n, "full_set": float(v), "full_set_std": float(s),
                        "subset_mean": cal.subset_mean[n] if cal.subset_mean is not None else None,
                        "subset_spread": cal.spread[n] if cal.filtering is not None else None}
                       for n, v, s in zip(names, full.values, std)],
        "coverage": {"percent": cal.coverage.percent, "image_corner_percent": cal.coverage.corner_percent,
                     "points": cal.coverage.points},
        "model_advice": cal.model_advice,
        "outliers": None if getattr(cal, "outliers", None) is None else cal.outliers.as_dict(),
        "residual_pattern": None if getattr(cal, "residual_pattern", None) is None else cal.residual_pattern.as_dict(),
        "residual_pattern_all_corners": None if getattr(cal, "residual_pattern_all", None) is None
        else cal.residual_pattern_all.as_dict(),
        "model_choice": cal.model_choice.as_dict() if cal.model_choice is not None else None,  # --model auto
        "warnings": list(cal.warnings),
        "timings": dict(cal.timings),
    }
    if cal.filtering is not None:
        f, plan = cal.filtering, cal.plan
        survivors = f.survivors
        summary["subsets"] = {
            "per_set": int(plan.per_set), "total_combinations": int(plan.total), "solved": int(len(plan)),
            "exhaustive": bool(plan.exhaustive), "sampling": plan.describe(), "seed": int(plan.seed),
            "initial_count": int(f.usable.sum()), "final_count": int(survivors.sum()),
            "unconverged": {"count": len(cal.unconverged), "subsets": cal.unconverged[:LIST_SURVIVORS]},
            "reprojection_error": "re = each subset's RMS reprojection error, sqrt(SSE / points) px, "
                                  "the value cv2.calibrateCamera returns",
            "steps": steps_summary(f),
            "initial": f.stats(0), "final": f.stats(len(f.steps)),
            "survivor_subsets": [int(i) for i in np.flatnonzero(survivors)] if len(survivors) <= LIST_SURVIVORS
            else f"{int(survivors.sum())} subsets: see subsets.csv (survives = 1)",
        }
        summary["final_source"] = f"mean over the {int(survivors.sum())} surviving subsets (the thesis's answer)"
        summary["final_spread"] = dict(cal.spread)
        summary["final"]["re"] = f.stats(len(f.steps))["re"]["mean"]
        if cal.final_solution is not None:  # calib/final_solution.py: what camera.yml holds, beside the mean
            summary["final_source"] = cal.final_solution.source(cal.used)
            summary["final_check"] = cal.final_solution.as_dict(cal.used)
            summary["subset_mean"] = dict(cal.subset_mean) | {"re": f.stats(len(f.steps))["re"]["mean"]}
            if cal.final_solution.choice == "survivors":
                summary["final"]["re"] = float(cal.final_solution.solution.rms)
    return summary


def write_projection_uncertainty(folder: Path, cal: CameraCalibration, figures=None) -> dict:
    """plots/projection_uncertainty.png and projection_uncertainty.npz (u, v, std, cov, range, mask, method, field:
    the grid pixels within 1.5 grid steps of an observed corner, where the map is a claim; beyond, the lens model is
    extrapolated and the map a lower bound) of the full-set solve's map (`calib.finished`); returns the summary
    entry. `figures`: a `figure_pool.Figures`
    that draws the PNG (else drawn here)."""
    from types import SimpleNamespace

    from dstereo.runtime.figure_pool import Figures

    from dstereo.io.sigma_maps import projection_uncertainty_png

    done = finished(cal).projection
    pmap = done.map
    field = getattr(finished(cal), "field", None)
    field = {} if field is None else {"field": field}
    np.savez(folder / "projection_uncertainty.npz", u=pmap.u, v=pmap.v, std=pmap.std, cov=pmap.cov,
             range=pmap.range_, mask=pmap.mask, method=pmap.method, **field)
    drawing = figures if figures is not None else Figures()
    # The map's arrays only, in a namespace: the worker then needs no JAX-importing class to unpickle it.
    plain = SimpleNamespace(u=np.asarray(pmap.u), v=np.asarray(pmap.v), std=np.asarray(pmap.std), range_=pmap.range_)
    drawing.draw(projection_uncertainty_png, folder / "plots" / "projection_uncertainty.png", plain,
                 cal.detection.image_size, f"projection uncertainty ({pmap.method}, full-set solve)", cal.config.unit)
    if figures is None:
        drawing.wait()
    entry = {**pmap.summary(), "range_source": done.range_source, "unit": cal.config.unit,
             "files": ["plots/projection_uncertainty.png", "projection_uncertainty.npz"]}
    if done.fallback:
        entry["note"] += " (the solve kept no per-view blocks, so the pose-compensated map could not be made)"
    if pmap.view_scatter is not None and pmap.view_scatter.alarm:
        entry["view_scatter_warning"] = "projection uncertainty: " + pmap.view_scatter.message()
    if pmap.masked:
        entry["warning"] = (f"projection uncertainty: {pmap.masked} of {pmap.mask.size} grid pixels masked (grey in "
                            "plots/projection_uncertainty.png): the distortion model cannot be inverted there (not "
                            "monotonic beyond the field the corners cover); do not use the camera there, or add views "
                            "that reach those parts of the image")
    return entry


def finished(cal: CameraCalibration):
    """The calibration's finished numbers (`calib.finished.FinishedCamera`), which the job computes before any
    writer runs: this module writes them and computes nothing."""
    done = getattr(cal, "finished", None)
    if done is None:
        raise ValueError("this calibration was not finished: its job calls dstereo.calib.finished.finish_camera "
                         "before writing it")
    return done


def draw_parameter_figures(figures, plot_dir: Path, filtering, full) -> tuple[str, ...]:
    """Hand each subset column's figure (`plots.parameter_figure_data`: initial and final subsets, the full set's
    value as reference) to `figures`, as plot_dir/<column>.png; returns the columns drawn."""
    from dstereo.io import plots

    names = tuple(_drawn_columns(filtering))
    for name in names:
        ref = float(full.rms) if name == "re" else float(full.values[list(full.names).index(name)])
        initial, final = filtering.values(name, 0), filtering.values(name, len(filtering.steps))
        data = plots.parameter_figure_data(name, initial, final, UNITS.get(name, ""), ref)
        figures.draw(plots.draw_parameter_figure, data, plot_dir / f"{name}.png")
    return names


class EarlyFigures:
    """The parameter figures of a camera's results, drawn as soon as the subsets' steps end (`parameters`, given to
    `pipeline.calibrate_camera` as `after_steps`): the figure workers then draw them while this process runs the
    survivors' solve and writes the rest, instead of after it (measured on rig640, C = 4845: ten figures, ~0.8 s
    of drawing on two cores that were otherwise waiting at the end of the run). They go to a staging folder next to
    the results (the results folder is made only once everything is computed) and `fill_camera_folder` moves them
    in; `discard` removes whatever a failed command left."""

    def __init__(self, out: str | Path):
        self.out = Path(out)
        self.staging: Path | None = None
        self.names: tuple[str, ...] = ()
        self.figures = None

    def parameters(self, filtering, full) -> None:
        from dstereo.runtime.figure_pool import Figures

        from dstereo.io import staging

        parent = self.out.parent if self.out.parent.is_dir() else None  # the system's temporary folder otherwise
        self.staging = staging.make(parent, self.out.name, "figures")
        self.figures = Figures()
        self.names = draw_parameter_figures(self.figures, self.staging, filtering, full)

    def ready_for(self, filtering) -> bool:
        """Whether these are the figures of `filtering`'s columns (else the folder draws its own)."""
        return self.staging is not None and self.names == tuple(_drawn_columns(filtering))

    def take(self, plot_dir: Path) -> None:
        """Wait for the figures and move them into `plot_dir`."""
        self.figures.wait()
        for name in self.names:
            shutil.move(self.staging / f"{name}.png", plot_dir / f"{name}.png")

    def discard(self) -> None:
        import sys

        from dstereo.runtime import interrupts
        from dstereo.io import staging

        if self.staging is None:
            return
        if isinstance(sys.exc_info()[1], interrupts.Interrupted):
            from dstereo.runtime import figure_pool

            figure_pool.kill()  # a signal: end the drawing now rather than wait for up to ten figures
        else:
            try:
                self.figures.wait()  # a worker still drawing into the folder would recreate files in it
            except Exception:  # noqa: BLE001 - the command is failing or done; its own error is what counts
                pass
        shutil.rmtree(self.staging, ignore_errors=True)
        staging.done(self.staging)
        self.staging = None


def _drawn_columns(filtering) -> list[str]:
    """The subset columns that get a figure: not the board's sag, which the subsets hold at the full set's value
    (a figure of one value says nothing)."""
    from dstereo.calib.problem import WARP_NAMES

    return [n for n in filtering.columns if n not in WARP_NAMES]


def _solved_board(cal: CameraCalibration):
    """({"board_sag": ...} for camera.json or {}, the board the written camera was solved with or None, the
    camera.yml comment): a camera solved with the board's sag fits its corners on THAT board; refitted on the
    flat nominal board it reads 0.1-5 % worse than a flat solve (measured on the real sets), which says nothing
    about the camera."""
    done = finished(cal)
    sag, board = done.board_sag, done.solved_board
    if sag is None:
        return {}, None, None
    unit = cal.config.unit
    text = (f"solved with the board's sag x {sag[0]:.6g}, y {sag[1]:.6g} {unit} (mrcal's calobject_warp): refit poses on "
            "corners.npz object_points_solved, not the flat object_points")
    return {"board_sag": {"x": float(sag[0]), "y": float(sag[1]), "unit": unit,
                          "object_points": "corners.npz object_points_solved", "note": text}}, board, text


def fill_camera_folder(folder: Path, cal: CameraCalibration, early: EarlyFigures | None = None) -> dict:
    """Everything of the results folder into an existing (temporary) folder; returns the summary. `early`:
    parameter figures drawn already (`EarlyFigures`)."""
    from dstereo.io import plots
    from dstereo.runtime.figure_pool import Figures

    full, det = cal.full, cal.detection
    camera = full.camera()  # the full-set solve's
    summary = summary_dict(cal)
    figures = Figures()  # drawn in the figure workers (when started) while this process writes the rest
    K, D = cal.final_camera_matrix, distortion_vector(cal.final_coefficients, camera.dist.free)
    names = distortion_names(camera.dist.free, len(D))
    section = None
    if camera.lens == "splined":
        section = (cal.final_coefficients, camera.dist.free, finished(cal).splined_spans)
    sag, solved_board, comment = _solved_board(cal)
    write_camera_files(folder, K, D, det.image_size, model=camera.lens, splined=section, comment=comment,
                       unit=cal.config.unit, extra={
        "distortion_names": names, "source": summary["final_source"],
        "full_set": {"camera_matrix": camera.matrix().tolist(),
                     "distortion_coefficients": distortion_vector(camera.coeffs(), camera.dist.free).tolist(),
                     "rms": float(full.rms), "std": summary["full_set"]["std"]}, **sag})
    summary["cameramodel"] = _write_mrcal(folder, cal, K)
    converted = _write_mrcal_conversion(folder, cal)
    if converted is not None:
        summary["cameramodel_converted"] = converted
    np.savez(folder / "corners.npz", object_points=det.object_points,
             **({} if solved_board is None else {"object_points_solved": solved_board}),
             **{name: det.corners[name] for name in cal.used})
    (folder / "config.toml").write_text(to_toml(cal.config, comments=False))
    plot_dir = folder / "plots"
    plot_dir.mkdir()
    pts = cal.observations.reshape(-1, 2)
    from dstereo.calib.coverage import CORNER_MIN_PERCENT

    # The full-set figures first: the workers draw them while the parameter figures' data are reduced here.
    figures.draw(plots.coverage_heatmap, pts, det.image_size, cal.coverage.percent, plot_dir / "coverage.png",
                 cal.coverage.corner_percent, CORNER_MIN_PERCENT)
    figures.draw(plots.residual_vectors, np.asarray(cal.observations), np.asarray(full.residuals[:, 0]), det.image_size,
                 plot_dir / "residuals.png")
    figures.draw(plots.per_image_rms, list(cal.used), np.asarray(full.per_view_rms[:, 0]),
                 plot_dir / "per_image_rms.png")
    # the map next (~10 ms here): its figure, the slowest to draw, is then not the last one the workers start
    projection = write_projection_uncertainty(folder, cal, figures)
    if getattr(finished(cal), "covariance", None) is not None:
        from dstereo.io.covariance_file import write_calibration_covariance

        pmap = finished(cal).projection.map
        summary["calibration_covariance"] = write_calibration_covariance(
            folder, finished(cal).covariance, camera.lens, pmap.range_, (len(pmap.u), len(pmap.v)),
            det.image_size, field=getattr(finished(cal), "field", None))
    taken = cal.filtering is not None and early is not None and early.ready_for(cal.filtering)
    if cal.filtering is not None:
        f = cal.filtering
        if not taken:
            draw_parameter_figures(figures, plot_dir, f, full)
        summary["subsets"]["stats_files"] = write_stats_files(folder / "stats", f)
        if full.board_sag is not None:
            summary["subsets"]["held"] = {"board_sag": "held at the full set's value in every subset (the board is "
                                                        "one object in all views; calib/mono.solve_subsets)"}
        write_subsets_csv(folder / "subsets.csv", cal.plan, f, f.table.status)
    summary["undistorted"] = write_undistorted(folder / "undistorted", cal, K, cal.final_coefficients)
    summary["projection_uncertainty"] = projection
    for entry in (summary["projection_uncertainty"],):
        for key in ("warning", "view_scatter_warning"):
            if entry.get(key):
                summary["warnings"].append(entry[key])
                cal.warnings.append(entry[key])  # printed after writing, with the others
    if getattr(cal, "cross_validation", None) is not None:
        from dstereo.io.cross_validation_files import write_cross_validation

        summary["cross_validation"] = write_cross_validation(folder, cal.cross_validation, cal.config.unit,
                                                             list(cal.used), write_camera_files)
    figures.wait()
    if taken:
        early.take(plot_dir)
    summary["files"] = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) + \
        ["summary.json", "report.md", "report.html"]
    write_json(folder / "summary.json", summary)
    (folder / "report.md").write_text(report_markdown(cal, summary))
    from dstereo.io.report_headlines import camera_headline
    from dstereo.io.report_html import write_report_html

    write_report_html(folder, camera_headline(summary))  # every figure is in place: the workers were waited for
    return summary


def _write_mrcal(folder: Path, cal: CameraCalibration, K: np.ndarray) -> str:
    """camera.cameramodel (mrcal's format, io/cameramodel.py) of what camera.yml holds; what was done, or why not."""
    from dstereo.io.cameramodel import write_cameramodel

    solve, why = _board_solve(cal)
    return write_cameramodel(folder / "camera.cameramodel", cal.full.camera().dist.free,
                             K[[0, 1, 0, 1], [0, 1, 2, 2]], cal.final_coefficients, cal.detection.image_size,
                             note="written by dstereo calibrate",
                             solve=solve, no_solve_why=why, region=_region(cal))


def _write_mrcal_conversion(folder: Path, cal: CameraCalibration) -> str | None:
    """camera.mrcal-opencv8.cameramodel: the nearest mrcal model of a lens with no twin (--mrcal-convert); what was
    done, or None when not asked."""
    from dstereo.io.cameramodel import cameramodel_text, NO_MODEL_CONVERSION

    conv = getattr(finished(cal), "mrcal_conversion", None)
    if not getattr(cal.config, "mrcal_convert", False) or cal.full.camera().lens not in ("fisheye", "splined"):
        return None
    if conv is None:
        return NO_MODEL_CONVERSION
    (folder / "camera.mrcal-opencv8.cameramodel").write_text(cameramodel_text(
        "LENSMODEL_OPENCV8", conv.intrinsics, conv.coeffs8, cal.detection.image_size,
        note=f"written by dstereo calibrate --mrcal-convert\n{conv.text()}"))
    return f"camera.mrcal-opencv8.cameramodel: {conv.text()}"


def _region(cal: CameraCalibration):
    region = getattr(finished(cal), "valid_region", None)
    return None if region is None else region.polygon


def _board_solve(cal: CameraCalibration):
    """(the solve camera.yml holds, as io.cameramodel.BoardSolve, or None and why): the full set's, or the
    survivors' on their views; none for the thesis's subset mean, which no one solve produced."""
    from dstereo.io.cameramodel import BoardSolve

    fs = getattr(cal, "final_solution", None)
    if fs is not None and fs.choice == "mean":
        return None, "no optimization inputs: the file holds the mean over subsets (--final mean), not one solve"
    sol = cal.full if fs is None else fs.solution
    views = np.ones(len(cal.observations), bool) if fs is None else np.asarray(fs.views, bool)
    if sol.poses.shape[0] != int(views.sum()):
        return None, "no optimization inputs: the solve's views could not be matched to the corners"
    board = cal.detection.board  # one square side: mrcal's calibration_object_spacing
    camera = sol.camera()
    return BoardSolve.one_camera(camera.dist.free, sol.values[:4], camera.coeffs(), camera.image_size, sol.poses,
                                 np.asarray(cal.observations)[views], sol.camera_inliers(), (board.cols, board.rows),
                                 board.square, sol.board_sag), ""


def write_undistorted(folder: Path, cal: CameraCalibration, K: np.ndarray, coeffs8: np.ndarray) -> list[str]:
    """Original | undistorted side by side for the images whose corners reach furthest from the centre."""
    import cv2

    folder.mkdir()
    if cal.full.camera().lens == "splined":  # OpenCV cannot undistort this lens
        return []
    w, h = cal.detection.image_size
    reach = np.max(np.linalg.norm(cal.observations - np.array([w / 2, h / 2]), axis=2), axis=1)
    by_name = {p.name: p for p in cal.files}
    written = []
    for i in np.argsort(-reach)[:N_UNDISTORTED]:
        name = cal.used[int(i)]
        image = cv2.imread(str(by_name[name]), cv2.IMREAD_COLOR)
        if image is None:
            continue
        if cal.full.camera().lens == "fisheye":  # same K for the view: the image circle's rim falls outside it
            fixed = cv2.fisheye.undistortImage(image, K, np.asarray(coeffs8[:4], float), Knew=K)
        else:
            fixed = cv2.undistort(image, K, coeffs8)
        gap = np.full((image.shape[0], 8, 3), 255, np.uint8)
        target = f"{Path(name).stem}_undistorted.jpg"
        # JPEG at quality 95: a picture to judge straight lines by, encoded in ~3 ms where PNG took 20-37 ms an
        # image (measured at 1288 x 512), a third of a served plain calibration's own time for three of them
        cv2.imwrite(str(folder / target), np.hstack([image, gap, fixed]), [cv2.IMWRITE_JPEG_QUALITY, 95])
        written.append(f"undistorted/{target}")
    return written


def _fmt(value: float) -> str:
    return f"{value:.6g}" if value == value else "-"


REPORT_OUTLIERS = 30  # rejected corners listed in report.md (all of them in summary.json)


def outlier_lines(report) -> list[str]:
    """report.md's outlier section: the summary and the worst rejected corners (calib/outliers.py)."""
    if report is None:
        return []
    lines = ["## Outlier rejection", "", report.summary() + ".", ""]
    if report.corners:
        worst = sorted(report.corners, key=lambda c: -c[3])[:REPORT_OUTLIERS]
        lines += ["| image | corner | residual (px) | residual / sigma |", "|---|---|---|---|"]
        lines += [f"| {i} | {c} | {r:.3f} | {z:.1f} |" for i, c, r, z in worst]
        if len(report.corners) > REPORT_OUTLIERS:
            lines.append(f"| ... {len(report.corners) - REPORT_OUTLIERS} more in summary.json | | | |")
        lines.append("")
    return lines


def _model_choice_lines(choice) -> list[str]:
    """report.md's `--model auto` section: the candidates' table and the rule (calib/model_choice.py)."""
    kind = "leave one view out" if choice.heldout_views == choice.folds else f"{choice.folds} folds"
    return ["## Model choice (--model auto)", "",
            f"Held-out error: {kind} ({choice.heldout_views} views held out); each held-out view's board pose "
            "refitted for the fold's fixed camera, RMS over its corners. Rule: " + choice.rule + ".", "",
            *choice.table_markdown(), "",
            f"Chosen: **{choice.chosen}** ({', '.join(choice.chosen_candidate.free)}); the rest of this report is "
            "its calibration.", ""]


def _fmt_px(value) -> str:
    return "-" if value is None else f"{value:.3g}"


def report_markdown(cal: CameraCalibration, summary: dict) -> str:
    """report.md: the run in a page, tying the files of the folder together."""
    from dstereo.models.distortion import model_label

    full, cfg, board = cal.full, cal.config, cal.detection.board  # the board summary.json reports, too
    camera = full.camera()
    lines = [f"# Camera calibration: {cal.folder}", "",
             f"- board: {board.cols} x {board.rows} inner corners, square {board.square:g} {cfg.unit}",
             f"- images: {len(cal.used)} usable of {len(cal.detection.names)} "
             f"({len(cal.detection.rejected)} rejected), "
             f"{cal.detection.image_size[0]} x {cal.detection.image_size[1]} px",
             f"- distortion model: {camera.lens}, "
             + (f"{model_label(camera.dist.free)} (knots in camera.yml's splined section)" if camera.lens == "splined"
                else f"{', '.join(camera.dist.free) or 'none'}"),
             f"- full-set solve: RMS {full.rms:.4f} px, {full.status_text}; {full.conditioning.message()}", ""]
    if cal.model_advice:
        lines += [f"**Model:** {cal.model_advice}", ""]
    lines += outlier_lines(getattr(cal, "outliers", None))
    pattern = getattr(cal, "residual_pattern", None)
    if pattern is not None:
        lines += [f"- residual pattern (8 x 6 cells): systematic {pattern.systematic_px:.3f} px of RMS "
                  f"{pattern.rms_px:.3f} px, chi^2 {pattern.statistic:.0f} / {pattern.dof} dof, "
                  f"p = {pattern.p_value:.2g}"
                  f" ({'significant: the model is too simple' if pattern.significant else 'no significant pattern'})",
                  ""]
    if cal.model_choice is not None:
        lines += _model_choice_lines(cal.model_choice)
    sub = summary["subsets"]
    if sub is not None:
        lines += ["## Subsets and optimisation steps", "",
                  f"{sub['sampling']} of m = {sub['per_set']} images; {sub['initial_count']} converged "
                  f"({sub['unconverged']['count']} did not and are left out). Reprojection error `re` is each "
                  "subset's RMS (the value cv2.calibrateCamera returns).", "",
                  "| step | parameters | max error | before | survivors | passes | note |",
                  "|---|---|---|---|---|---|---|"]
        for s in sub["steps"]:
            note = "stopped by the minimum number of subsets" if s["stopped_by_minimum"] else ""
            lines.append(f"| {s['step']} | {', '.join(s['parameters'])} | {', '.join(f'{e:g}' for e in s['max_error'])}"
                         f" | {s['before']} | {s['survivors']} | {s['passes']} | {note} |")
        files = sub.get("stats_files", [])
        lines += ["", "Statistics per step: " + ", ".join(f"[{n}](stats/{n})" for n in files if n.startswith("step")),
                  "", "Per parameter through the steps: "
                  + ", ".join(f"[{n[10:-4]}](stats/{n})" for n in files if n.startswith("parameter")),
                  "", "Per-subset values and fates: [subsets.csv](subsets.csv)", ""]
    ve = summary["full_set"].get("view_effects")
    ratios = sorted((ve or {}).get("std_ratio", {}).values())
    scaled = (f" with the views' effects ({ratios[0]:.2f}-{ratios[-1]:.2f}x the Jacobian's: the views scatter the "
              "solve more than independent corner noise says; `std_jacobian` in summary.json has the Jacobian's)"
              if ratios and ratios[-1] > 1.0 + 1e-9 else "")
    lines += ["## Result", "", summary["final_source"] + ". Beside it: the full-set solve with its "
              f"standard deviations{scaled or ' (the Jacobian ones)'}, and the thesis's mean and spread (standard "
              "deviation) across the surviving subsets.", "",
              "| parameter | final | full set | +- std | subset mean | subset spread |",
              "|---|---|---|---|---|---|"]
    for row in summary["comparison"]:
        spread, mean = row["subset_spread"], row["subset_mean"]
        lines.append(f"| {row['parameter']} | {_fmt(summary['final'][row['parameter']])} | {_fmt(row['full_set'])} | "
                     f"{_fmt(row['full_set_std'])} | {_fmt(mean) if mean is not None else '-'} | "
                     f"{_fmt(spread) if spread is not None else '-'} |")
    check = summary.get("final_check", {}).get("mean_check")
    if check is not None:
        verdict = ("**fits worse than the solve**" if check["mean_worse"] else
                   f"fits as well as the solve (within {100 * check['margin']:g} %)")
        lines += ["", f"Fit on the {check['views']} surviving views' corners, each board pose refitted: the solve "
                  f"RMS {check['rms_solution_px']:.4f} px, the thesis's subset mean RMS {check['rms_mean_px']:.4f} px "
                  f"({check['ratio']:.3f}x): the mean {verdict}."]
    lines += ["", "Camera for OpenCV: [camera.yml](camera.yml) (also [camera.json](camera.json)); corners: "
              "[corners.npz](corners.npz); the configuration as run: [config.toml](config.toml).",
              f"For mrcal's tools: {summary.get('cameramodel', '-')}."]
    if "cameramodel_converted" in summary:
        lines += [f"Converted for mrcal (--mrcal-convert): {summary['cameramodel_converted']}."]
    elif cal.full.camera().lens in ("fisheye", "splined"):
        lines += ["`--mrcal-convert` writes the nearest mrcal model (OpenCV8) beside it, with its fit error."]
    lines += [""]
    cov = cal.coverage
    lines += ["## Distortion coverage (thesis section 5.2.1.2)", "", "| image area | % of corners |", "|---|---|"]
    lines += [f"| {name.replace('_', ' ')} | {cov.percent[name]:.1f} |" for name in cov.percent]
    lines += ["", "![coverage](plots/coverage.png)", ""]
    lines += [f"- warning: {w}" for w in cov.warnings] + ([""] if cov.warnings else [])
    pu = summary.get("projection_uncertainty")
    if pu is not None:
        lines += ["## Projection uncertainty", "",
                  f"Std of the projected pixel (worst direction) of a point {pu['range']:.4g} {pu['unit']} along each "
                  f"pixel's ray ({pu['range_source']}), {pu['method']}: median "
                  f"{_fmt_px(pu['std_px']['median'])} px, max {_fmt_px(pu['std_px']['max'])} px; "
                  f"{pu['masked_pixels']} grid pixels masked (model not invertible there). {pu['note']}.", "",
                  "![projection uncertainty](plots/projection_uncertainty.png)", ""]
    xv = summary.get("cross_validation")
    if xv is not None:
        lines += ["## Cross-validation", "", xv["verdict"] + ".", "", "![cross-validation](plots/cross_validation.png)",
                  "", "Each split's halves are camera folders, cross_validation/split_<k>/a and b: `dstereo diff "
                  "cross_validation/split_1/a cross_validation/split_1/b` repeats split 1's comparison from them.", ""]
    lines += ["## Figures", "", "![per-image RMS](plots/per_image_rms.png)", "",
              "![residuals](plots/residuals.png)", ""]
    if cal.filtering is not None:
        lines += [f"![{n}](plots/{n}.png)" for n in _drawn_columns(cal.filtering)] + [""]
    lines += ["Undistorted images (straight lines should look straight): "
              + ", ".join(f"[{Path(p).name}]({p})" for p in summary["undistorted"]), ""]
    others = [w for w in cal.warnings if w not in cov.warnings and w != cal.model_advice]
    if others:
        lines += ["## Warnings", ""] + [f"- {w}" for w in others] + [""]
    return "\n".join(lines)
