"""A stereo rig (`--left/--right`'s images, the K-camera job with K = 2) against `--cameras` with the same two folders
(issue 29's acceptance: `--left/--right` equals `--cameras` to the solver's stopping rule). On the shared real rigs
rig640 and opencv_stereo, board 9x6 with unit squares, defaults otherwise.

    python -m experiments.stereo_as_k_cameras

Per rig: `calibrate_stereo_project` on the left/right files vs the `--cameras` job on links cam0/<key>.jpg,
cam1/<key>.jpg to the same files: max relative difference of every rig parameter, std and the pair covariance; the
pair's rotation angle, |T| and RMS. Nothing is written but the links, in a temporary folder. (Before issue 29's
switch this also compared the fixed-mode stereo job: rig640 joint vs fixed 0.072 deg, |T| -0.33 %.)
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
    from dstereo.jobs.calibrate_cameras import calibrate_cameras_project
    from dstereo.jobs.calibrate_stereo import calibrate_stereo_project

    folder = DATA / name
    config = Config(pattern=(9, 6), square=1.0)
    left, right = tuple(sorted(folder.glob("left*.jpg"))), tuple(sorted(folder.glob("right*.jpg")))
    stereo = calibrate_stereo_project(StereoSources(left, right, left, right, f"{name} left/right"), config)
    with tempfile.TemporaryDirectory() as tmp:
        _links(folder, Path(tmp) / "cams")
        cams = calibrate_cameras_project(Path(tmp) / "cams", config)
    print(f"## {name}: {len(stereo.frames)} frames (--left/--right), {len(cams.frames)} (--cameras)")
    a, b = stereo.solution, cams.solution
    print(f"--left/--right vs --cameras: values {_rel(a.values, b.values):.3g}, std {_rel(a.std, b.std):.3g}, pair "
          f"cov {_rel(stereo.pair_files[0].cov, cams.pair_files[0].cov):.3g} (max relative difference)")
    pair = stereo.pair_files[0]
    angle = np.degrees(Rotation.from_matrix(pair.R).magnitude())
    print(f"  rotation {angle:.4f} deg, |T| {np.linalg.norm(pair.T):.6g}, RMS {a.rms:.4f} px, sag {a.board_sag}")


if __name__ == "__main__":
    for rig in ("rig640", "opencv_stereo"):
        one(rig)
