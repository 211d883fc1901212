"""Heat maps of uncertainties (matplotlib, Agg, PNG): depth std of a reconstruction, projection std of a camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.io.figures import (ROBUST_PERCENTILE, colour_limits, fixed_margins, log_colour_bar, map_norm,  # noqa: F401
                                pyplot, save, text_height)


OVER_COLOUR = "tab:red"  # pixels above the colour scale


def sigma_z_png(path: Path, sigma_z: np.ndarray, title: str, unit: str = "mm") -> None:
    """Depth standard deviation per pixel, colour bar in `unit`, pixels without a point black; the colour
    scale stops at the 95th percentile (arrow on the bar, `colour_limits`) when a few far, badly matched
    points would otherwise wash the map out."""
    import matplotlib

    plt = pyplot()
    h, w = sigma_z.shape
    vmin, vmax, extend = colour_limits(sigma_z, 95.0)
    fig, ax = plt.subplots(figsize=(max(4.0, w / 100 + 1.2), max(3.0, h / 100)), dpi=100)
    cmap = matplotlib.colormaps["magma"].with_extremes(bad="black", over="tab:cyan")
    im = ax.imshow(np.ma.masked_invalid(sigma_z), cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    scale = "\ncolour scale to the 95th percentile; cyan above it" if extend != "neither" else ""
    ax.set_title(title + scale, fontsize=10)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, label=f"depth std sigma_z [{unit}]", fraction=0.046, pad=0.04, extend=extend)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def projection_uncertainty_png(path: Path, pmap, image_size: tuple[int, int], title: str, unit: str) -> None:
    """Worst-direction std (px) of the projection over the image, with contour lines (a `ProjectionUncertaintyMap`).
    Colour scale from `colour_limits` (values above it in OVER_COLOUR, non-finite grey), on a log scale when it
    spans more than LOG_RANGE (a wide-angle lens: 0.4 px in the middle, 20 px at the rim), so both show."""
    import matplotlib

    plt = pyplot()
    w, h = image_size
    std = np.ma.masked_invalid(np.asarray(pmap.std, float))
    norm, extend, log = map_norm(pmap.std)
    least, vmax, clipped = norm.vmin, norm.vmax, extend != "neither"
    finite = np.asarray(pmap.std, float)[np.isfinite(pmap.std)]
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.8))
    du = (pmap.u[1] - pmap.u[0]) / 2 if len(pmap.u) > 1 else 0.5
    dv = (pmap.v[1] - pmap.v[0]) / 2 if len(pmap.v) > 1 else 0.5
    extent = (pmap.u[0] - du, pmap.u[-1] + du, pmap.v[-1] + dv, pmap.v[0] - dv)
    cmap = matplotlib.colormaps["viridis"].with_extremes(over=OVER_COLOUR, bad="0.6")
    im = ax.imshow(std, extent=extent, cmap=cmap, interpolation="nearest" if clipped else "bilinear", norm=norm)
    if finite.size and np.ptp(finite) > 0:
        if log:
            levels = np.geomspace(least, vmax, 7)[1:-1]
        else:
            levels = np.linspace(float(finite.min()), vmax, 7)[1:-1] if clipped else 6
        cs = ax.contour(pmap.u, pmap.v, std, levels=levels, colors="w", linewidths=0.7)
        ax.clabel(cs, fmt="%.2g", fontsize=8)
    bar = fig.colorbar(im, ax=ax, fraction=0.04, extend=extend,
                       label="projection std, worst direction (px)" + (", log scale" if log else ""))
    if log:
        log_colour_bar(bar)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    notes = []
    if clipped:
        notes.append(f"red: above the scale ({ROBUST_PERCENTILE:g}th percentile {vmax:.3g} px; max "
                     f"{float(finite.max()):.3g} px)")
    if np.ma.count_masked(std):
        notes.append("grey: masked (the model cannot be inverted there)")
    held = ("fixed in the boards' frame (pose-compensated)" if getattr(pmap, "method", "") == "pose-compensated"
            else "fixed in the camera frame (intrinsics only, no pose compensation)")
    title = ax.set_title(f"{title}\npoint at {pmap.range_:.4g} {unit} along each ray, {held}"
                         + ("\n" + "; ".join(notes) if notes else ""), fontsize=9)
    # margins for the labels, the colour bar and the title's lines instead of tight_layout (which lays out every
    # text once more: ~30 % of the figure's time, measured); PNG at zlib level 1 (`save`)
    fixed_margins(fig, left=0.75, right=1.0, bottom=0.55, top=text_height(fig, [title]) + 0.15)
    save(fig, path)
