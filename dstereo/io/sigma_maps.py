"""Heat maps of uncertainties (matplotlib, Agg, PNG): depth std of a reconstruction, projection std of a camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def sigma_z_png(path: Path, sigma_z: np.ndarray, title: str, unit: str = "mm") -> None:
    """Depth standard deviation per pixel, colour bar in `unit`, pixels without a point black; the colour
    scale stops at the 95th percentile (arrow on the bar) so a few far, badly matched points do not wash the
    map out."""
    import matplotlib

    plt = _pyplot()
    h, w = sigma_z.shape
    finite = sigma_z[np.isfinite(sigma_z)]
    top = float(np.percentile(finite, 95)) if finite.size else 1.0
    fig, ax = plt.subplots(figsize=(max(4.0, w / 100 + 1.2), max(3.0, h / 100)), dpi=100)
    cmap = matplotlib.colormaps["magma"].with_extremes(bad="black")
    im = ax.imshow(np.ma.masked_invalid(sigma_z), cmap=cmap, vmin=0.0, vmax=top if top > 0 else None,
                   interpolation="nearest")
    ax.set_title(title)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, label=f"depth std sigma_z [{unit}] (scale to the 95th percentile)", fraction=0.046,
                 pad=0.04, extend="max")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def projection_uncertainty_png(path: Path, pmap, image_size: tuple[int, int], title: str, unit: str) -> None:
    """Worst-direction std (px) of the projection over the image, with contour lines (a `ProjectionUncertaintyMap`)."""
    plt = _pyplot()
    w, h = image_size
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.8))
    du = (pmap.u[1] - pmap.u[0]) / 2 if len(pmap.u) > 1 else 0.5
    dv = (pmap.v[1] - pmap.v[0]) / 2 if len(pmap.v) > 1 else 0.5
    extent = (pmap.u[0] - du, pmap.u[-1] + du, pmap.v[-1] + dv, pmap.v[0] - dv)
    im = ax.imshow(pmap.std, extent=extent, cmap="viridis", interpolation="bilinear", vmin=0.0)
    if np.ptp(pmap.std) > 0:
        cs = ax.contour(pmap.u, pmap.v, pmap.std, levels=6, colors="w", linewidths=0.7)
        ax.clabel(cs, fmt="%.2g", fontsize=8)
    fig.colorbar(im, ax=ax, fraction=0.04, label="projection std, worst direction (px)")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(f"{title}\npoint at {pmap.range_:.4g} {unit} along each ray; intrinsics only (no extrinsics "
                 "compensation)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
