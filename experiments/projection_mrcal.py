"""dstereo's pose-compensated projection uncertainty against mrcal's, on exactly the same corners.

mrcal is NOT a dependency of dstereo or of `make test`: install it for the SYSTEM Python from Debian's packages,
    apt-get install -y mrcal python3-mrcal
and run this with the system interpreter (latest output: experiments/results/projection_mrcal.md), giving it a results folder of `dstereo calibrate` (corners.npz,
summary.json) and the venv's python to compute dstereo's side:
    /usr/bin/python3 experiments/projection_mrcal.py RESULTS_DIR [GRID_COLS GRID_ROWS]
mrcal solves from dstereo's full-set solution with outlier rejection, regularisation and board warp off
(--skip-outlier-rejection --skip-regularization --skip-calobject-warp-solve), so both fit the same least-squares
problem; then mrcal.projection_uncertainty (mean-frames, at the same distance) is compared pixel by pixel with
dstereo's map (worst-direction std). mrcal's noise estimate is sqrt(SSE / N) where dstereo's is sqrt(SSE / (N - p)),
so a ratio of sqrt((N - p) / N) (~0.97-0.99) is expected.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

LENSMODELS = {("k1", "k2", "p1", "p2", "k3"): "LENSMODEL_OPENCV5",
              ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"): "LENSMODEL_OPENCV8"}
REPO = Path(__file__).resolve().parents[1]

DSTEREO_SIDE = r"""
import json, sys, numpy as np
from dstereo.calib.mono import calibrate_full
from dstereo.uncertainty.projection import solution_map
res, gw, gh, rng = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
s = json.load(open(res + "/summary.json")); c = np.load(res + "/corners.npz")
obs = np.stack([c[n] for n in s["images"]["used"]])
full = calibrate_full(c["object_points"], obs, tuple(s["image_size"]), tuple(s["model"]))
maps = {m: solution_map(full, tuple(s["image_size"]), rng, m, grid=(gw, gh)) for m in ("pose-compensated", "intrinsics-only")}
# the same map from the Jacobian covariance alone (mrcal's premise: independent corner noise), beside the reported one,
# which carries the views' effects where the tool's test fits them
from dstereo.uncertainty.covariance import joint_covariance
from dstereo.uncertainty.projection import projection_uncertainty_map
from dstereo.uncertainty.view_scatter import inliers_of, sse_of
joint = joint_covariance(full.normal, len(full.values), sse_of(full), 2 * inliers_of(full).sum())
maps["jacobian"] = projection_uncertainty_map(full.values[:4], full.camera().coeffs(), full.names, joint, tuple(s["image_size"]),
                                              rng, (gw, gh), poses=full.poses, method="pose-compensated")
json.dump({"values": full.values.tolist(), "coeffs": full.camera().coeffs().tolist(), "poses": full.poses.tolist(),
           "rms": full.rms, "effects": maps["pose-compensated"].covariance,
           **{m: np.where(np.isfinite(p.std), p.std, -1).tolist() for m, p in maps.items()},
           "u": maps["pose-compensated"].u.tolist(), "v": maps["pose-compensated"].v.tolist()}, sys.stdout)
