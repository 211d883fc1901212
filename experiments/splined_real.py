"""`--model auto` with the splined candidate on the real cameras: the held-out table, and the chosen model's
residual against OpenCV's best model on the same corners.

For each camera (fisheye640; opencv_stereo left; rig640 left; square = 1, dstereo's corners), as
experiments/model_auto.py but with `model_choice.CANDIDATES` now including `splined` (models/splined.py, its
default 10 x 8 grid): every candidate's full-set RMS, leave-one-view-out held-out RMS, identifiability, the choice;
OpenCV's cv2.calibrateCamera (rational) and cv2.fisheye.calibrate on the same corners; the acceptance is chosen
RMS <= OpenCV's best (and, as model_auto.py states it, <= 1.01 x).

`python -m experiments.splined_real`; writes experiments/results/splined_real.{md,json}. Several minutes (the
splined candidate's folds are ~15-25 solves of 170 shared parameters).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from experiments.model_auto import CAMERAS, _opencv, _views

OUT = Path(__file__).resolve().parent / "results"


def main() -> dict:
    from dstereo.calib.model_choice import CANDIDATES, choose_model

    rows, md = [], ["# `--model auto` with the splined candidate on the real cameras (dstereo's corners, square = 1)",
                    "", f"Candidates: {', '.join(CANDIDATES)}. Load at the start: {os.getloadavg()[0]:.1f} "
                    "(2 cores shared by several jobs: timings are only indicative).", ""]
    for name, side in CAMERAS:
        obj, obs, size = _views(name, side)
        t0 = time.perf_counter()
        choice = choose_model(obj, obs, size)
        seconds = time.perf_counter() - t0
        cv = _opencv(obj, obs, size)
        best_cv = np.nanmin([cv["rational"], cv["fisheye"]])
        chosen = choice.chosen_candidate
        splined = next(c for c in choice.candidates if c.preset == "splined")
        ok = chosen.rms <= best_cv
        rows.append({"camera": f"{name} {side or ''}".strip(), "views": int(len(obs)), **choice.as_dict(),
                     "opencv_rms": cv, "chosen_rms": chosen.rms, "chosen_not_above_opencv": bool(ok),
                     "splined_rms": splined.rms, "splined_heldout_rms": splined.heldout_rms, "seconds": seconds})
        md += [f"## {name} {side or ''} ({len(obs)} views, {size[0]} x {size[1]})", "", *choice.table_markdown(), "",
               f"OpenCV on the same corners: rational RMS {cv['rational']:.4f} px, fisheye RMS "
               + (f"{cv['fisheye']:.4f} px" if np.isfinite(cv["fisheye"]) else f"failed ({cv.get('fisheye_error')})")
               + f". Chosen {choice.chosen}: RMS {chosen.rms:.4f} px = {chosen.rms / best_cv:.4f} x OpenCV's best "
               f"({'not above' if ok else 'ABOVE'} it); held-out {chosen.heldout_rms:.4f} px. Splined: RMS "
               f"{splined.rms:.4f} px, held-out {splined.heldout_rms:.4f} px. Model choice took {seconds:.0f} s.", ""]
        print(md[-2], flush=True)
    md += ["Rule: " + choice.rule + "."]
    OUT.mkdir(exist_ok=True)
    (OUT / "splined_real.json").write_text(json.dumps(rows, indent=1, default=float))
    (OUT / "splined_real.md").write_text("\n".join(md) + "\n")
    return {"rows": rows}


if __name__ == "__main__":
    main()
