"""Figures of the calibration results folder (matplotlib, Agg backend, PNG files).

Every function takes plain numpy arrays and a path, draws one figure, saves it and closes it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.io.figures import fixed_margins, log_ticks, pyplot, save, text_height, tick_label  # noqa: F401


def _horizontal() -> dict:
    """Horizontal box plots: `orientation` from matplotlib 3.10 on (`vert` is deprecated there)."""
    import matplotlib

    major, minor = (int(v) for v in matplotlib.__version__.split(".")[:2])
    return {"orientation": "horizontal"} if (major, minor) >= (3, 10) else {"vert": False}


EXACT_KDE_MAX = 500  # up to this many values the KDE is scipy's exact sum; beyond, binned (cost ~ grid, not C)
BIN_BLOCK = 1 << 20  # values binned at a time
MAX_FLIERS = 1000  # outliers drawn per box plot at most (evenly spaced in order, extremes included)


def _kde(values: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """Gaussian KDE on `grid` (even spacing) with scipy's default bandwidth (Scott), or None when the values
    have no spread (a KDE is undefined then). Beyond EXACT_KDE_MAX values the same estimate is computed on a
    binned copy (`binned_kde`), so its cost grows with the grid, not with C x grid."""
    values = values[np.isfinite(values)]
    if values.size < 2 or np.ptp(values) == 0:
        return None
    if values.size > EXACT_KDE_MAX:
        return binned_kde(values, grid)
    from scipy.stats import gaussian_kde

    try:
        return gaussian_kde(values)(grid)
    except np.linalg.LinAlgError:
        return None


def binned_kde(values: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """scipy's gaussian_kde(values)(grid) by linear binning onto a fine grid and an FFT convolution.

    Bandwidth h = std (ddof 1) x n^(-1/5) (Scott's factor, scipy's default). The fine spacing is at most
    h / 10, where linear binning's error is below (spacing / h)^2 / 8 ~ 0.1 % of the peak density
    (Wand & Jones, Kernel Smoothing, 1995, section D.2); at most 2^20 fine points."""
    n = values.size
    h = float(np.std(values, ddof=1)) * n ** (-1 / 5)
    if not h > 0:
        return None
    lo, hi = min(float(grid[0]), float(values.min())), max(float(grid[-1]), float(values.max()))
    lo, hi = lo - 4 * h, hi + 4 * h
    points = int(min(2 ** 20, max(len(grid), np.ceil((hi - lo) / (h / 10))) + 1))
    delta = (hi - lo) / (points - 1)
    counts = np.zeros(points + 1)
    for a in range(0, n, BIN_BLOCK):  # a block at a time: transient memory ~ BIN_BLOCK, not C
        pos = (values[a: a + BIN_BLOCK] - lo) / delta
        left = np.floor(pos).astype(np.int64)
        frac = pos - left
        counts += np.bincount(left, 1 - frac, minlength=points + 1) + np.bincount(left + 1, frac,
                                                                                   minlength=points + 1)
    half = int(np.ceil(5 * h / delta))
    offsets = np.arange(-half, half + 1) * delta
    kernel = np.exp(-0.5 * (offsets / h) ** 2) / (h * np.sqrt(2 * np.pi) * n)
    density = _convolve_same(counts[:points], kernel)
    return np.interp(grid, lo + delta * np.arange(points), np.maximum(density, 0.0))


def _convolve_same(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """scipy.signal.fftconvolve(a, kernel, mode="same") with numpy's FFT (scipy's import alone costs ~0.3-1 s
    of a run); an odd-length kernel, as `binned_kde` builds it."""
    n = a.size + kernel.size - 1
    size = 1 << (n - 1).bit_length()
    full = np.fft.irfft(np.fft.rfft(a, size) * np.fft.rfft(kernel, size), size)[:n]
    start = (kernel.size - 1) // 2
    return full[start: start + a.size]


def _percentile_sorted(s: np.ndarray, q: float) -> float:
    """numpy's default (linear) percentile of an already sorted array, without another copy."""
    pos = q / 100 * (s.size - 1)
    i = int(np.floor(pos))
    j = min(i + 1, s.size - 1)
    return float(s[i] + (s[j] - s[i]) * (pos - i))


def box_stats(values: np.ndarray, label: str = "") -> dict:
    """matplotlib's box-plot statistics (quartiles by linear interpolation, whiskers at the most extreme
    values within 1.5 IQR, the rest fliers) from one sorted copy, for `Axes.bxp`: no per-point artist for
    millions of values. More than MAX_FLIERS fliers are thinned to evenly spaced order statistics."""
    x = np.asarray(values, float)
    s = np.sort(x[np.isfinite(x)]) if not np.isfinite(x).all() else np.sort(x)
    q1, med, q3 = (_percentile_sorted(s, q) for q in (25, 50, 75))
    iqr = q3 - q1
    lo, hi = np.searchsorted(s, q1 - 1.5 * iqr, "left"), np.searchsorted(s, q3 + 1.5 * iqr, "right")
    fliers = np.concatenate([s[:lo], s[hi:]])
    if fliers.size > MAX_FLIERS:
        fliers = fliers[np.unique(np.linspace(0, fliers.size - 1, MAX_FLIERS).round().astype(int))]
    return {"label": label, "med": med, "q1": q1, "q3": q3, "whislo": float(s[lo]) if hi > lo else q1,
            "whishi": float(s[hi - 1]) if hi > lo else q3, "fliers": fliers, "mean": float(np.mean(s))}


