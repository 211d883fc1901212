"""The cross-validation files of a camera's results folder: cross_validation.npz, its figure, and each split's two
halves as camera folders (cross_validation/split_<k>/a and b: camera.yml, camera.json, calibration_covariance.npz),
so that `dstereo diff cross_validation/split_1/a cross_validation/split_1/b` reads split 1's figures."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dstereo.io.figures import pyplot

if TYPE_CHECKING:  # annotations only: the writer takes a finished cross-validation (and stays free of JAX)
    from dstereo.calib.cross_validation import CrossValidation


def write_cross_validation(folder, xval: CrossValidation, unit: str, view_names=None, camera_writer=None) -> dict:
    """cross_validation.npz (per split: diff, predicted cov, Mahalanobis, weight), plots/cross_validation.png and,
    given `camera_writer` (`io.results.write_camera_files`, passed in: results imports this module), the halves'
    camera folders; `view_names`: the used views' names (the halves' indices point into them)."""
    folder = Path(folder)
    np.savez(folder / "cross_validation.npz", u=xval.u, v=xval.v, range=xval.range_,
             diff=np.stack([s.diff for s in xval.splits]), cov=np.stack([s.cov for s in xval.splits]),
             mahalanobis=np.stack([s.mahalanobis for s in xval.splits]),
             weight=np.stack([np.ones(s.diff.shape[:2]) if s.weight is None else s.weight for s in xval.splits]))
    _plot(folder / "plots" / "cross_validation.png", xval, unit)
    halves = (_write_halves(folder / "cross_validation", xval, unit, view_names, camera_writer)
              if xval.solutions and camera_writer is not None else [])
    return {**xval.summary(), "unit": unit, "files": ["cross_validation.npz", "plots/cross_validation.png"] + halves}


def _write_halves(root: Path, xval: CrossValidation, unit: str, view_names, write_camera_files) -> list[str]:
    """cross_validation/split_<k>/{a,b}: each half's camera and calibration_covariance.npz (at the
    cross-validation's range and grid, so `dstereo diff` repeats the split as computed here)."""
    from types import SimpleNamespace

    from dstereo.io.covariance_file import NAME, write_calibration_covariance
    from dstereo.models.distortion import lens_model

    names = tuple(xval.names)
    free = names[4:]
    model = lens_model(free)
    written = []
    for k, (split, parts) in enumerate(zip(xval.splits, xval.halves)):
        for h, (sol, part) in enumerate(zip(xval.solutions[2 * k: 2 * k + 2], parts)):
            where = root / f"split_{k + 1}" / "ab"[h]
            where.mkdir(parents=True)
            p = np.asarray(sol.params, float)
            K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
            views = [int(i) for i in part]
            extra = {"distortion_names": free, "source": f"cross-validation split {k + 1}, half {'AB'[h]}",
                     "views": views if view_names is None else [view_names[i] for i in views]}
            d = p[4:8] if model == "fisheye" else p[4: 12 if set(free) & {"k4", "k5", "k6"} else 9]
            write_camera_files(where, K, d, xval.image_size, extra, model=model, unit=unit)
            values = np.asarray(sol.values, float)[: len(names)]  # the lens parameters lead (a sag follows)
            cov = SimpleNamespace(names=names, values=values, cov=sol.cov, jacobian=None,
                                  kind="the half's reported covariance (the views' effects where fitted)",
                                  views=len(views), joint=sol.joint, poses=sol.poses)
            write_calibration_covariance(where, cov, model, xval.range_, xval.grid, xval.image_size,
                                         solve=f"cross-validation split {k + 1}, half {'AB'[h]}", field=sol.field)
            rel = where.relative_to(root.parent)
            written += [str(rel / "camera.yml"), str(rel / "camera.json"), str(rel / NAME)]
    return written


def _plot(path, xval: CrossValidation, unit: str) -> None:
    import matplotlib

    plt = pyplot()
    s = xval.splits[0]
    obs, pred, maha = xval.median_maps()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    ext = (xval.u[0], xval.u[-1], xval.v[-1], xval.v[0])
    both = np.concatenate([obs[np.isfinite(obs)], pred[np.isfinite(pred)]])
    # the 95th percentile, not the maximum: extrapolated image corners would flatten the rest into one colour
    top = float(np.percentile(both, 95)) if both.size else 1.0
    for ax, data, title, vmax in ((axes[0], obs, "observed |difference| (px), median over splits", top),
                                  (axes[1], pred, "predicted rms difference (px)", top),
                                  (axes[2], maha, "Mahalanobis distance (1.18 if right)", 4.0)):
        cmap = matplotlib.colormaps["viridis"].with_extremes(over="tab:red", bad="0.6")
        im = ax.imshow(np.ma.masked_invalid(data), extent=ext, vmin=0, vmax=vmax, cmap=cmap)
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.04, extend="max")
    q = np.stack(np.meshgrid(xval.u, xval.v), axis=-1)
    spacing = xval.u[1] - xval.u[0] if len(xval.u) > 1 else 1.0
    axes[0].quiver(q[..., 0], q[..., 1], s.diff[..., 0], -s.diff[..., 1], color="w", scale_units="xy",
                   scale=max(top, 1e-12) / (0.8 * spacing))  # the 95th-percentile length spans 0.8 grid steps
    verdict = xval.verdict()
    cut = verdict.find(": the uncertainty")
    fig.suptitle(f"at {xval.range_:.4g} {unit} (arrows: split 1's difference); {verdict[:cut]}\n{verdict[cut + 2:]}",
                 fontsize=8)
    fig.savefig(path, bbox_inches="tight", dpi=80)
    plt.close(fig)
