"""Issue 29 item 3: the rig-consistency test's false-alarm rate and power on rendered-truth corners.

K = 2, 3, 4 ring rigs (`synth/rig_corners.py`), 24 frames, 0.1 px noise; each camera calibrated alone on its own
views (as `--cameras` does), the rig solved jointly from there, then `calib/rig_consistency.py`. Simultaneous frames
against a board moved SHIFT mm between the reference's exposure and the others'. Writes results/rig_consistency.json.

    .venv/bin/python -m experiments.rig_consistency_seeds [SEEDS] [--check]

--check (`make bench-check`): the 20 seeds again, compared with docs/validation.md's table (nothing written).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from dstereo.calib.multiview import calibrate_views, cameras_alone
from dstereo.calib.rig_consistency import of_multiview
from dstereo.synth.rig_corners import rig_corners

SHIFTS = (0.0, 0.5)


def consistency(case: dict):
    obj, obs, visible = case["obj"], case["obs"], case["visible"]
    cams = cameras_alone(obj, obs, visible, case["image_sizes"])[0]
    joint = calibrate_views(obj, obs, visible, case["image_sizes"], mode="joint", cameras=cams)
    return of_multiview(joint, obj, obs)


def check(rows: list[dict]) -> bool:
    """Flag counts and T/c against docs/validation.md's rig-consistency table (its columns by name)."""
    from experiments._validation import compare, table

    ok = []
    for doc in table("| cameras | simultaneous: flagged"):
        k = int(doc["cameras"])
        still = [r for r in rows if r["cameras"] == k and r["shift_mm"] == 0.0]
        moved = [r for r in rows if r["cameras"] == k and r["shift_mm"] == SHIFTS[1]]
        for col, group in (("simultaneous: flagged", still),
                           (f"board moved {SHIFTS[1]} mm between exposures: flagged", moved)):
            flagged, of = (int(v) for v in doc[col].split("/"))
            ok.append(compare(f"K={k} {col}", sum(r["flagged"] for r in group), str(flagged)) and of == len(group))
        ok.append(compare(f"K={k} mean T/c", float(np.mean([r["ratio"] for r in still])), doc["mean T/c"]))
        ok.append(compare(f"K={k} min T/c (moved)", float(np.min([r["ratio"] for r in moved])), doc["min T/c"]))
    print(f"rig_consistency_seeds --check: {sum(ok)} of {len(ok)} figures as documented", flush=True)
    return bool(ok) and all(ok)


def main(seeds: int = 20, check_only: bool = False) -> None:
    rows = []
    for k in (2, 3, 4):
        for shift in SHIFTS:
            for seed in range(seeds):
                t0 = time.perf_counter()
                r = consistency(rig_corners(k, 24, seed, 0.1, shift))
                rows.append({"cameras": k, "shift_mm": shift, "seed": seed, "ratio": r.ratio, "dof": r.dof,
                             "p_value": r.p_value, "flagged": not r.consistent,
                             "rms_alone": r.rms_alone.tolist(), "rms_rig": r.rms_rig.tolist(),
                             "seconds": time.perf_counter() - t0})
                print(f"K={k} shift {shift} seed {seed}: T/c {r.ratio:.3f} (c {r.dof}) p {r.p_value:.3g}", flush=True)
    summary = {f"K{k}_shift{s}": {"flagged": sum(r["flagged"] for r in rows if r["cameras"] == k and r["shift_mm"] == s),
                                   "of": sum(1 for r in rows if r["cameras"] == k and r["shift_mm"] == s),
                                   "ratio_mean": float(np.mean([r["ratio"] for r in rows
                                                                if r["cameras"] == k and r["shift_mm"] == s]))}
               for k in (2, 3, 4) for s in SHIFTS}
    if check_only:
        raise SystemExit(0 if check(rows) else 1)
    print(json.dumps(summary, indent=1))
    out = Path(__file__).parent / "results" / "rig_consistency.json"
    out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--check"]
    main(int(args[0]) if args else 20, check_only="--check" in sys.argv[1:])
