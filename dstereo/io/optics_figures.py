"""Figures 5.1-5.3 of the thesis for `dstereo optics`: total depth of field against focal length, f-number and both,
the chosen set-up marked; the curves come from `dstereo.optics.calculator`."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dstereo.io.figures import log_ticks, pyplot, tick_label
from dstereo.optics.calculator import PLOT_NAMES, OpticsConfig, f_number_axis, focal_axis, total_dof_curve


def write_plots(config: OpticsConfig, out_dir: str | os.PathLike) -> list[Path]:
    """Total DoF vs focal length (fixed N), vs N (fixed f) and over (f, N) with the set-up marked; PNGs."""
    plt = pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures = (_plot_vs_focal(config, plt), _plot_vs_f_number(config, plt), _plot_contour(config, plt))
    paths = []
    for name, fig in zip(PLOT_NAMES, figures):
        tmp = out_dir / f".{name}.partial"
        fig.savefig(tmp, format="png", dpi=120)
        plt.close(fig)
        os.replace(tmp, out_dir / name)
        paths.append(out_dir / name)
    return paths


def _label_focal(config: OpticsConfig) -> str:
    return f"lens focal length (mm); DoF with the {config.dof_focal_length} focal length"


def _plot_vs_focal(config: OpticsConfig, plt):
    fig, ax = plt.subplots(figsize=(6, 4))
    focal = focal_axis(config)
    ax.plot(focal, total_dof_curve(config, focal, config.f_number))
    chosen = float(total_dof_curve(config, config.focal_length, config.f_number))
    ax.plot([config.focal_length], [chosen], "rx", ms=10, label=f"chosen set-up: {chosen:.3g} mm")
    ax.set(xlabel=_label_focal(config), ylabel="total depth of field (mm)",
           title=f"N = {config.f_number:g}, s = {config.focus_distance:g} mm")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _plot_vs_f_number(config: OpticsConfig, plt):
    fig, ax = plt.subplots(figsize=(6, 4))
    f_number = f_number_axis(config)
    ax.plot(f_number, total_dof_curve(config, config.focal_length, f_number))
    chosen = float(total_dof_curve(config, config.focal_length, config.f_number))
    ax.plot([config.f_number], [chosen], "rx", ms=10, label=f"chosen set-up: {chosen:.3g} mm")
    ax.set(xlabel="f-number N", ylabel="total depth of field (mm)",
           title=f"f = {config.focal_length:g} mm, s = {config.focus_distance:g} mm")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def _plot_contour(config: OpticsConfig, plt):
    fig, ax = plt.subplots(figsize=(6, 4.5))
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FuncFormatter

    focal, f_number = np.meshgrid(focal_axis(config, 120), f_number_axis(config, 120))
    total = total_dof_curve(config, focal, f_number)
    if np.all(np.isnan(total)):
        ax.text(0.5, 0.5, "focus beyond the hyperfocal distance everywhere", ha="center", transform=ax.transAxes)
    else:
        levels = np.geomspace(np.nanmin(total), np.nanmax(total), 21)
        filled = ax.contourf(focal, f_number, total, levels=levels, norm=LogNorm())
        bar = fig.colorbar(filled, ax=ax, label="total depth of field (mm, log scale)",
                           ticks=log_ticks(levels[0], levels[-1]), format=FuncFormatter(tick_label))
        bar.minorticks_off()
    chosen = float(total_dof_curve(config, config.focal_length, config.f_number))
    if np.isfinite(chosen):
        line = ax.contour(focal, f_number, total, levels=[chosen], colors="white", linewidths=1)
        ax.clabel(line, fmt="%.0f mm")
    ax.plot([config.focal_length], [config.f_number], "rx", ms=12, mew=2, label="chosen set-up")
    ax.set(xlabel=_label_focal(config), ylabel="f-number N", title=f"s = {config.focus_distance:g} mm")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return fig
