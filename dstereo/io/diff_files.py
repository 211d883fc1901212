"""`dstereo diff`'s files: the two cameras it reads (with their uncertainty files) and the folder it writes.

A camera is given as
- a camera's results folder (`dstereo calibrate --images`, or a rig's `left/`, `right/`, `<camera>/` subfolder, or
  a cross-validation half `cross_validation/split_<k>/a`): its camera.yml, with calibration_covariance.npz and
  projection_uncertainty.npz beside it when there;
- a camera file (camera.yml, or any OpenCV camera file `io.camera_file` reads): the same files beside it count;
- a rig's camera, `stereo.yml:left` or `stereo.yml:right` (a rig folder `DIR:left` finds DIR/stereo.yml): its
  intrinsics, its block of the pair's covariance (`cov`, `cov_names`), and rig_<camera>_projection_uncertainty.npz
  beside it when there.

Written (`write_diff`, under a temporary name renamed at the end): diff.json (the summary), diff.npz (the grid, the
difference, the prediction, Mahalanobis distances, weights), diff.png (heat maps), report.md and report.html.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError
from dstereo.io.covariance_file import NAME as COVARIANCE_NAME
from dstereo.io.covariance_file import read_calibration_covariance

MAP_NAME = "projection_uncertainty.npz"
SIDES = ("left", "right")


@dataclass
class DiffInput:
    """One camera as read for a difference: K (3, 3), coeffs (8,) in its model's slots (a splined lens: its
    knots), the covariance file's content (None without one), its written map (u, v, cov, range) when there."""

    label: str
    model: str  # pinhole, fisheye, splined
    K: np.ndarray
    coeffs: np.ndarray
    image_size: tuple[int, int] | None
    unit: str | None
    free: tuple[str, ...] = ()  # a splined lens's knot names
    covariance: dict | None = None  # `read_calibration_covariance`'s dict, or the rig's block (names, values, cov)
    written_map: dict | None = None  # u, v, cov, range of its projection_uncertainty.npz
    files: list[str] = field(default_factory=list)  # what was read
    notes: list[str] = field(default_factory=list)


def _read_map(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: np.asarray(z[k]) for k in ("u", "v", "cov", "range")}
            out["field"] = np.asarray(z["field"], bool) if "field" in z.files else None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to replace
        raise DstereoError(f"{path}: not a readable projection-uncertainty map ({type(exc).__name__}); remove it or "
                           "write it again with dstereo calibrate") from None
    out["range"] = float(out["range"])
    return out


def read_diff_input(spec: str, which: str) -> DiffInput:
    """The camera `spec` names (module docstring); `which` ("A" or "B") for messages."""
    text = str(spec)
    side = None
    if ":" in Path(text).name:
        text, side = text.rsplit(":", 1)
        if side not in SIDES:
            raise DstereoError(f"camera {which} {spec!r}: after ':' give left or right (a rig's camera in its "
                               "stereo.yml)")
    path = Path(text)
    if not path.exists():
        raise DstereoError(f"camera {which}: {path} does not exist; give a results folder, a camera.yml or "
                           "stereo.yml:left")
    if side is not None:
        return _rig_camera(path / "stereo.yml" if path.is_dir() else path, side, which)
    if path.is_dir():
        if (path / "camera.yml").is_file():
            path = path / "camera.yml"
        elif (path / "stereo.yml").is_file():
            raise DstereoError(f"camera {which}: {path} is a rig's folder; name one camera: {path}/left (its own "
                               f"calibration) or {path}:left (the rig's joint solve)")
        else:
            raise DstereoError(f"camera {which}: {path} holds no camera.yml; give a camera's results folder or file")
    return _camera_file(path, which)


def _camera_file(path: Path, which: str) -> DiffInput:
    from dstereo.io.camera_file import read_camera_file

    cam = read_camera_file(path)
    out = DiffInput(f"{which}: {path}", cam.model, cam.K, cam.coeffs, cam.image_size, cam.unit, cam.free,
                    files=[str(path)])
    cov_path, map_path = path.parent / COVARIANCE_NAME, path.parent / MAP_NAME
    if cov_path.is_file():
        out.covariance = read_calibration_covariance(cov_path)
        out.files.append(str(cov_path))
    else:
        out.notes.append(f"{path.parent} has no {COVARIANCE_NAME} (a folder written before it existed, or another "
                         "program's file): no prediction for this camera")
    out.written_map = _read_map(map_path)
    if out.written_map is not None:
        out.files.append(str(map_path))
    return out