def parameter_figure(name: str, initial: np.ndarray, final: np.ndarray, path: Path, unit: str = "",
                     reference: float | None = None) -> None:
    """Thesis Figure 5.9 of the initial and final subsets: histogram, probability density (KDE) and box plot.
    `reference` (e.g. the full-set value) is drawn as a dashed line."""
    draw_parameter_figure(parameter_figure_data(name, initial, final, unit, reference), path)


def parameter_figure_data(name: str, initial: np.ndarray, final: np.ndarray, unit: str = "",
                          reference: float | None = None) -> dict:
    """What `draw_parameter_figure` draws, reduced from the C subsets' values: histogram counts, KDE on 400 grid
    points, box-plot statistics. Cost grows with C only through histograms and quantiles (binned KDE, box plots
    from `box_stats`); the result is small whatever C, so a worker process can draw it."""
    initial, final = np.asarray(initial, float), np.asarray(final, float)
    lo, hi = float(np.min(initial)), float(np.max(initial))
    pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo) * 1e-3, 1e-12)
    bins = np.linspace(lo - pad, hi + pad, 31)
    grid = np.linspace(lo - pad, hi + pad, 400)
    sets = []
    for values, text, colour in ((initial, f"initial ({initial.size} subsets)", "tab:gray"),
                                 (final, f"final ({final.size} subsets)", "tab:blue")):
        sets.append({"counts": np.histogram(values, bins=bins)[0], "density": _kde(values, grid), "text": text,
                     "colour": colour, "size": int(np.isfinite(values).sum())})
    return {"name": name, "unit": unit, "reference": reference, "bins": bins, "grid": grid, "sets": sets,
            "boxes": [box_stats(initial, "initial"), box_stats(final, "final")]}


def draw_parameter_figure(data: dict, path: Path) -> None:
    """Draw and save what `parameter_figure_data` computed: the histogram with each set's KDE over it as subsets
    per bin (density x subsets x bin width, so the curve follows the bars), and the box plots.

    Two panels and one legend: each panel's axes, ticks and texts are most of a figure's drawing time, and a results
    folder draws ten of these (the thesis's three panels with two legends: 0.12 s a figure, these 0.08 s, measured;
    the same content)."""
    plt = pyplot()
    name, unit, reference = data["name"], data["unit"], data["reference"]
    label = f"{name} ({unit})" if unit else name
    fig, (hist, box) = plt.subplots(1, 2, figsize=(11, 3.8), width_ratios=(1.4, 1))
    width = float(data["bins"][1] - data["bins"][0])
    for s in data["sets"]:
        hist.stairs(s["counts"], data["bins"], fill=True, alpha=0.45, color=s["colour"], label=s["text"])
        if s["density"] is not None:
            hist.plot(data["grid"], s["density"] * s["size"] * width, color=s["colour"], lw=1.5)
    box.bxp(data["boxes"], widths=0.6, **_horizontal())
    for ax, title in ((hist, "histogram and density (KDE, in subsets per bin)"), (box, "box plot (whiskers 1.5 IQR)")):
        # a fixed title place: matplotlib's automatic one lays out the tick labels once more (~10 % of the figure)
        ax.set_title(title, y=1.0, pad=6)
        ax.set_xlabel(label)
        if reference is not None and np.isfinite(reference):
            ax.axvline(reference, color="tab:red", ls="--", lw=1, label="full set")
    from matplotlib.ticker import MaxNLocator

    for ax in (hist, box):
        ax.xaxis.set_major_locator(MaxNLocator(5))  # values like 799.25 need room: at most ~5 ticks
        ax.ticklabel_format(axis="x", useOffset=False)
    hist.yaxis.set_major_locator(MaxNLocator(5))
    hist.set_ylabel("subsets per bin")
    hist.legend(fontsize=8, loc="upper left")  # a fixed corner: "best" tries every place against the data
    fig.suptitle(f"{name}: initial and optimised subsets")
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.14, top=0.84, wspace=0.2)
    save(fig, path)


def corner_patches(image_size: tuple[int, int]) -> dict[str, tuple[float, float, float, float]]:
    """The four image-corner patches of the coverage check (outer quarter of the width and of the height,
    1/16 of the area each, as `pipeline.corner_coverage` counts them), as (x0, y0, width, height) in px with
    pixel centres at integer coordinates."""
    w, h = image_size
    x0 = {"left": -0.5, "right": 0.75 * w - 0.5}
    y0 = {"upper": -0.5, "lower": 0.75 * h - 0.5}
    return {f"{v}_{u}": (x0[u], y0[v], w / 4, h / 4) for v in ("upper", "lower") for u in ("left", "right")}


