"""Per-view random effects (`uncertainty/view_effects.py`) against a Monte Carlo, on synthetic calibrations.

A synthetic camera (f 800 px, 640 x 480, k1 k2 p1 p2 k3) sees a 9 x 6 board (25 mm) in V views. Each draw
makes fresh corner errors and re-solves with all views; the spread of the draws' intrinsics is the truth the
predicted covariances are compared with. Three error processes:

- `independent`: N(0, 0.2 px) per corner coordinate (every covariance should be the Jacobian's);
- `camera jitter`: 0.1 px plus each view seeing its own camera (fx, fy +- 1.5 px, cx, cy +- 1 px, k1 +- 0.004:
  the random-effects model's own premise);
- `board flex`: 0.1 px plus each view's board sagging by its own N(0, 0.4 mm) in x and in y (mrcal's parabola),
  the sag not solved: a process the model does not contain.

Per process and covariance (Jacobian; Jacobian x max(1, kappa), the view scatter; random effects), over the draws:
the mean predicted std / the MC std per parameter (1 if right), and mean e' C^-1 e / G of the draws' deviations from
the MC mean under each draw's own prediction (1 if right; above: optimistic). Run:
.venv/bin/python -m experiments.view_effects_mc [DRAWS]   (about a minute for 200 draws)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from dstereo.calib.mono import _residual_weights, _run, _shared, calibrate_full
from dstereo.calib.problem import sag_basis
from dstereo.models.camera import Camera
from dstereo.solver.lm import LMOptions
from dstereo.synth import Board, board_pose_set, object_points, true_corners
from dstereo.uncertainty.covariance import covariance
from dstereo.uncertainty.view_effects import view_effects
from dstereo.uncertainty.view_scatter import view_scatter

SIZE, PATTERN, SQUARE = (640, 480), (9, 6), 25.0
VIEWS = 16
FREE = ("k1", "k2", "p1", "p2", "k3")
TRUE = (800.0, 805.0, 322.0, 238.0, [-0.25, 0.1, 1e-3, -5e-4, -0.02])
JITTER = np.array([1.5, 1.5, 1.0, 1.0, 0.004, 0, 0, 0, 0])  # std per view of fx fy cx cy k1 (k2.. none)
FLEX_MM = 0.4


def _camera(params):
    return Camera.create(*params[:4], list(params[4:]), FREE, SIZE)


def corners(rng, process: str, poses, obj):
    base = np.r_[TRUE[:4], TRUE[4]]
    out = []
    for p in poses:
        params = base + (rng.normal(0, JITTER) if process == "camera jitter" else 0.0)
        if process == "board flex":
            import cv2
            from scipy.spatial.transform import Rotation
            pts = obj.copy()
            pts[:, 2] += sag_basis(obj) @ rng.normal(0, FLEX_MM, 2)
            cam = Rotation.from_rotvec(p[:3]).apply(pts) + p[3:]
            k = np.array([[base[0], 0, base[2]], [0, base[1], base[3]], [0, 0, 1.0]])
            out.append(cv2.projectPoints(cam, np.zeros(3), np.zeros(3), k, base[4:])[0].reshape(-1, 2))
        else:
            out.append(true_corners(_camera(params), p, PATTERN, SQUARE))
    sigma = 0.2 if process == "independent" else 0.1
    return np.array(out) + rng.normal(0, sigma, (len(poses), len(obj), 2))


def run(process: str, draws: int, seed: int = 0, views: int = VIEWS):
    rng = np.random.default_rng(seed)
    cam0 = _camera(np.r_[TRUE[:4], TRUE[4]])
    poses = board_pose_set([cam0], [np.zeros(6)], Board(PATTERN, SQUARE, SQUARE), views, seed)
    obj = object_points(PATTERN, SQUARE)
    obs = np.stack([corners(rng, process, poses, obj) for _ in range(draws)])
    nominal = calibrate_full(obj, obs[0], SIZE, FREE)
    k, g = draws, len(nominal.values)
    opts = LMOptions()
    res = _run(nominal.free, opts, np.repeat(nominal.values[None], k, 0), np.repeat(nominal.poses[None], k, 0), obs,
               np.ones((k, views)), np.full(k, opts.lambda0), _shared(obj),
               r_weight=np.repeat(_residual_weights(np.ones((views, len(obj)), bool))[None], k, 0))
    est = np.asarray(res.g)
    ok = np.asarray(res.status) > 0
    dev = est[ok] - est[ok].mean(axis=0)
    mc = dev.T @ dev / (len(dev) - 1)
    n_res, dof = 2 * views * len(obj), 2 * views * len(obj) - g - 6 * views
    preds = {"jacobian": [], "view scatter": [], "random effects": []}
    for i in np.flatnonzero(ok):
        sse = float(res.sse[i])
        jac = covariance(np.asarray(res.schur[i]), sse, n_res, g + 6 * views)
        normal = np.asarray(res.normal[i])
        preds["jacobian"].append(jac)
        preds["view scatter"].append(max(1.0, view_scatter(normal, g, sse / dof).kappa) * jac)
        preds["random effects"].append(view_effects(normal, g, sse / dof, dof).cov)
    rows = []
    for name, covs in preds.items():
        covs = np.array(covs)
        std_ratio = np.sqrt(np.mean(covs[:, range(g), range(g)], axis=0) / np.diag(mc))
        m2 = np.mean([d @ np.linalg.solve(c, d) for d, c in zip(dev, covs)]) / g
        rows.append((process, name, std_ratio, m2))
    return rows, nominal.names, int(ok.sum())


def main(draws: int = 200) -> None:
    lines = ["| views | process | covariance | predicted / MC std: fx fy cx cy k1 k2 p1 p2 k3 | mean e'C^-1e / G |",
             "|---|---|---|---|---|"]
    for views in (7, 12, 16):
        for process in ("independent", "camera jitter", "board flex"):
            rows, names, n_ok = run(process, draws, views=views)
            for p, name, ratio, m2 in rows:
                lines.append(f"| {views} | {p} | {name} | {' '.join(f'{r:.2f}' for r in ratio)} | {m2:.2f} |")
                print(lines[-1], flush=True)
    text = ("# Per-view random effects against a Monte Carlo (experiments/view_effects_mc.py)\n\n"
            f"{draws} draws per process, all views solved. 1.00 is right in both columns (the MC std's own "
            f"sampling error ~{100 / np.sqrt(2 * (draws - 1)):.0f} %; a draw's own C is an estimate, so the last "
            "column sits a little above 1 even when C is right on average).\n\n" + "\n".join(lines) + "\n")
    (Path(__file__).parent / "results" / "view_effects_mc.md").write_text(text)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 200)
