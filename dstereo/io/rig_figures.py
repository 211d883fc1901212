"""Figures of a rig of K cameras (`--left/--right` and `--cameras`): the rig in 3D, and its consistency per frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dstereo.io.figures import pyplot as _pyplot

COLOURS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown", "tab:pink", "tab:olive")


def _frustum(k: np.ndarray, size: tuple[int, int], depth: float) -> np.ndarray:
    """(5, 3) apex and image-corner rays of a camera at `depth`, camera frame."""
    fx, fy, cx, cy = k
    w, h = size
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float) - 0.5  # the image's outer edges (pixel centres at
    # integer coordinates)
    rays = np.column_stack([(corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy, np.ones(4)]) * depth
    return np.vstack([np.zeros(3), rays])


def frustum_depth(baseline: float, distance: float) -> float:
    """Drawn depth of a camera frustum: half the baseline (two frusta side by side then stay apart and the
    baseline reads at a glance), kept between 3 % and 25 % of the board distance so they remain visible."""
    return float(np.clip(0.5 * baseline, 0.03 * distance, 0.25 * distance))


def _display(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera frame (x right, y down, z forward) -> plot axes (x, z, -y): the cameras look 'into' the plot."""
    p = np.asarray(points)
    return p[:, 0], p[:, 2], -p[:, 1]


def rig_view(cameras, rts, names, poses, obj, pattern, path: Path, unit: str, title: str = "rig") -> None:
    """3D view in the reference camera's frame: each camera's frustum (cameras: (k (4,), image size)), its
    place (rts (K, 6) T_k_ref as rvec, T), the lines from the reference to each camera, and every frame's board
    (poses (F, 6) T_ref_board; obj (n, 3) its corners, pattern (cols, rows))."""
    from dstereo.models.pose import rotation_matrix

    plt = _pyplot()
    cols, rows = pattern
    outline = np.asarray(obj)[[0, cols - 1, cols * rows - 1, cols * (rows - 1), 0]]
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    boards = []
    for pose in poses:
        pts = outline @ rotation_matrix(pose[:3]).T + pose[3:]
        boards.append(pts)
        ax.plot(*_display(pts), color="tab:gray", lw=0.8)
    rots = [rotation_matrix(rt[:3]) for rt in rts]
    centres = [-r.T @ np.asarray(rt[3:], float) for r, rt in zip(rots, rts)]
    baselines = [float(np.linalg.norm(c)) for c in centres[1:]]
    distance = float(np.median([np.linalg.norm(b.mean(axis=0)) for b in boards]))
    depth = frustum_depth(min(baselines) if baselines else distance, distance)
    for name, centre, b in zip(names[1:], centres[1:], baselines):
        ax.plot(*_display([np.zeros(3), centre]), color="k", lw=2.5 if len(names) == 2 else 1.2, marker="o", ms=4,
                label=f"{names[0]} - {name} {b:.4g} {unit}")
    for i, (name, (k, size), rot, centre) in enumerate(zip(names, cameras, rots, centres)):
        f = _frustum(np.asarray(k), size, depth) @ rot + centre  # camera -> reference: R' x + centre
        colour = COLOURS[i % len(COLOURS)]
        for j in range(1, 5):
            ax.plot(*_display([f[0], f[j]]), color=colour, lw=1)
        ax.plot(*_display(f[[1, 2, 3, 4, 1]]), color=colour, lw=1.5, label=name)
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"z ({unit})")
    ax.set_zlabel(f"-y ({unit})")
    everything = np.vstack(boards + [np.asarray(centres)])
    span = np.ptp(everything, axis=0).max() / 2
    mid = (everything.max(axis=0) + everything.min(axis=0)) / 2
    ax.set_xlim(mid[0] - span, mid[0] + span)
    ax.set_ylim(mid[2] - span, mid[2] + span)
    ax.set_zlim(-mid[1] - span, -mid[1] + span)
    ax.set_title(f"{title}, {len(poses)} board poses (median distance {distance:.4g} {unit}); frusta drawn "
                 f"{depth:.3g} {unit} deep", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def consistency_figure(consistency, path: Path) -> None:
    """Each frame's share of the rig-consistency statistic, T_f / dof_f (1 expected; `calib/rig_consistency.py`),
    with the 99.9 % point of chi^2(dof_f) / dof_f: frames above it are ones the rig cannot explain."""
    from scipy import stats

    plt = _pyplot()
    frames = np.flatnonzero(consistency.frame_dof > 0)
    ratio = consistency.frame_statistic[frames] / consistency.frame_dof[frames]
    limit = stats.chi2.ppf(1.0 - consistency.alpha, consistency.frame_dof[frames]) / consistency.frame_dof[frames]
    fig, ax = plt.subplots(figsize=(max(6, 0.4 * len(frames) + 2), 4))
    x = np.arange(len(frames))
    ax.bar(x, ratio, color=np.where(ratio > limit, "tab:red", "tab:blue"))
    ax.step(np.r_[x - 0.5, x[-1] + 0.5], np.r_[limit, limit[-1]], where="post", color="k", lw=1,
            label=f"{100 * (1 - consistency.alpha):.1f} % point of a consistent frame")
    ax.axhline(1.0, color="tab:gray", lw=0.8, ls="--", label="expected (1)")
    ax.set_xticks(x)
    ax.set_xticklabels([consistency.frames[f] for f in frames], rotation=90, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("T_f / constraints")
    ax.set_title(f"rig consistency per frame: T/c = {consistency.ratio:.2f} overall, p = {consistency.p_value:.2g}",
                 fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


RIG_UNITS = {"stereo_re": "px", "RVnorm": "rad", "RVx": "rad", "RVy": "rad", "RVz": "rad"}  # the rest: board unit


def box_plots(filtering, names, path: Path, title: str, unit: str) -> None:
    """Thesis Figures 5.15/5.16: one panel per column (`NAME@a-b` of `calib/rig_subsets.py`), box plots of the
    initial and the optimised subsets."""
    from dstereo.io.plots import box_stats

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.8))
    for ax, name in zip(np.atleast_1d(axes), names):
        col = filtering.column(name)
        ax.bxp([box_stats(col[filtering.alive_after(0)], "initial"), box_stats(col[filtering.survivors], "final")],
               widths=0.6)
        ax.set_xticks([1, 2], ["initial", "optimised"])
        ax.set_title(f"{name} ({RIG_UNITS.get(name.split('@')[0], unit)})")
        ax.ticklabel_format(axis="y", useOffset=False)
    fig.suptitle(f"{title}: {int(filtering.usable.sum())} initial, {int(filtering.survivors.sum())} optimised subsets")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
