"""The cross-validation files of a camera's results folder: cross_validation.npz and its figure."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dstereo.io.figures import pyplot

if TYPE_CHECKING:  # annotations only: the writer takes a finished cross-validation (and stays free of JAX)
    from dstereo.calib.cross_validation import CrossValidation


def write_cross_validation(folder, xval: CrossValidation, unit: str) -> dict:
    """cross_validation.npz (per split: diff, predicted cov, Mahalanobis) and plots/cross_validation.png."""
    folder = Path(folder)
    np.savez(folder / "cross_validation.npz", u=xval.u, v=xval.v, range=xval.range_,
             diff=np.stack([s.diff for s in xval.splits]), cov=np.stack([s.cov for s in xval.splits]),
             mahalanobis=np.stack([s.mahalanobis for s in xval.splits]))
    _plot(folder / "plots" / "cross_validation.png", xval, unit)
    return {**xval.summary(), "unit": unit, "files": ["cross_validation.npz", "plots/cross_validation.png"]}


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