"""


def main(res: Path, grid=(8, 6)) -> None:
    import mrcal

    s = json.loads((res / "summary.json").read_text())
    c = np.load(res / "corners.npz")
    obj = c["object_points"]
    cols, rows = s["pattern"]["columns"], s["pattern"]["rows"]
    spacing = float(obj[1, 0] - obj[0, 0])
    obs = np.stack([c[n] for n in s["images"]["used"]])
    free = tuple(s["model"])
    if free not in LENSMODELS:
        raise SystemExit(f"model {free}: only {list(LENSMODELS)} have an mrcal equivalent here")
    poses = np.array([[0.0]])
    distance = s["projection_uncertainty"]["range"]
    out = subprocess.run([str(REPO / ".venv" / "bin" / "python"), "-c", DSTEREO_SIDE, str(res), str(grid[0]),
                          str(grid[1]), str(distance)], check=True, capture_output=True, text=True, cwd=REPO)
    d = json.loads(out.stdout)
    poses = np.array(d["poses"])
    n_coeffs = len(free)
    intrinsics = np.concatenate([d["values"][:4], np.array(d["coeffs"])[:n_coeffs]])[None]
    board = np.concatenate([obs.reshape(len(obs), rows, cols, 2), np.ones((len(obs), rows, cols, 1))], axis=-1)
    inputs = dict(
        intrinsics=intrinsics.copy(), extrinsics_rt_fromref=np.zeros((0, 6)), frames_rt_toref=poses.copy(),
        points=None, observations_board=board, observations_point=None,
        indices_frame_camintrinsics_camextrinsics=np.c_[np.arange(len(obs)), np.zeros(len(obs)),
                                                        -np.ones(len(obs))].astype(np.int32),
        indices_point_camintrinsics_camextrinsics=None, lensmodel=LENSMODELS[free],
        imagersizes=np.array([s["image_size"]], dtype=np.int32), calibration_object_spacing=spacing,
        calobject_warp=None, do_optimize_intrinsics_core=True, do_optimize_intrinsics_distortions=True,
        do_optimize_extrinsics=True, do_optimize_frames=True, do_optimize_calobject_warp=False,
        do_apply_regularization=False, do_apply_outlier_rejection=False, verbose=False)
    stats = mrcal.optimize(**inputs)
    model = mrcal.cameramodel(optimization_inputs=inputs, icam_intrinsics=0)
    print(f"{res.name}: mrcal RMS {stats['rms_reproj_error__pixels']:.6f} px vs dstereo {d['rms']:.6f}; "
          f"intrinsics max |diff| {np.max(np.abs(inputs['intrinsics'][0] - intrinsics[0])):.2e}")
    # diagnostics only: what mrcal's board-warp solve and outlier rejection find on the same corners
    extra = {**inputs, "intrinsics": inputs["intrinsics"].copy(), "frames_rt_toref": inputs["frames_rt_toref"].copy(),
             "observations_board": board.copy(), "calobject_warp": np.zeros(2), "do_optimize_calobject_warp": True,
             "do_apply_outlier_rejection": True}
    st2 = mrcal.optimize(**extra)
    n_out = int(np.sum(extra["observations_board"][..., 2] <= 0))
    print(f"  mrcal with board warp + outlier rejection: warp {extra['calobject_warp']} (board unit), "
          f"{n_out} outlier corners, RMS {st2['rms_reproj_error__pixels']:.4f} px (per coordinate; "
          f"{stats['rms_reproj_error__pixels']:.4f} without); fx cx moved by "
          f"{extra['intrinsics'][0][0] - inputs['intrinsics'][0][0]:+.3f}, {extra['intrinsics'][0][2] - inputs['intrinsics'][0][2]:+.3f} px")
    u, v = np.array(d["u"]), np.array(d["v"])
    q = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    p = mrcal.unproject(q, *model.intrinsics(), normalize=True) * distance
    var = mrcal.projection_uncertainty(p, model=model, atinfinity=False, what="covariance")
    ours = np.array(d["jacobian"]).ravel()
    reported = np.array(d["pose-compensated"]).ravel()
    mr = np.sqrt(np.linalg.eigvalsh(var)[:, -1])
    ok = ours > 0
    ratio = ours[ok] / mr[ok]
    for i in np.flatnonzero(ok)[np.abs(ratio - np.median(ratio)) > 0.01]:
        print(f"  pixel {q[i]}: dstereo {ours[i]:.4g} px, mrcal {mr[i]:.4g} px")
    centre = np.argmin(np.sum((q - np.array(s["image_size"]) / 2.0) ** 2, axis=1))
    io = np.array(d["intrinsics-only"]).ravel()
    n_obs, n_par = obs.size, len(d["values"]) + poses.size
    print(f"  noise convention sqrt(N / (N - p)) = {np.sqrt(n_obs / (n_obs - n_par)):.4f} (N {n_obs}, p {n_par})")
    rep = reported[ok] / mr[ok]
    print(f"  at {distance:.4g} {s['pattern']['unit']}: dstereo pose-compensated (Jacobian) / mrcal {ratio.min():.3f}.."
          f"{ratio.max():.3f} (median {np.median(ratio):.3f}) over {ok.sum()} pixels; centre: dstereo {ours[centre]:.4f} "
          f"px, mrcal {mr[centre]:.4f} px, dstereo intrinsics-only {io[centre]:.4f} px; the map dstereo reports "
          f"({d['effects']}) / mrcal {rep.min():.3f}..{rep.max():.3f} (median {np.median(rep):.3f})")


if __name__ == "__main__":
    main(Path(sys.argv[1]), tuple(int(a) for a in sys.argv[2:4]) if len(sys.argv) > 3 else (8, 6))
