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

from dstereo.synth.board_views import PROCESSES, view_effects_monte_carlo as run


def main(draws: int = 200) -> None:
    lines = ["| views | process | covariance | predicted / MC std: fx fy cx cy k1 k2 p1 p2 k3 | mean e'C^-1e / G |",
             "|---|---|---|---|---|"]
    for views in (7, 12, 16):
        for process in PROCESSES:
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
