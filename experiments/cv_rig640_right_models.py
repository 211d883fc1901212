"""Hypothesis (a) of experiments/cv_rig640_right.py: does a richer lens model bring rig640 R's cross-validation into
its band, and does it predict better? Each model on rig640 R and L (board sag and outlier rejection on, as the
defaults), the same 40 random halvings (seed 0) as `cross_validate` draws them (its first 4 are what
`--cross-validate 4` uses): the 4-split and 40-split geometric-mean ratios, the 40-split band if right, the pooled
ratio inside / outside the corners' field, and the parameter chi^2.

Run: .venv/bin/python -m experiments.cv_rig640_right_models   (results/cv_rig640_right_models.md; ~8 min on 2 cores)."""

from __future__ import annotations

import json
import time

import numpy as np

from experiments.cv_rig640_right import DATA, RESULTS, run_splits

MODELS = [("k1k2", ("k1", "k2")), ("k1k2p1p2", ("k1", "k2", "p1", "p2")), ("default", ("k1", "k2", "p1", "p2", "k3")),
          ("fisheye", ("fk1", "fk2", "fk3", "fk4"))]
SPLITS = 40


def main() -> None:
    from dstereo.config.calibration import Config
    from dstereo.errors import DstereoError
    from dstereo.jobs.calibrate_camera import calibrate_camera
    from dstereo.uncertainty.projection import mean_board_distance
    from dstereo.uncertainty.view_scatter import solution_view_scatter

    rows, data = [], []
    for label, glob in (("rig640 R", "right*.jpg"), ("rig640 L", "left*.jpg")):
        for preset, model in MODELS:
            t0 = time.perf_counter()
            cal = calibrate_camera(DATA / "rig640", Config(pattern=(9, 6), square=10.0, unit="mm", glob=glob,
                                                           model=model))
            full, obj, obs = cal.full, cal.detection.object_points, cal.observations
            rng = np.random.default_rng(0)
            halves = []
            for _ in range(SPLITS):
                p = rng.permutation(len(obs))
                halves.append((np.sort(p[: len(obs) // 2]), np.sort(p[len(obs) // 2:])))
            try:
                x = run_splits(full, obj, obs, cal.detection.image_size, halves,
                               mean_board_distance(full.poses, obj))
            except DstereoError as e:
                rows.append(f"| {label} | {preset} | {full.rms:.4f} | - | {e} | | | |")
                continue
            c = x.splits[0].covered
            r4 = float(np.exp(np.mean(np.log([s.ratio for s in x.splits[:4]]))))
            d = {"camera": label, "model": preset, "rms": float(full.rms),
                 "kappa": float(solution_view_scatter(full).kappa), "ratio_4": r4, "ratio_40": x.ratio,
                 "band_40": list(x.band.ratio), "inside": x._pooled(c), "outside": x._pooled(~c),
                 "parameter_chi2": x.parameter_chi2, "seconds": time.perf_counter() - t0}
            data.append(d)
            rows.append(f"| {label} | {preset} | {d['rms']:.4f} | {d['kappa']:.2f} | {r4:.2f} | {x.ratio:.2f} "
                        f"({x.band.ratio[0]:.2f}-{x.band.ratio[1]:.2f}) | {d['inside']:.2f} / {d['outside']:.2f} | "
                        f"{x.parameter_chi2:.2f} |")
            print(rows[-1], flush=True)
    text = ("# rig640: the cross-validation against the lens model (experiments/cv_rig640_right_models.py)\n\n"
            + __doc__.split("\n\n")[0] + "\n\n| camera | model | RMS px | kappa | ratio, first 4 splits | ratio, 40 "
            "splits (band if right) | pooled ratio inside / outside the corners' field | parameter d'C^-1d/G |\n"
            "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
    (RESULTS / "cv_rig640_right_models.md").write_text(text)
    (RESULTS / "cv_rig640_right_models.json").write_text(json.dumps(data, indent=1))
    print(text)


if __name__ == "__main__":
    main()
