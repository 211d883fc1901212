"""The results folder of `dstereo reconstruct`: rectified images, epipolar check, disparity, depth, points,
per-point standard deviations, PLY cloud and mesh, matrices, summary.json, report.md and report.html (with the
cloud in 3D, `io.reconstruction_report`), written atomically."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dstereo.io.json_files import json_default
from dstereo.io.results import atomic_folder

if TYPE_CHECKING:  # annotations only: a writer takes a finished result and imports none of the pipeline
    from dstereo.stereo.pair_result import PairResult
    from dstereo.config.reconstruction_config import ReconstructionConfig


def _epipolar_image(left: np.ndarray, right: np.ndarray, step: int = 32) -> np.ndarray:
    import cv2

    pair = np.concatenate([left, right], axis=1)
    pair = pair if pair.ndim == 3 else cv2.cvtColor(pair, cv2.COLOR_GRAY2BGR)
    pair = np.ascontiguousarray(pair)
    for i, y in enumerate(range(step // 2, pair.shape[0], step)):
        cv2.line(pair, (0, y), (pair.shape[1] - 1, y), (0, 255, 0) if i % 2 else (0, 0, 255), 1)
    return pair


def _disparity_png(path: Path, disparity: np.ndarray, title: str) -> None:
    import matplotlib

    from dstereo.io.figures import pyplot

    plt = pyplot()

    h, w = disparity.shape
    fig, ax = plt.subplots(figsize=(max(4.0, w / 100 + 1.2), max(3.0, h / 100)), dpi=100)
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="black")
    im = ax.imshow(np.ma.masked_invalid(disparity), cmap=cmap, interpolation="nearest")
    ax.set_title(title)
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, label="disparity [px]", fraction=0.046, pad=0.04)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def write_pair(folder: Path, result: PairResult, config: ReconstructionConfig | None = None) -> None:
    """All outputs of one pair into `folder` (which exists)."""
    if config is None:
        from dstereo.config.reconstruction_config import ReconstructionConfig

        config = ReconstructionConfig()
    import cv2

    from dstereo.io.calib_files import write_pfm
    from dstereo.io.pointcloud import write_mesh_ply, write_ply_points

    t0 = time.perf_counter()
    cv2.imwrite(str(folder / "rectified_left.png"), result.left_rect)
    cv2.imwrite(str(folder / "rectified_right.png"), result.right_rect)
    cv2.imwrite(str(folder / "epipolar.png"), _epipolar_image(result.left_rect, result.right_rect))
    np.save(folder / "disparity.npy", result.disparity)
    write_pfm(folder / "disparity.pfm", result.disparity)
    _disparity_png(folder / "disparity.png", result.disparity, f"{result.name}: disparity")
    np.save(folder / "depth.npy", result.depth.astype(np.float32))
    write_pfm(folder / "depth.pfm", result.depth.astype(np.float32))
    np.save(folder / "points.npy", result.points.astype(np.float32))
    unc = result.uncertainty
    scalars = None
    if unc is not None:
        np.save(folder / "sigma_z.npy", unc.sigma_z.astype(np.float32))
        np.save(folder / "sigma_xyz.npy", unc.sigma_xyz.astype(np.float32))
        np.save(folder / "sigma_z_disparity.npy", unc.sigma_z_disparity.astype(np.float32))  # random part, mm
        np.save(folder / "sigma_z_calibration.npy", unc.sigma_z_calibration.astype(np.float32))
        if unc.sigma_d_map is not None:
            np.save(folder / "sigma_d.npy", unc.sigma_d_map.astype(np.float32))  # disparity noise, px
        if unc.cov is not None:
            np.save(folder / "cov_xyz.npy", unc.cov.astype(np.float32))
        from dstereo.io.sigma_maps import sigma_z_png

        sigma_z_png(folder / "sigma_z.png", unc.sigma_z, f"{result.name}: depth std (per-pixel sigma_d, median "
                    f"{unc.sigma_d:.3g} px" + ("" if unc.calibration_included else
                                                ", calibration uncertainty not included") + ")")
        scalars = {f"sigma_{a}": unc.sigma_xyz[..., i] for i, a in enumerate("xyz")}
    if result.filled is not None:  # filled, not matched: flagged in the arrays and the cloud (`dstereo.stereo.fill`)
        np.save(folder / "filled.npy", result.filled)
        np.save(folder / "fill_sigma_d.npy", result.fill_sigma.astype(np.float32))
        scalars = (scalars or {}) | {"filled": result.filled.astype(np.float32)}
    n_points = write_ply_points(folder / "points.ply", result.points, result.colors, scalars=scalars)
    n_vertices, n_faces = write_mesh_ply(folder / "mesh.ply", result.points, result.colors, config.max_jump)
    np.savez(folder / "matrices.npz", **result.matrices)
    summary = dict(result.summary)
    summary["ply_points"] = n_points
    summary["mesh"] = {"vertices": n_vertices, "faces": n_faces, "max_jump": config.max_jump}
    summary["config"] = config.as_dict()
    summary["timings_s"] = {**summary.get("timings_s", {}), "write_s": time.perf_counter() - t0}
    (folder / "summary.json").write_text(json.dumps(summary, indent=2, default=json_default))
    from dstereo.io.reconstruction_report import write_report

    write_report(folder, summary, result.points, None if unc is None else unc.sigma_z)


def write_atomically(out: str | Path, force: bool, fill) -> Path:
    """Call fill(tmp_folder), then rename the folder to `out`; nothing is left half-written on failure."""
    with atomic_folder(out, force) as tmp:
        fill(tmp)
    return Path(out)


def read_rectification(path: str | Path):
    """The `dstereo.stereo.rectify.Rectification` a results folder's `matrices.npz` (or that file) holds: R1 R2 P1
    P2 Q roi1 roi2, its size and `projection` (a file written before these were recorded: pinhole, and the size of
    the `disparity.npy` beside it)."""
    import jax.numpy as jnp

    from dstereo.errors import DstereoError
    from dstereo.stereo.rectify import PINHOLE, PROJECTIONS, Rectification

    path = Path(path)
    path = path / "matrices.npz" if path.is_dir() else path
    with np.load(path) as z:
        size = tuple(int(v) for v in z["size"]) if "size" in z.files else None
        if size is None and (path.parent / "disparity.npy").is_file():
            size = tuple(int(v) for v in np.load(path.parent / "disparity.npy", mmap_mode="r").shape[1::-1])
        missing = [k for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2") if k not in z.files]
        missing += ["size"] if size is None else []
        if missing:
            raise DstereoError(f"{path}: no {', '.join(missing)}: not a calibrated reconstruction's matrices.npz")
        projection = str(z["projection"]) if "projection" in z.files else PINHOLE
        if projection not in PROJECTIONS:
            raise DstereoError(f"{path}: projection {projection!r} is not one of {list(PROJECTIONS)}")
        arrays = [jnp.asarray(z[k], float) for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2")]
    vertical = bool(abs(float(arrays[3][1, 3])) > abs(float(arrays[3][0, 3])))
    return Rectification(*arrays, size=size, vertical=vertical, projection=projection)
