"""Figures 5.1-5.3 of the thesis for `dstereo optics`: total depth of field against focal length, f-number and both,
the chosen set-up marked; the curves come from `dstereo.optics.calculator`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dstereo.io.figures import log_ticks, pyplot, tick_label
from dstereo.optics.calculator import PLOT_NAMES, DofCurves, OpticsConfig


def write_plots(config: OpticsConfig, curves: DofCurves, out_dir: str | os.PathLike) -> list[Path]:
    """Total DoF vs focal length (fixed N), vs N (fixed f) and over (f, N) with the set-up marked; PNGs of the
    `curves` (`optics.calculator.dof_curves`)."""
    plt = pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = (_plot_vs_focal(config, curves, plt), _plot_vs_f_number(config, curves, plt),
               _plot_contour(config, curves, plt))
    paths = []
    for name, fig in zip(PLOT_NAMES, figures):
        tmp = out_dir / f".{name}.partial"
        fig.savefig(tmp, format="png", dpi=120)
        plt.close(fig)
        os.replace(tmp, out_dir / name)
        paths.append(out_dir / name)
    return paths


def write_report(out_dir: str | os.PathLike, rows: list[tuple[str, str]], results: dict) -> list[Path]:
    """report.md (the set-up's table `rows` of (quantity, value), the notes, the figures) and report.html beside
    the figures `write_plots` drew in `out_dir`; returns both paths."""
    from dstereo.io.report_headlines import optics_headline
    from dstereo.io.report_html import write_report_html

    out_dir = Path(out_dir)
    lines = ["# Optics: depth of field of the set-up", "", "| quantity | value |", "|---|---|"]
    lines += [f"| {label} | {value} |" for label, value in rows]
    lines += ["", *(f"- note: {n}" for n in results.get("notes", [])), "", "## Figures", ""]
    lines += [f"![{name}]({name})" for name in PLOT_NAMES]
    (out_dir / "report.md").write_text("\n".join(lines) + "\n")
    return [out_dir / "report.md", write_report_html(out_dir, optics_headline(results))]


def _label_focal(config: OpticsConfig) -> str:
    return f"lens focal length (mm); DoF with the {config.dof_focal_length} focal length"


def _plot_vs_focal(config: OpticsConfig, curves: DofCurves, plt):
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(curves.focal, curves.total_vs_focal)
    chosen = curves.chosen
    ax.plot([config.focal_length], [chosen], "rx", ms=10, label=f"chosen set-up: {chosen:.3g} mm")
    ax.set(xlabel=_label_focal(config), ylabel="total depth of field (mm)",
           title=f"N = {config.f_number:g}, s = {config.focus_distance:g} mm")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _plot_vs_f_number(config: OpticsConfig, curves: DofCurves, plt):
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(curves.f_number, curves.total_vs_f_number)
    chosen = curves.chosen
    ax.plot([config.f_number], [chosen], "rx", ms=10, label=f"chosen set-up: {chosen:.3g} mm")
    ax.set(xlabel="f-number N", ylabel="total depth of field (mm)",
           title=f"f = {config.focal_length:g} mm, s = {config.focus_distance:g} mm")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _plot_contour(config: OpticsConfig, curves: DofCurves, plt):
    fig, ax = plt.subplots(figsize=(6, 4.5))
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FuncFormatter

    focal, f_number, total = curves.grid_focal, curves.grid_f_number, curves.grid_total
    if np.all(np.isnan(total)):
        ax.text(0.5, 0.5, "focus beyond the hyperfocal distance everywhere", ha="center", transform=ax.transAxes)
    else:
        levels = np.geomspace(np.nanmin(total), np.nanmax(total), 21)
        filled = ax.contourf(focal, f_number, total, levels=levels, norm=LogNorm())
        bar = fig.colorbar(filled, ax=ax, label="total depth of field (mm, log scale)",
                           ticks=log_ticks(levels[0], levels[-1]), format=FuncFormatter(tick_label))
        bar.minorticks_off()
    chosen = curves.chosen
    if np.isfinite(chosen):
        line = ax.contour(focal, f_number, total, levels=[chosen], colors="white", linewidths=1)
        ax.clabel(line, fmt="%.0f mm")
    ax.plot([config.focal_length], [config.f_number], "rx", ms=12, mew=2, label="chosen set-up")
    ax.set(xlabel=_label_focal(config), ylabel="f-number N", title=f"s = {config.focus_distance:g} mm")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return fig
