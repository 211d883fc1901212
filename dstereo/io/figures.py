"""What every figure of the results folders shares: the Agg backend, log-scale ticks and labels, robust colour
scales for maps, margins and the PNG save. The figures themselves live with their folder's writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display; forced, as figure workers start fresh)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def log_ticks(lo: float, hi: float) -> np.ndarray:
    """Colour-bar ticks of a log scale over [lo, hi]: 1-2-5 times powers of ten inside, else (a range under
    about a factor 5) five geometric steps rounded to 2 significant digits; distinct and labelled by `tick_label`."""
    decades = np.arange(np.floor(np.log10(lo)), np.ceil(np.log10(hi)) + 1)
    ticks = np.array([m * 10.0 ** d for d in decades for m in (1, 2, 5)])
    ticks = ticks[(ticks >= lo) & (ticks <= hi)]
    if len(ticks) < 3:
        ticks = np.unique([float(f"{t:.2g}") for t in np.geomspace(lo, hi, 5)])
        ticks = ticks[(ticks >= lo) & (ticks <= hi)]
    return ticks


def tick_label(value: float, _pos=None) -> str:
    """'0.05', '2', '150', '20000': the tick's own digits (1-2-5 ticks are short), never a small value as 0."""
    return f"{value:g}"


def fixed_margins(fig, left: float, right: float, bottom: float, top: float) -> None:
    """Margins in inches (the labels' room) instead of `tight_layout`, which lays out every text once more
    before the save draws it (~30 % of such a figure's time, measured)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h)


def text_height(fig, texts) -> float:
    """Height in inches of the tallest of `texts` (matplotlib Text artists, rotated ones by their extent): the
    room a margin must leave for them, laid out alone rather than the whole figure (`fixed_margins`)."""
    renderer = fig.canvas.get_renderer()
    return max((t.get_window_extent(renderer).height for t in texts if t.get_text()), default=0.0) / fig.dpi


def save(fig, path: Path, dpi: int = 90) -> None:
    """savefig as PNG with zlib level 1 (faster than the default 6; a parameter figure measured 62 kB instead of
    61 kB), then close the figure."""
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=dpi, pil_kwargs={"compress_level": 1})
    plt.close(fig)


ROBUST_PERCENTILE = 99.0  # projection maps: the colour scale stops here unless the data fit in it
SWAMP_FACTOR = 1.25  # the full range is kept unless it is more than this times the percentile range


def colour_limits(values: np.ndarray, percentile: float = ROBUST_PERCENTILE,
                  lower: float | None = None) -> tuple[float, float, str]:
    """(vmin, vmax, extend) of a map's colour scale. Non-negative maps (`lower` None): 0 to the `percentile` of
    the finite values, so that one huge value (a 4e13 px std where a ray leaves the model's valid range) does
    not compress every other pixel into one colour. Signed maps: `lower` to `percentile` percentiles.
    `extend` ("neither", "max", "min", "both", as matplotlib's colour bar takes it) says which side has finite
    values beyond the scale (drawn in the over/under colour). Non-finite values are ignored (mask them)."""
    finite = np.asarray(values, float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return 0.0, 1.0, "neither"
    top, peak = float(np.percentile(finite, percentile)), float(finite.max())
    bottom, least = (0.0, 0.0) if lower is None else (float(np.percentile(finite, lower)), float(finite.min()))
    if peak - bottom <= SWAMP_FACTOR * (top - bottom):  # nothing far above: the full range shows it all
        top = peak
    if lower is not None and top - least <= SWAMP_FACTOR * (top - bottom):
        bottom = least
    if not top > bottom:  # constant
        top = bottom + (abs(bottom) or 1.0)
    over, under = peak > top, lower is not None and least < bottom
    return bottom, top, {(False, False): "neither", (True, False): "max", (False, True): "min",
                         (True, True): "both"}[(bool(over), bool(under))]


LOG_RANGE = 20.0  # a non-negative map whose colour range spans more than this factor is drawn on a log scale


def map_norm(values: np.ndarray, percentile: float = ROBUST_PERCENTILE, lower: float | None = None):
    """(norm, extend, log) for imshow / colorbar: `colour_limits`, and for a non-negative map whose scale spans
    more than LOG_RANGE from its smallest positive value, a log scale from there (both the small middle and
    the large rim of a map then show)."""
    from matplotlib.colors import LogNorm, Normalize

    vmin, vmax, extend = colour_limits(values, percentile, lower)
    finite = np.asarray(values, float)
    finite = finite[np.isfinite(finite)]
    least = float(finite[finite > 0].min()) if lower is None and (finite > 0).any() else 0.0
    if least > 0 and vmax / least > LOG_RANGE:
        return LogNorm(least, vmax), extend, True
    return Normalize(vmin, vmax), extend, False


def log_colour_bar(bar) -> None:
    """1-2-5 ticks with significant-digit labels on a log colour bar (matplotlib's default can print 0)."""
    from matplotlib.ticker import FuncFormatter

    bar.set_ticks(log_ticks(bar.norm.vmin, bar.norm.vmax))
    bar.ax.yaxis.set_major_formatter(FuncFormatter(tick_label))
    bar.minorticks_off()
