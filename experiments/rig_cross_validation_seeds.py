"""Issue 29 item 3: the rig cross-validation (calib/rig_cross_validation.py) on exact corners with noise.

K = 2 and 3 ring rigs (`synth/rig_corners.py`, 32 frames, 0.1 px), 8 seeds, 6 splits: the statistics and whether
they read inside the band a right +- reads; then the same rigs with the board moved 0.3 mm between exposures.
Writes results/rig_cross_validation.json.

With `--sag`: the acceptance's rigs instead (K = 2, 3, 4, a board sagging 0.3 mm solved with the rest, the
simultaneous exposures only); writes results/rig_cross_validation_sag.json.

    .venv/bin/python experiments/rig_cross_validation_seeds.py [SEEDS] [--sag]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


from dstereo.calib.multiview import cameras_alone
from dstereo.calib.rig_cross_validation import cross_validate_rig
from dstereo.synth.rig_corners import rig_corners

SAG = (0.3, 0.0)


def run(k: int, seed: int, shift: float = 0.0, sag: bool = False):
    case = rig_corners(k, 32, seed, 0.1, shift_mm=shift, sag_mm=SAG if sag else None)
    cams = cameras_alone(case["obj"], case["obs"], case["visible"], case["image_sizes"])[0]
    return cross_validate_rig(case["obj"], case["obs"], case["visible"], case["image_sizes"], cams,
                              tuple(f"cam{c}" for c in range(k)), 6, seed=seed, board_warp=sag)


def main(seeds: int = 8, sag: bool = False) -> None:
    rows = []
    for k in ((2, 3, 4) if sag else (2, 3)):
        for shift in ((0.0,) if sag else (0.0, 0.3)):
            for seed in range(seeds):
                cv = run(k, seed, shift, sag)
                rows.append({"cameras": k, "shift_mm": shift, "sag_mm": SAG[0] if sag else 0.0, "seed": seed,
                             "rig_ratio": cv.rig_ratio, "intrinsics_ratio": cv.intrinsics_ratio,
                             "trusted": cv.trusted, "rig_band": cv.band(cv.rig_dof),
                             "intrinsics_band": cv.band(cv.intrinsics_dof)})
                print(f"K={k} shift {shift} seed {seed}: {cv.line()} trusted {cv.trusted}", flush=True)
    out = Path(__file__).parent / "results" / ("rig_cross_validation_sag.json" if sag else "rig_cross_validation.json")
    out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--sag"]
    main(int(args[0]) if args else 8, "--sag" in sys.argv[1:])