def _rig_camera(path: Path, side: str, which: str) -> DiffInput:
    from dstereo.io.calib_files import read_opencv_stereo

    if not path.is_file():
        raise DstereoError(f"camera {which}: {path} does not exist; a rig's camera is STEREO_YML:left or :right")
    calib = read_opencv_stereo(path, unscaled=True)  # the file's own unit: the range is given in it
    i = SIDES.index(side)
    K, D, model = (calib.K1, calib.D1, calib.models[0]) if i == 0 else (calib.K2, calib.D2, calib.models[1])
    from dstereo.io.calib_files import _read_storage

    unit = str(_read_storage(path).get("unit", "") or "").strip().lower() or None
    out = DiffInput(f"{which}: {path}:{side}", model, np.asarray(K, float), np.asarray(D, float).ravel()[:8],
                    calib.image_size, unit, files=[str(path)])
    cov, names = calib.extras.get("cov"), calib.extras.get("cov_names")
    if cov is None:
        out.notes.append(f"{path} carries no covariance: no prediction for this camera")
    else:
        prefix = f"{side}."
        rows = [j for j, n in enumerate(names) if n.startswith(prefix)]
        own = tuple(names[j][len(prefix):] for j in rows)
        if model == "fisheye":  # the pair's names k1..k4 are cv2.fisheye's coefficients in the first slots
            own = tuple({"k1": "fk1", "k2": "fk2", "k3": "fk3", "k4": "fk4"}.get(n, n) for n in own)
        # the values it belongs to are the file's own (one joint solve): None, nothing to check
        out.covariance = {"names": own, "values": None, "cov": np.asarray(cov, float)[np.ix_(rows, rows)],
                          "kind": str(calib.extras.get("cov_structure", "")), "solve": "the rig's joint solve",
                          "joint": None, "poses": None, "range": None, "grid": None, "image_size": calib.image_size}
    map_path = path.parent / f"rig_{side}_{MAP_NAME}"
    out.written_map = _read_map(map_path)
    if out.written_map is not None:
        out.files.append(str(map_path))
    return out


def write_diff(out: Path, force: bool, result: dict, arrays: dict, figure) -> Path:
    """The results folder (module docstring), atomically: `result` as diff.json, `arrays` as diff.npz, and
    `figure(path)` drawing diff.png."""
    from dstereo.io.json_files import write_json
    from dstereo.io.results import atomic_folder

    from dstereo.io.report_html import write_report_html

    with atomic_folder(out, force) as tmp:
        np.savez(tmp / "diff.npz", **arrays)
        figure(tmp / "diff.png")
        write_json(tmp / "diff.json", result)
        (tmp / "report.md").write_text(report_markdown(result))
        write_report_html(tmp, diff_headline(result))
    return Path(out)


