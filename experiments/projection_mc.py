"""Pose-compensated projection uncertainty against a Monte Carlo of re-noised synthetic calibrations.

A synthetic camera (f 800 px, 640 x 480, k1 k2 p1 p2 k3) sees a 9 x 6 board in V views; every draw adds fresh
N(0, sigma) corner noise to the true corners and re-solves (the batched structured solver). For grid pixels, the
point at the mean board distance along the TRUE ray is mapped into each TRUE board frame and brought back with
the draw's solved poses (mean over views) and projected by the draw's intrinsics: the spread over draws is the
projection uncertainty of a board-fixed point, which the pose-compensated map predicts. The intrinsics-only map
(point fixed in the camera frame) is shown against the same spread. Run: .venv/bin/python experiments/projection_mc.py
"""

from __future__ import annotations

import sys

import numpy as np

from dstereo.calib.cross_validation import solve_halves
from dstereo.calib.mono import calibrate_full
from dstereo.synth.board_views import FREE, SIZE, board_fixed_spread, scene
from dstereo.uncertainty.projection import mean_board_distance, solution_map


def main(n_draws: int = 200, sigma: float = 0.3):
    cam, poses, obj, corners = scene()
    rng = np.random.default_rng(1)
    noisy0 = corners + rng.normal(0, sigma, corners.shape)
    nominal = calibrate_full(obj, noisy0, SIZE, FREE)
    obs_all = corners[None] + rng.normal(0, sigma, (n_draws, *corners.shape))
    draws = solve_halves(nominal, obj, obs_all, np.ones((n_draws, len(corners))))  # all views, fresh noise each
    range_ = mean_board_distance(poses, obj)
    maps = {m: solution_map(nominal, SIZE, range_, m, grid=(8, 6)) for m in ("pose-compensated", "intrinsics-only")}
    q = np.stack(np.meshgrid(maps["pose-compensated"].u, maps["pose-compensated"].v), axis=-1).reshape(-1, 2)
    spread = board_fixed_spread(cam, poses, draws, q, range_)
    spread -= spread.mean(axis=0)
    emp = np.sqrt(np.linalg.eigvalsh(np.einsum("dpi,dpj->pij", spread, spread) / len(spread))[:, -1])
    print(f"{n_draws} draws, sigma {sigma} px, {len(poses)} views, range {range_:.0f} mm")
    for m, pm in maps.items():
        ratio = pm.std.ravel() / emp
        print(f"{m:17s}: predicted {np.nanmin(pm.std):.4f}..{np.nanmax(pm.std):.4f} px, MC {emp.min():.4f}.."
              f"{emp.max():.4f} px, predicted/MC {np.nanmin(ratio):.3f}..{np.nanmax(ratio):.3f} "
              f"(median {np.nanmedian(ratio):.3f}), centre {pm.at((320, 240)):.4f} px")
    return maps, emp


if __name__ == "__main__":
    main(*(int(a) if i == 0 else float(a) for i, a in enumerate(sys.argv[1:])))
