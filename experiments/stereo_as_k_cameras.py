"""A stereo rig (`--left/--right`'s images) through the K-camera job as K = 2, against `--cameras` with the same two
folders and against today's stereo job (issue 29's acceptance: `--left/--right` equals `--cameras` to the solver's
stopping rule). On the shared real rigs rig640 and opencv_stereo, board 9x6 with unit squares, defaults otherwise.

    python -m experiments.stereo_as_k_cameras

Per rig: (1) the K = 2 job on the left/right sources (`jobs.rig_sources.stereo_pair_sources`) vs the `--cameras` job
on links cam0/<key>.jpg, cam1/<key>.jpg to the same files: max relative difference of every rig parameter and std;
(2) the K = 2 job's pair (its joint solve) vs the stereo job's stereo.yml numbers (fixed mode: intrinsics held at
each camera's final values, the sag held at the cameras' mean): rotation between the two R, |T|, fx, in the stereo
job's sigmas. Nothing is written but the links, in a temporary folder.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _links(folder: Path, root: Path) -> None:
    from dstereo.io.pairing import pair_key

    for side, label in (("left", "cam0"), ("right", "cam1")):
        (root / label).mkdir(parents=True)
        for f in sorted(folder.glob(f"{side}*.jpg")):
            (root / label / f"{pair_key(f)}.jpg").symlink_to(f.resolve())


def _rel(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(a), 1e-300))) if a.size else 0.0


def one(name: str) -> None:
    from dstereo.calib.calibrations import StereoSources
    from dstereo.config.calibration import Config
    from dstereo.jobs.calibrate_cameras import calibrate_cameras_project, calibrate_rig
    from dstereo.jobs.calibrate_stereo import calibrate_stereo_project
    from dstereo.jobs.rig_sources import stereo_pair_sources

    folder = DATA / name
    config = Config(pattern=(9, 6), square=1.0)
    left, right = tuple(sorted(folder.glob("left*.jpg"))), tuple(sorted(folder.glob("right*.jpg")))
    stereo_sources = StereoSources(left, right, left, right, f"{name} left/right")
    with tempfile.TemporaryDirectory() as tmp:
        sources, _ = stereo_pair_sources(stereo_sources, config)
        k2 = calibrate_rig(sources, config, folder)
        _links(folder, Path(tmp) / "cams")
        cams = calibrate_cameras_project(Path(tmp) / "cams", config)
    stereo = calibrate_stereo_project(stereo_sources, config)
    print(f"## {name}: {len(k2.frames)} frames (K = 2 job), {len(cams.frames)} (--cameras), "
          f"{len(stereo.detection.pairs)} pairs (stereo job)")
    print(f"K = 2 job vs --cameras: values {_rel(k2.solution.values, cams.solution.values):.3g}, std "
          f"{_rel(k2.solution.std, cams.solution.std):.3g}, pair cov {_rel(k2.pair_files[0].cov, cams.pair_files[0].cov):.3g}"
          " (max relative difference)")
    pair, (names, cov, _) = k2.pair_files[0], stereo.calibration_covariance
    std = dict(zip(names, np.sqrt(np.diag(cov))))
    angle = np.degrees((Rotation.from_matrix(stereo.R).inv() * Rotation.from_matrix(pair.R)).magnitude())
    t_s, t_k = np.linalg.norm(stereo.T), np.linalg.norm(pair.T)
    t_sigma = stereo.full_set_sigma.std["Tnorm"]
    print(f"K = 2 joint pair vs stereo job (fixed): rotation {angle:.4f} deg (RVnorm sigma "
          f"{np.degrees(stereo.full_set_sigma.std['RVnorm']):.4f} deg), |T| {t_k:.6g} vs {t_s:.6g} "
          f"({(t_k / t_s - 1) * 100:+.3f} %, {(t_k - t_s) / t_sigma:+.2f} sigma)")
    for side, c in (("left", 0), ("right", 1)):
        k_k2, k_st = np.asarray(k2.solution.cameras[c].k), np.asarray(getattr(stereo.full, side).k)
        for i, n in enumerate(("fx", "fy", "cx", "cy")):
            print(f"  {side}.{n}: {k_k2[i]:.3f} vs {k_st[i]:.3f} ({(k_k2[i] - k_st[i]) / std[f'{side}.{n}']:+.2f} "
                  "sigma)", end="" if i < 3 else "\n")
    print(f"  RMS: K = 2 joint {k2.solution.rms:.4f} px, stereo job (fixed) {stereo.full.rms:.4f} px; sag: K = 2 "
          f"{k2.solution.board_sag}, stereo job {None if stereo.rig_sag is None else stereo.rig_sag.value}")


if __name__ == "__main__":
    for rig in ("rig640", "opencv_stereo"):
        one(rig)
