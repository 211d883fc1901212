"""Why does rig640 R's cross-validation read optimistic (issue 32, item 3)? Each hypothesis, measured.

For each camera (rig640 R, the suspect; rig640 L and opencv_stereo L as controls) the pipeline of `dstereo calibrate`
(defaults: k1,k2,p1,p2,k3, board sag, outlier rejection) is run in-process, then:

(e) many random splits: the per-split ratios of 40 random halvings, their geometric mean and the band a right
    prediction reads over 40 splits; and the spread of a 4-split geometric mean drawn from those 40 (is the 4-split
    1.66 within the statistic's own sampling spread?);
(f) frame order: the halves split by frame order (first half / second half of the file names) against interleaved
    (odd / even) and random halvings; a camera whose intrinsics drift with frame order (focus, zoom, a knock) reads
    a large ratio on the first and not on the second; plus windows of 8 consecutive frames, each calibrated: fx,
    cx, cy, k1 against their +-;
(d) the halves' own view effects: each half fits its per-view effects (omega, tau) on its 12-13 views; the same
    splits with the full set's effects (fitted on all 25 views) applied to each half's views instead;
(c) per-view chi^2 of the profiled score under the full set's claimed per-view covariance (one bad view stands
    out), and per-view residual RMS;
(b) the board's sag and its +-.

Run: .venv/bin/python -m experiments.cv_rig640_right [--quick]   (results/cv_rig640_right.md and .json)."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
RESULTS = Path(__file__).resolve().parent / "results"
SETS = [("rig640 R", "rig640", "right*.jpg"), ("rig640 L", "rig640", "left*.jpg"),
        ("opencv_stereo L", "opencv_stereo", "left*.jpg")]
MANY = 40


def calibrate(folder: str, glob: str):
    from dstereo.config.calibration import Config
    from dstereo.jobs.calibrate_camera import calibrate_camera

    cfg = Config(pattern=(9, 6), square=10.0, unit="mm", glob=glob)
    return calibrate_camera(DATA / folder, cfg)


def run_splits(full, obj, obs, size, halves, range_, effects_from=None):
    """`cross_validate` on the given halves (list of (a, b) index arrays); `effects_from`: a full-set ViewEffects
    whose omega and tau replace each half's own."""
    from dstereo.calib import cross_validation as cv

    original = cv.view_effects
    if effects_from is not None:
        def patched(normal, g, sigma2, dof, weight=None):
            e = original(normal, g, sigma2, dof, weight)
            from dstereo.uncertainty.covariance import scaled_inverse

            s_inv = scaled_inverse(e.s_views.sum(axis=0))
            omega, tau = effects_from.omega, effects_from.tau
            s2 = effects_from.sigma2
            extra = np.einsum("vik,vjk->ij", e.s_views * omega, e.s_views)
            cov = (s2 + tau) * s_inv + s_inv @ extra @ s_inv
            return dataclasses.replace(e, omega=omega, tau=tau, sigma2=s2, cov=cov, fitted=True)
        cv.view_effects = patched
    try:
        weights = []
        for a, b in halves:
            for part in (a, b):
                w = np.zeros(len(obs))
                w[part] = 1.0
                weights.append(w)
        sols = cv.solve_halves(full, obj, obs, np.array(weights))
    finally:
        cv.view_effects = original
    names = cv._lens_names(full)
    corners = np.asarray(obs, float).reshape(-1, 2)
    res = [cv.compare_halves(sols[2 * i], sols[2 * i + 1], names, size, range_, corners=corners)
           for i in range(len(halves))]
    band = cv.band_if_right(halves, sols, res)
    x = cv.CrossValidation(res, range_, halves, np.zeros(2), np.zeros(2), [s.std_ratio for s in sols], band, sols,
                           names, tuple(size))
    return x


def summary_of(x) -> dict:
    return {"ratio": x.ratio, "ratios": [s.ratio for s in x.splits], "mahalanobis": x.mahalanobis_median,
            "parameter_chi2": x.parameter_chi2, "band": None if x.band is None else list(x.band.ratio),
            "std_ratios": x.std_ratios}