def report_markdown(s: dict) -> str:
    """report.md of a difference (its diff.json's content, formatted)."""
    t, p = s["implied_transform"], s["prediction"]
    at = "infinity" if s["distance"] is None else f"{s['distance']:.4g} {s['unit'] or ''}".strip()
    lines = ["# dstereo diff", "", f"A: {s['a']}", "", f"B: {s['b']}", "",
             f"Points at {at} ({s['distance_source']}) on a {s['grid'][0]} x {s['grid'][1]} grid of pixels "
             f"({s['pixels_left_out']} left out: no ray through both cameras); the transform between the cameras "
             f"fitted with weights from {s['weighting']}: rotation {t['rotation_deg']:.4g} deg, translation "
             f"{', '.join(f'{x:.4g}' for x in t['translation'])} {s['unit'] or ''}.", "",
             "## Verdict", "", s["verdict"] + ".", "", "| figure | value |", "|---|---|",
             f"| observed rms difference (weighted) | {s['observed_rms_px']:.4g} px |",
             f"| largest difference | {s['observed_max_px']:.4g} px |"]
    if p is not None:
        b = p["band_if_right"]
        lines += [f"| predicted rms difference | {p['predicted_rms_px']:.4g} px |",
                  f"| ratio (1 if right) | {p['ratio']:.3f} (a right prediction: {b['ratio'][0]:.2f}-"
                  f"{b['ratio'][1]:.2f}, 5-95 %) |",
                  f"| median Mahalanobis distance (1.18 if right) | {p['mahalanobis_median']:.3f} "
                  f"({b['mahalanobis_median'][0]:.2f}-{b['mahalanobis_median'][1]:.2f}) |",
                  f"| raw ratio, its typical value if right | {p['ratio_raw']:.3f}, "
                  f"{p['typical_raw_ratio_if_right']:.3f} |"]
        if p.get("ratio_vs_pose_compensated_maps") is not None:
            lines += [f"| raw ratio against the two pose-compensated maps alone | "
                      f"{p['ratio_vs_pose_compensated_maps']:.3f} |"]
    lines += ["", "![observed difference, predicted difference and Mahalanobis distance per pixel](diff.png)", ""]
    if s["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in s["notes"]] + [""]
    lines += ["Files: [diff.json](diff.json) (these figures), [diff.npz](diff.npz) (the grid's arrays).", ""]
    return "\n".join(lines)


def diff_headline(s: dict):
    """report.html's summary of a difference."""
    from dstereo.io.report_html import Check, Headline

    p = s["prediction"]
    measured = [("observed rms difference", f"{s['observed_rms_px']:.3g} px")]
    if p is None:
        return Headline(measured, [Check("prediction", None, "a camera has no covariance")])
    b = p["band_if_right"]
    measured += [("predicted rms difference", f"{p['predicted_rms_px']:.3g} px"),
                 ("ratio (1 if right)", f"{p['ratio']:.2f}"),
                 ("median Mahalanobis (1.18 if right)", f"{p['mahalanobis_median']:.2f}")]
    return Headline(measured, [Check("inside the band a right prediction falls in", bool(p["inside_band"]),
                                     f"ratio {b['ratio'][0]:.2f}-{b['ratio'][1]:.2f}, Mahalanobis "
                                     f"{b['mahalanobis_median'][0]:.2f}-{b['mahalanobis_median'][1]:.2f}")])


def diff_png(path: Path, u, v, diff, predicted, maha, title: str) -> None:
    """Heat maps on the grid: the observed |difference| with its directions, the predicted rms difference (one
    log colour scale for both: inside the calibrated field they are tenths of a pixel, in extrapolated corners
    tens), and the Mahalanobis distance (1.18 if right); grey where a pixel is left out."""
    import textwrap

    import matplotlib
    from matplotlib.colors import LogNorm

    from dstereo.io.figures import pyplot, save

    plt = pyplot()
    size = np.hypot(diff[..., 0], diff[..., 1])
    panels = [(size, "observed |difference| (px)")]
    if predicted is not None:
        panels += [(predicted, "predicted rms difference (px)"), (maha, "Mahalanobis distance (1.18 if right)")]
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.3), squeeze=False)
    ext = (u[0], u[-1], v[-1], v[0])
    both = np.concatenate([p[np.isfinite(p) & (p > 0)] for p, _ in panels[:2]])
    lo, hi = (np.percentile(both, [2, 98]) if both.size else (1e-3, 1.0))
    hi = max(hi, lo * 10.0)
    for k, (ax, (data, label)) in enumerate(zip(axes[0], panels)):
        cmap = matplotlib.colormaps["viridis"].with_extremes(over="tab:red", under="k", bad="0.6")
        norm = matplotlib.colors.Normalize(0.0, 4.0) if k == 2 else LogNorm(lo, hi)
        im = ax.imshow(np.ma.masked_invalid(data), extent=ext, norm=norm, cmap=cmap)
        ax.set_title(label, fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.04, extend="max" if k == 2 else "both")
    q = np.stack(np.meshgrid(u, v), axis=-1)
    unit = np.where(size > 0, 1.0 / np.where(size > 0, size, 1.0), 0.0)
    step = max(1, len(u) // 16)  # at most ~16 arrows a row: directions, each of the same length
    axes[0][0].quiver(q[::step, ::step, 0], q[::step, ::step, 1], (diff[..., 0] * unit)[::step, ::step],
                      -(diff[..., 1] * unit)[::step, ::step], color="w", pivot="middle", scale_units="xy",
                      scale=1.0 / (0.6 * step * (u[1] - u[0] if len(u) > 1 else 1.0)))
    fig.suptitle("\n".join(textwrap.wrap(title, 190)), fontsize=7)
    save(fig, path, dpi=80)
