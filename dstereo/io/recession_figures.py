"""Figures of the `dstereo recession` results folder (matplotlib, Agg backend): one function, one PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.io.figures import log_colour_bar, map_norm, pyplot


def recession_vs_time(result, path: Path) -> None:
    """Stagnation-point recession over time with its standard errors, the fitted line and its 95 % band."""
    plt = pyplot()
    ok = result.ok
    t = result.times
    r = np.array([f.recession.value for f in result.frames])
    se = np.array([f.recession.se for f in result.frames])
    fit = result.fit
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    ax.errorbar(t[ok], r[ok], yerr=np.nan_to_num(1.96 * se[ok]), fmt="o", ms=4, capsize=2, label="stagnation point")
    tt = np.linspace(t.min(), t.max(), 200)
    ax.plot(tt, fit.intercept + fit.rate * tt, "C1-",
            label=f"fit: {1000 * fit.rate:.3f} mm/ks, 95% [{1000 * fit.ci95[0]:.3f}, {1000 * fit.ci95[1]:.3f}]")
    if result.fit_band is not None:
        tt, band = result.fit_band
        ax.fill_between(tt, fit.intercept + fit.rate * tt - band, fit.intercept + fit.rate * tt + band, color="C1",
                        alpha=0.2, label="95% band of the line")
    for f in result.frames:
        if not f.ok:
            ax.axvline(f.time_s, color="0.7", ls=":", lw=1)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("recession along the axis [mm]")
    ax.set_title("Recession at the stagnation point" + (" (dotted: skipped frames)" if not ok.all() else ""))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _extent(grid) -> list[float]:
    h = grid.spacing / 2
    return [grid.u[0] - h, grid.u[-1] + h, grid.v[-1] + h, grid.v[0] - h]


def recession_maps(result, path: Path, max_panels: int = 12) -> None:
    """Recession maps of the frames (up to `max_panels`, evenly picked) on one colour scale."""
    plt = pyplot()
    idx = np.flatnonzero(result.ok)
    if len(idx) > max_panels:
        idx = idx[np.round(np.linspace(0, len(idx) - 1, max_panels)).astype(int)]
    cols = min(4, len(idx))
    rows = int(np.ceil(len(idx) / cols))
    finite = np.isfinite(result.recession[idx]).any()
    lo, hi = np.nanpercentile(result.recession[idx], [0.5, 99.9]) if finite else (0.0, 1.0)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols + 1, 3.0 * rows), dpi=100, squeeze=False)
    im = None
    for ax, i in zip(axes.ravel(), idx):
        im = ax.imshow(result.recession[i], extent=_extent(result.grid), cmap="viridis", vmin=lo, vmax=hi,
                       interpolation="nearest")
        ax.set_title(f"{result.frames[i].name}: t = {result.frames[i].time_s:g} s", fontsize=8)
        ax.plot(0, 0, "r+", ms=8)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(idx):]:
        ax.set_axis_off()
    if im is not None:
        fig.colorbar(im, ax=axes, label="recession [mm]", shrink=0.8)
    fig.suptitle("Recession maps (face coordinates u, v in mm; + stagnation point)")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def rate_map(result, path: Path) -> None:
    """Rate per grid cell and the half-width of its 95 % interval. Colour scales from the 1st-99th percentile
    (rate) and up to the 99th (interval; log when it spans more than 20x), so a few edge cells fitted from few
    frames do not wash the maps out; cells beyond the scale in the over/under colour (red/blue), cells without a
    fit white."""
    import matplotlib

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), dpi=100)
    for ax, key, title in ((axes[0], "rate", "recession rate"), (axes[1], "ci95_half", "95% interval half-width")):
        data = 1000 * np.asarray(result.rates[key], float)
        norm, extend, log = map_norm(data, 99.0, lower=1.0 if key == "rate" else None)
        cmap = matplotlib.colormaps["magma" if key == "rate" else "cividis"].with_extremes(
            over="tab:red", under="tab:blue", bad="white")
        im = ax.imshow(np.ma.masked_invalid(data), extent=_extent(result.grid), cmap=cmap, norm=norm,
                       interpolation="nearest")
        ax.plot(0, 0, "c+", ms=10)
        ax.set_title(title + ("" if extend == "neither" else " (colour scale 1st-99th percentile)"
                              if key == "rate" else " (colour scale to the 99th percentile)"), fontsize=10)
        ax.set_xlabel("u [mm]")
        ax.set_ylabel("v [mm]")
        bar = fig.colorbar(im, ax=ax, label="mm/ks (um/s)" + (", log scale" if log else ""), extend=extend)
        if log:
            log_colour_bar(bar)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def radial_profiles(result, path: Path, ring_mm: float | None = None) -> None:
    """Azimuthal median of each frame's recession against the distance from the stagnation point."""
    plt = pyplot()
    u, v = result.grid.centres()
    rho = np.hypot(u, v)
    step = ring_mm or max(result.grid.spacing, 0.5)
    edges = np.arange(0, np.nanmax(rho) + step, step)
    centres = 0.5 * (edges[1:] + edges[:-1])
    which = np.digitize(rho, edges) - 1
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    cmap = plt.get_cmap("viridis")
    ok = np.flatnonzero(result.ok)
    for k, i in enumerate(ok):
        m = result.recession[i]
        prof = [np.nanmedian(m[(which == j) & np.isfinite(m)]) if ((which == j) & np.isfinite(m)).sum() >= 3
                else np.nan for j in range(len(centres))]
        ax.plot(centres, prof, color=cmap(k / max(len(ok) - 1, 1)), lw=1.2,
                label=f"t = {result.frames[i].time_s:g} s" if k in (0, len(ok) - 1) else None)
    ax.set_xlabel("distance from the stagnation point [mm]")
    ax.set_ylabel("recession [mm] (ring median)")
    ax.set_title("Radial recession profiles")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