def windows(full, obj, obs, names_img, width=8):
    """Each window of `width` consecutive frames calibrated alone: its lens values and their +-."""
    from dstereo.calib import cross_validation as cv

    starts = list(range(0, len(obs) - width + 1, 2))
    weights = []
    for s in starts:
        w = np.zeros(len(obs))
        w[s: s + width] = 1.0
        weights.append(w)
    sols = cv.solve_halves(full, obj, obs, np.array(weights))
    lens = cv._lens_names(full)
    rows = []
    for s, h in zip(starts, sols):
        std = np.sqrt(np.diag(h.cov))
        rows.append({"frames": f"{names_img[s]}..{names_img[s + width - 1]}",
                     **{n: [float(h.values[i]), float(std[i])] for i, n in enumerate(lens)}})
    return rows


def per_view(full):
    """Per used view: residual RMS (px) and chi^2 / G of its profiled score under the full set's claimed per-view
    score covariance (the effects' E[s_v s_v'], `view_effects._expected`): about 1 for every view if the model
    holds; one bad view stands out."""
    from dstereo.uncertainty.covariance import scaled_inverse
    from dstereo.uncertainty.view_effects import _expected, solution_effects
    from dstereo.uncertainty.view_scatter import inliers_of, profiled

    e = solution_effects(full)
    g = len(full.values)
    s_views, scores = profiled(np.asarray(full.normal), g, e.views)
    s_inv = scaled_inverse(s_views.sum(axis=0))
    q = (e.sigma2 + e.tau) * s_views + np.einsum("vik,vjk->vij", s_views * e.omega, s_views)
    expected = _expected(q, s_views, s_inv)
    chi2 = [float(s @ np.linalg.pinv(c, rcond=1e-10, hermitian=True) @ s) / g for s, c in zip(scores, expected)]
    inl = inliers_of(full)[:, 0]
    r = np.asarray(full.residuals[:, 0], float)
    rms = [float(np.sqrt(np.sum(r[v][inl[v]] ** 2) / max(inl[v].sum(), 1))) for v in range(len(r))]
    return chi2, rms