def coverage_heatmap(points: np.ndarray, image_size: tuple[int, int], percent: dict[str, float], path: Path,
                     corner_percent: dict[str, float] | None = None, corner_min: float | None = None) -> None:
    """Heat map of all detected corners over the image, quadrant and centre regions outlined with their share;
    the image-corner patches the coverage warnings speak of are drawn (dashed) with their share, in orange
    where below `corner_min` %."""
    plt = pyplot()
    w, h = image_size
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.6))
    counts, _, _ = np.histogram2d(points[:, 0], points[:, 1], bins=(32, max(int(32 * h / w), 1)),
                                  range=((-0.5, w - 0.5), (-0.5, h - 0.5)))
    im = ax.imshow(counts.T, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.04, label="corners per cell")
    ax.axvline(w / 2 - 0.5, color="w", lw=1)
    ax.axhline(h / 2 - 0.5, color="w", lw=1)
    ax.add_patch(plt.Rectangle((w / 4 - 0.5, h / 4 - 0.5), w / 2, h / 2, fill=False, ec="tab:red", lw=1.5))
    # Quadrant shares between the image-corner patch and the centre box (the patches carry their own).
    spots = {"upper_left": (0.375, 0.125), "upper_right": (0.625, 0.125), "lower_left": (0.375, 0.875),
             "lower_right": (0.625, 0.875), "centre": (0.5, 0.5)}
    for name, (fx, fy) in spots.items():
        ax.text(fx * w, fy * h, f"{percent[name]:.1f}%", color="w", ha="center", va="center", fontsize=12,
                bbox=dict(facecolor="black", alpha=0.4, lw=0))
    if corner_percent is not None:
        for name, (x0, y0, pw, ph) in corner_patches(image_size).items():
            low = corner_min is not None and corner_percent[name] < corner_min
            colour = "tab:orange" if low else "w"
            ax.add_patch(plt.Rectangle((x0, y0), pw, ph, fill=False, ec=colour, lw=2.5 if low else 1, ls="--"))
            ax.text(x0 + pw / 2, y0 + ph / 2, f"corner\n{corner_percent[name]:.1f}%", color=colour, ha="center",
                    va="center", fontsize=9, bbox=dict(facecolor="black", alpha=0.4, lw=0))
    ax.set_title(f"corner coverage ({len(points)} corners): % per quadrant, centre (red)"
                 + ("\nand image-corner patch (dashed, 1/16 of the area)" if corner_percent is not None else ""),
                 fontsize=10)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fixed_margins(fig, left=0.75, right=1.0, bottom=0.55, top=0.6 if corner_percent is not None else 0.4)
    save(fig, path)


def per_image_rms(names: list[str], rms: np.ndarray, path: Path) -> None:
    """Bar chart of each image's RMS reprojection error in the full-set solve."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(max(6, 0.45 * len(names) + 2), 4))
    ax.bar(range(len(names)), rms, color="tab:blue")
    ax.axhline(float(np.sqrt(np.mean(np.square(rms)))), color="tab:red", ls="--", lw=1, label="overall RMS")
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("per-image reprojection error (full-set solve)")
    ax.legend()
    # the rotated image names set the bottom margin (tight_layout would lay out every text for it: ~30 % of the
    # figure's time, measured)
    fixed_margins(fig, left=0.75, right=0.15, bottom=text_height(fig, ax.get_xticklabels()) + 0.2, top=0.4)
    save(fig, path)


def residual_vectors(observed: np.ndarray, residuals: np.ndarray, image_size: tuple[int, int], path: Path) -> None:
    """Residual vectors (projected - observed) of every corner, drawn at the corner, exaggerated to be seen;
    colour = length (colour bar in px), a key arrow gives the scale."""
    plt = pyplot()
    w, h = image_size
    pts, res = observed.reshape(-1, 2), residuals.reshape(-1, 2)
    length = np.linalg.norm(res, axis=1)
    typical = float(np.percentile(length, 95)) or 1.0
    scale = 0.04 * max(w, h) / typical  # the 95th-percentile residual drawn 4 % of the image long
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.6))
    arrows = ax.quiver(pts[:, 0], pts[:, 1], res[:, 0] * scale, res[:, 1] * scale, length,
                       angles="xy", scale_units="xy", scale=1, cmap="plasma", width=0.002)
    fig.colorbar(arrows, ax=ax, fraction=0.04, label="residual length (px)")
    key = float(f"{typical:.1g}")
    ax.quiverkey(arrows, 0.82, 1.02, key * scale, f"{key:g} px", labelpos="E", coordinates="axes", color="k")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(f"residuals (projected - observed), drawn x{scale:.0f}", loc="left")
    fixed_margins(fig, left=0.75, right=1.0, bottom=0.55, top=0.45)
    save(fig, path)
