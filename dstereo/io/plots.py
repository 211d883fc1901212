"""Figures of the calibration results folder (matplotlib, Agg backend, PNG files).

Every function takes plain numpy arrays and a path, draws one figure, saves it and closes it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _horizontal() -> dict:
    """Horizontal box plots: `orientation` from matplotlib 3.10 on (`vert` is deprecated there)."""
    import matplotlib

    major, minor = (int(v) for v in matplotlib.__version__.split(".")[:2])
    return {"orientation": "horizontal"} if (major, minor) >= (3, 10) else {"vert": False}


def _kde(values: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """Gaussian KDE on `grid`, or None when the values have no spread (a KDE is undefined then)."""
    from scipy.stats import gaussian_kde

    if values.size < 2 or np.ptp(values) == 0:
        return None
    try:
        return gaussian_kde(values)(grid)
    except np.linalg.LinAlgError:
        return None


def parameter_figure(name: str, initial: np.ndarray, final: np.ndarray, path: Path, unit: str = "",
                     reference: float | None = None) -> None:
    """Thesis Figure 5.9: histogram, probability density (KDE) and box plot of the initial and final subsets.
    `reference` (e.g. the full-set value) is drawn as a dashed line."""
    plt = _pyplot()
    initial, final = np.asarray(initial, float), np.asarray(final, float)
    lo, hi = float(np.min(initial)), float(np.max(initial))
    pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo) * 1e-3, 1e-12)
    bins = np.linspace(lo - pad, hi + pad, 31)
    grid = np.linspace(lo - pad, hi + pad, 400)
    label = f"{name} ({unit})" if unit else name
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    sets = ((initial, f"initial ({initial.size} subsets)", "tab:gray"),
            (final, f"final ({final.size} subsets)", "tab:blue"))
    for values, text, colour in sets:
        axes[0].hist(values, bins=bins, alpha=0.55, color=colour, label=text, histtype="stepfilled")
        density = _kde(values, grid)
        if density is not None:
            axes[1].plot(grid, density, color=colour, label=text)
    axes[2].boxplot([initial, final], widths=0.6, **_horizontal())
    axes[2].set_yticks([1, 2], ["initial", "final"])
    for ax, title in zip(axes, ("histogram", "probability density (KDE)", "box plot")):
        ax.set_title(title)
        ax.set_xlabel(label)
        if reference is not None and np.isfinite(reference):
            ax.axvline(reference, color="tab:red", ls="--", lw=1, label="full set")
    axes[0].set_ylabel("subsets")
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=8)
    fig.suptitle(f"{name}: initial and optimised subsets")
    fig.subplots_adjust(left=0.05, right=0.98, bottom=0.14, top=0.84, wspace=0.25)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def coverage_heatmap(points: np.ndarray, image_size: tuple[int, int], percent: dict[str, float], path: Path) -> None:
    """Heat map of all detected corners over the image, quadrant and centre regions outlined with their share."""
    plt = _pyplot()
    w, h = image_size
    fig, ax = plt.subplots(figsize=(7, 7 * h / w + 0.6))
    counts, _, _ = np.histogram2d(points[:, 0], points[:, 1], bins=(32, max(int(32 * h / w), 1)),
                                  range=((-0.5, w - 0.5), (-0.5, h - 0.5)))
    im = ax.imshow(counts.T, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.04, label="corners per cell")
    ax.axvline(w / 2 - 0.5, color="w", lw=1)
    ax.axhline(h / 2 - 0.5, color="w", lw=1)
    ax.add_patch(plt.Rectangle((w / 4 - 0.5, h / 4 - 0.5), w / 2, h / 2, fill=False, ec="tab:red", lw=1.5))
    spots = {"upper_left": (0.25, 0.1), "upper_right": (0.75, 0.1), "lower_left": (0.25, 0.9),
             "lower_right": (0.75, 0.9), "centre": (0.5, 0.5)}
    for name, (fx, fy) in spots.items():
        ax.text(fx * w, fy * h, f"{percent[name]:.1f}%", color="w", ha="center", va="center", fontsize=12,
                bbox=dict(facecolor="black", alpha=0.4, lw=0))
    ax.set_title(f"corner coverage ({len(points)} corners)")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def per_image_rms(names: list[str], rms: np.ndarray, path: Path) -> None:
    """Bar chart of each image's RMS reprojection error in the full-set solve."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(max(6, 0.45 * len(names) + 2), 4))
    ax.bar(range(len(names)), rms, color="tab:blue")
    ax.axhline(float(np.sqrt(np.mean(np.square(rms)))), color="tab:red", ls="--", lw=1, label="overall RMS")
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=8)
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("per-image reprojection error (full-set solve)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def residual_vectors(observed: np.ndarray, residuals: np.ndarray, image_size: tuple[int, int], path: Path) -> None:
    """Residual vectors (projected - observed) of every corner, drawn at the corner, exaggerated to be seen."""
    plt = _pyplot()
    w, h = image_size
    pts, res = observed.reshape(-1, 2), residuals.reshape(-1, 2)
    typical = float(np.percentile(np.linalg.norm(res, axis=1), 95)) or 1.0
    scale = 0.04 * max(w, h) / typical  # the 95th-percentile residual drawn 4 % of the image long
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.6))
    ax.quiver(pts[:, 0], pts[:, 1], res[:, 0] * scale, res[:, 1] * scale, np.linalg.norm(res, axis=1),
              angles="xy", scale_units="xy", scale=1, cmap="plasma", width=0.002)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"residuals (projected - observed), drawn x{scale:.0f}; colour = length (px)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
