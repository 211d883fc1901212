"""`--model auto` on the real cameras: the candidates' table and the choice, against OpenCV's own calibrations.

For each camera (fisheye640; opencv_stereo left; rig640 left; square = 1, dstereo's corners):
- `dstereo.calib.model_choice.choose_model`: every candidate's full-set RMS, its leave-one-view-out held-out RMS
  (pose refitted per held-out view for the fold's fixed camera), identifiability, the choice;
- OpenCV on the same corners, tight criteria: cv2.calibrateCamera (rational) and cv2.fisheye.calibrate (or its
  error message); the acceptance is chosen RMS <= 1.01 x the best of the two.

`python -m experiments.model_auto`; writes experiments/results/model_auto.{md,json}. ~1-2 min on one core.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from experiments import _uncertainty_common as uc

OUT = Path(__file__).resolve().parent / "results"
CAMERAS = (("fisheye640", None), ("opencv_stereo", "left"), ("rig640", "left"))


def _views(name, side):
    from dstereo.io.corners import detect_folder

    if side is not None:
        return uc.real_views(name, side)[:3]
    det = detect_folder(uc.DATA / name, (9, 6), 1.0)
    used = [n for n in det.names if n in det.corners]
    return det.object_points, np.stack([det.corners[n] for n in used]), det.image_size


def _opencv(obj, obs, size) -> dict:
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    o32, q32 = [obj.astype(np.float32)] * len(obs), [q.astype(np.float32) for q in obs]
    out = {"rational": float(cv2.calibrateCamera(o32, q32, size, None, None, flags=cv2.CALIB_RATIONAL_MODEL,
                                                 criteria=crit)[0])}
    try:
        out["fisheye"] = float(cv2.fisheye.calibrate([obj[None]] * len(obs), [q[None] for q in obs], size, None, None,
                                                     flags=cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW,
                                                     criteria=crit)[0])
    except cv2.error as exc:
        out["fisheye"] = float("nan")
        out["fisheye_error"] = " ".join(str(exc).split())[-120:]
    return out


def main() -> dict:
    from dstereo.calib.model_choice import choose_model

    rows, md = [], ["# `--model auto` on the real cameras (dstereo's corners, square = 1)", ""]
    for name, side in CAMERAS:
        obj, obs, size = _views(name, side)
        t0 = time.perf_counter()
        choice = choose_model(obj, obs, size)
        seconds = time.perf_counter() - t0
        cv = _opencv(obj, obs, size)
        best_cv = np.nanmin([cv["rational"], cv["fisheye"]])
        chosen = choice.chosen_candidate
        ok = chosen.rms <= 1.01 * best_cv
        rows.append({"camera": f"{name} {side or ''}".strip(), "views": int(len(obs)), **choice.as_dict(),
                     "opencv_rms": cv, "chosen_rms": chosen.rms, "acceptance_ok": bool(ok), "seconds": seconds})
        md += [f"## {name} {side or ''} ({len(obs)} views, {size[0]} x {size[1]})", "", *choice.table_markdown(), "",
               f"OpenCV on the same corners: rational RMS {cv['rational']:.4f} px, fisheye RMS "
               + (f"{cv['fisheye']:.4f} px" if np.isfinite(cv["fisheye"]) else f"failed ({cv.get('fisheye_error')})")
               + f". Chosen {choice.chosen}: RMS {chosen.rms:.4f} px = {chosen.rms / best_cv:.4f} x OpenCV's best "
               f"({'within' if ok else 'NOT within'} 1 %); held-out {chosen.heldout_rms:.4f} px. "
               f"Model choice took {seconds:.0f} s.", ""]
        print(md[-2])
    md += ["Rule: " + choice.rule + "."]
    OUT.mkdir(exist_ok=True)
    (OUT / "model_auto.json").write_text(json.dumps(rows, indent=1, default=float))
    (OUT / "model_auto.md").write_text("\n".join(md) + "\n")
    return {"rows": rows}


if __name__ == "__main__":
    main()