def camera(label, folder, glob, quick=False) -> dict:
    from dstereo.uncertainty.projection import mean_board_distance
    from dstereo.uncertainty.view_effects import solution_effects
    from dstereo.uncertainty.view_scatter import solution_view_scatter

    t0 = time.perf_counter()
    cal = calibrate(folder, glob)
    full, obs, obj, size = cal.full, cal.observations, cal.detection.object_points, cal.detection.image_size
    used = list(cal.used)
    range_ = mean_board_distance(full.poses, obj)
    n = len(obs)
    out = {"label": label, "views": n, "rms": float(full.rms)}
    eff = solution_effects(full)
    vs = solution_view_scatter(full)
    out["kappa"] = [float(vs.kappa), float(vs.standard_error)]
    out["effects"] = eff.summary(full.names)
    names = list(full.names)
    if "board_sag_x" in names:
        std = np.sqrt(np.diag(eff.cov))
        out["sag"] = {k: [float(full.values[names.index(k)]), float(std[names.index(k)])]
                      for k in ("board_sag_x", "board_sag_y")}
    rng = np.random.default_rng(0)
    many = MANY // 4 if quick else MANY
    rand = []
    for _ in range(many):
        p = rng.permutation(n)
        rand.append((np.sort(p[: n // 2]), np.sort(p[n // 2:])))
    x = run_splits(full, obj, obs, size, rand, range_)
    out["random"] = summary_of(x)
    out["random"]["diagnosis"] = x.diagnosis()  # pooled inside / outside the corners' field, per-parameter excess
    lr = np.log(out["random"]["ratios"])
    g4 = np.exp([np.mean(rng.choice(lr, 4, replace=False)) for _ in range(2000)])
    out["random"]["four_split_gm_5_95"] = list(map(float, np.percentile(g4, [5, 95])))
    # (d) the same splits with the full set's effects on each half's views
    out["random_full_effects"] = summary_of(run_splits(full, obj, obs, size, rand, range_, effects_from=eff))
    # (f) frame order
    idx = np.arange(n)
    order = {"first/second": (idx[: n // 2], idx[n // 2:]), "odd/even": (idx[::2], idx[1::2]),
             "first+last quarters / middle": (np.r_[idx[: n // 4], idx[n - n // 4:]], idx[n // 4: n - n // 4])}
    out["order"] = {}
    for k, (a, b) in order.items():
        y = run_splits(full, obj, obs, size, [(a, b)], range_)
        out["order"][k] = summary_of(y)
    out["windows"] = windows(full, obj, obs, used)
    chi2, rms = per_view(full)
    out["per_view"] = [{"view": u, "score_chi2_per_g": c, "rms_px": r} for u, c, r in zip(used, chi2, rms)]
    out["seconds"] = time.perf_counter() - t0
    return out


def table(data) -> str:
    lines = ["| camera | views | RMS px | kappa (1 +- se) | board sag x, y (+-) | "
             f"{MANY} random splits: ratio (band if right) | a 4-split geometric mean, 5-95 % over draws of 4 of them "
             "| the same splits, each half with the full set's view effects: ratio (band) | split by frame order: "
             "first/second | odd/even | quarters / middle |", "|---|" * 1 + "---|" * 10]
    for c in data:
        r, f = c["random"], c["random_full_effects"]
        sag = c.get("sag")
        sag_t = "-" if sag is None else ", ".join(f"{v[0]:.3f} ({v[1]:.3f})" for v in sag.values())
        o = c["order"]
        fmt = lambda s: f"{s['ratio']:.2f} ({s['band'][0]:.2f}-{s['band'][1]:.2f})"  # noqa: E731
        lines.append(f"| {c['label']} | {c['views']} | {c['rms']:.4f} | {c['kappa'][0]:.2f} (1 +- {c['kappa'][1]:.2f}) "
                     f"| {sag_t} | {fmt(r)} | {r['four_split_gm_5_95'][0]:.2f}-{r['four_split_gm_5_95'][1]:.2f} | "
                     f"{fmt(f)} | {fmt(o['first/second'])} | {fmt(o['odd/even'])} | "
                     f"{fmt(o['first+last quarters / middle'])} |")
    text = "\n".join(lines) + "\n"
    for c in data:
        pv = sorted(c["per_view"], key=lambda p: -p["score_chi2_per_g"])
        text += (f"\n{c['label']}: per-view score chi^2/G (1 if the claimed per-view covariance holds), worst five: "
                 + ", ".join(f"{p['view']} {p['score_chi2_per_g']:.2f} ({p['rms_px']:.3f} px)" for p in pv[:5])
                 + f"; median {np.median([p['score_chi2_per_g'] for p in pv]):.2f}; per-view RMS "
                 f"{min(p['rms_px'] for p in pv):.3f}-{max(p['rms_px'] for p in pv):.3f} px\n")
        dg = c["random"]["diagnosis"]
        text += (f"{c['label']}: {MANY} random splits pooled inside the corners' field "
                 f"{dg['ratio_pooled_inside_corner_field']:.2f}, outside {dg['ratio_pooled_outside_corner_field']:.2f}; "
                 "each lens parameter's squared difference / predicted variance, mean over splits (1 if right): "
                 + ", ".join(f"{k} {v:.2f}" for k, v in dg["parameter_variance_ratio"].items()) + "\n")
        text += f"{c['label']}: per-split ratios (random): " + ", ".join(f"{v:.2f}" for v in c["random"]["ratios"]) + "\n"
        keys = [k for k in c["windows"][0] if k not in ("frames",) and not k.startswith("board")][:9]
        text += f"\n{c['label']}: windows of 8 consecutive frames (value +- std)\n\n| frames | " + " | ".join(keys) + \
            " |\n|---|" + "---|" * len(keys) + "\n"
        for w in c["windows"]:
            text += f"| {w['frames']} | " + " | ".join(f"{w[k][0]:.4g} +- {w[k][1]:.2g}" for k in keys) + " |\n"
    return text


def main(quick: bool = False) -> None:
    data = []
    for s in SETS:
        data.append(camera(*s, quick=quick))
        print(table(data[-1:]), flush=True)
    text = "# rig640 R's optimistic cross-validation: the hypotheses measured (experiments/cv_rig640_right.py)\n\n" + \
        __doc__.split("\n\n")[1] + "\n\n" + table(data)
    (RESULTS / "cv_rig640_right.md").write_text(text)
    (RESULTS / "cv_rig640_right.json").write_text(json.dumps(data, indent=1))


if __name__ == "__main__":
    main("--quick" in sys.argv)
