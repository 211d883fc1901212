"""Issue 30: the disparity search range on rig640's 25 pairs, with the dstereo in --src (default: this checkout).

For each pair: the first range (sparse matches), the range kept, its valid share (of the rectified pixels with a
source in both images) and the share of the valid pixels behind infinity (sign-normalised d_s < d_inf = -Q33/|Q32|:
no scene point can be there), and whether the pair carries a search-range warning. `--src` points at another
dstereo tree (e.g. `git archive main dstereo | tar -x -C /tmp/main`) to measure it the same way; the table is
printed as markdown.

    python -m experiments.range_bounds_rig640 [--src DIR]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rig640"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--src", type=Path, default=None, help="folder holding the dstereo package to measure")
    args = parser.parse_args()
    if args.src is not None:
        sys.path.insert(0, str(args.src.resolve()))
    import cv2

    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.stereo.reconstruct import ReconstructionConfig, match_in_range, rectifying_maps
    from dstereo.io.images import read_image

    calib = read_stereo_calibration(DATA / "intrinsics.yml")
    maps = rectifying_maps(calib, (640, 512))
    Q = np.asarray(maps.rect.Q)
    d_inf = -Q[3, 3] / abs(Q[3, 2])
    usable = ~maps.outside
    print(f"infinity at {d_inf:.2f} px (sign-normalised)\n")
    print("| pair | first range px | kept range px | valid % | valid behind infinity % | warnings |")
    print("|---|---|---|---|---|---|")
    shares = []
    for left in sorted(DATA.glob("left*.jpg")):
        name = left.stem[4:]
        rect = [cv2.remap(read_image(p), mx, my, cv2.INTER_LINEAR)
                for p, (mx, my) in zip((left, DATA / f"right{name}.jpg"), maps.remap)]
        d, _, s, warnings = match_in_range(name, *rect, ReconstructionConfig(), Q, maps.outside, calib)
        d_s = np.sign(Q[3, 2]) * d[usable]
        valid = d_s[np.isfinite(d_s)]
        first = s["tries"][0]
        shares.append(valid.size / usable.sum())
        print(f"| {name} | {first['min_disparity']}..{first['max_disparity']} | {s['min_disparity']}.."
              f"{s['max_disparity']} | {100 * shares[-1]:.1f} | {100 * np.mean(valid < d_inf):.2f} | {len(warnings)} |")
    print(f"\nvalid share: mean {100 * np.mean(shares):.1f} %, {100 * min(shares):.1f}..{100 * max(shares):.1f} %")


if __name__ == "__main__":
    main()
