"""(a) Jacobian standard deviations vs subset spread vs Monte Carlo over re-rendered sensor noise, with the truth.

A synthetic 640 x 480 camera (fx 820, fy 818, cx 322, cy 236, k1 -0.25, k2 0.12; model k1, k2 fitted, so the
model is right) sees a 9x6 board (20 mm squares) at 20 poses from `dstereo.synth`'s pose generator. Each view's
radiance is rendered once; every Monte Carlo draw exposes it again with fresh sensor noise (shot noise, 1000 e- at
white, 2 DN read noise, 1 px lens blur, 8-bit) and re-detects the corners with the project's detector
(findChessboardCorners + cornerSubPix), so the draws include the detector. For N = 10, 15, 20 (the first N views):

- (i) the Jacobian standard deviation sigma sqrt(diag (J'J)^-1) of the full-set solve (mean over draws);
- (ii) the raw spread (std) of the estimates over C(N, m) subsets (all, or a seeded sample of `--cap`), and the
  delete-d jackknife rescaling sqrt(m / (N - m)) * spread, on the first `--subset-draws` draws;
- (iii) the Monte Carlo std of the full-set estimate over the draws;
- the bias of the full-set estimate against the truth, and the share of draws whose truth lies within 1.96
  Jacobian sigma; the detector's corner error against the true projections (fixed part and noise part).

`python -m experiments.uncertainty_mc [--quick]`; writes experiments/results/figures/uncertainty_mc.{md,json,png}.
"""

from __future__ import annotations

import argparse
import time

from experiments import _uncertainty_common as uc

import numpy as np  # noqa: E402

FREE = ("k1", "k2")


def configs(n_list):
    return [(n, m) for n in n_list for m in (n // 2, n - 3)]


def run(n_list=(10, 15, 20), draws=100, subset_draws=20, cap=128, progress=print) -> dict:
    from dstereo.calib import mono
    from dstereo.calib.subsets import plan_subsets

    t0 = time.perf_counter()
    cam = uc.truth_camera()
    truth = np.asarray(cam.free_vector())
    views = uc.render_views(cam, max(n_list), seed=0)
    size = cam.image_size
    t_render = time.perf_counter() - t0
    full = {n: {"values": [], "std": [], "rms": [], "status": []} for n in n_list}
    sub = {(n, m): {"raw": [], "jack": [], "pred": [], "converged": [], "total": 0} for n, m in configs(n_list)}
    errors, failed = [], 0
    t_detect = t_solve = 0.0
    clean = views.detect_clean()
    clean_bias = {n: mono.calibrate_full(views.obj, clean[:n], size, FREE).values - truth for n in n_list}
    for d in range(draws):
        t1 = time.perf_counter()
        obs, missed = views.draw(d)
        t_detect += time.perf_counter() - t1
        if obs is None:
            failed += 1
            continue
        errors.append(obs - views.truth)
        t1 = time.perf_counter()
        for n in n_list:
            sol = mono.calibrate_full(views.obj, obs[:n], size, FREE)
            f = full[n]
            f["values"].append(sol.values)
            f["std"].append(sol.std)
            f["rms"].append(sol.rms)
            f["status"].append(sol.status)
            if len(f["values"]) > subset_draws:
                continue
            for m in (n // 2, n - 3):
                plan = plan_subsets(n, m, cap=cap, seed=d)
                s = uc.solve_subsets_safe(mono.solve_subsets, views.obj, obs[:n], plan, sol)
                ok = s.converged
                raw = uc.spread(s.values[ok])
                rec = sub[(n, m)]
                rec["raw"].append(raw)
                rec["jack"].append(uc.jackknife_factor(n, m) * raw)
                # linear-model prediction of the raw spread from the subsets' own Jacobians (as tests/test_stereo.py's)
                rec["pred"].append(np.sqrt(np.maximum(np.mean(s.std[ok] ** 2, axis=0) - sol.std ** 2, 0.0)))
                rec["converged"].append(int(ok.sum()))
                rec["total"] = plan.total
        t_solve += time.perf_counter() - t1
        if progress and (d + 1) % 10 == 0:
            progress(f"  draw {d + 1}/{draws} ({time.perf_counter() - t0:.0f} s)")
    res = summarise(truth, full, sub, np.stack(errors), failed, views, cap,
                     {"render_s": t_render, "detect_s": t_detect, "solve_s": t_solve,
                      "total_s": time.perf_counter() - t0})
    res["corner"]["clean_rms_px"] = float(np.sqrt(np.mean((clean - views.truth) ** 2)))
    for n in n_list:
        res["full"][n]["clean_bias"] = clean_bias[n]
    return res


def _neighbour_corr(e: np.ndarray) -> float:
    """Correlation of an error field (..., rows, cols, 2) between horizontally adjacent corners."""
    return float(np.corrcoef(e[..., :, :-1, :].ravel(), e[..., :, 1:, :].ravel())[0, 1])


def _radial_profile(fixed: np.ndarray, truth: np.ndarray, centre: np.ndarray, bins: int = 5) -> dict:
    """Mean radial component (outwards from the principal point) of the detector's fixed error, by radius."""
    d = truth - centre
    r = np.linalg.norm(d, axis=-1)
    radial = np.sum(fixed * d, axis=-1) / np.maximum(r, 1e-9)
    edges = np.quantile(r, np.linspace(0, 1, bins + 1))
    which = np.clip(np.digitize(r, edges[1:-1]), 0, bins - 1)
    return {"r_px": [float(np.mean(r[which == b])) for b in range(bins)],
            "radial_px": [float(np.mean(radial[which == b])) for b in range(bins)],
            "se_px": [float(np.std(radial[which == b]) / np.sqrt(np.sum(which == b))) for b in range(bins)]}


def summarise(truth, full, sub, errors, failed, views, cap, timings) -> dict:
    cols, rows = uc.PATTERN
    fixed = errors.mean(axis=0)  # (V, n, 2): the detector's error that does not change with the noise draw
    noise = errors - fixed
    corner = {
        "draws": len(errors), "failed_draws": failed,
        "total_rms_px": float(np.sqrt(np.mean(errors ** 2))),
        "fixed_rms_px": float(np.sqrt(np.mean(fixed ** 2))),
        "noise_rms_px": float(np.sqrt(np.mean(noise ** 2) * len(errors) / (len(errors) - 1))),
        "fixed_neighbour_corr": _neighbour_corr(fixed.reshape(-1, rows, cols, 2)),
        "noise_neighbour_corr": _neighbour_corr(noise.reshape(-1, rows, cols, 2)),
        "mean_error_px": errors.mean(axis=(0, 1, 2)),
        "radial": _radial_profile(fixed, views.truth, np.asarray(views.camera.k[2:4])),
    }
    out = {"truth": dict(zip(uc.INTRINSICS, truth)), "corner": corner, "timings": timings, "cap": cap,
           "full": {}, "subsets": {}}
    for n, f in full.items():
        vals, std, status = np.array(f["values"]), np.array(f["std"]), np.array(f["status"])
        ok = status > 0
        vals, std = vals[ok], std[ok]
        mc = np.std(vals, axis=0, ddof=1)
        inside = np.abs(vals - truth) <= 1.96 * std
        out["full"][n] = {
            "draws": int(ok.sum()), "unconverged": int((~ok).sum()), "rms_px": float(np.mean(f["rms"])),
            "jacobian": std.mean(axis=0), "mc": mc, "bias": vals.mean(axis=0) - truth,
            "bias_se": mc / np.sqrt(len(vals)), "coverage95": inside.mean(axis=0),
            # spread of the Jacobian std itself across draws (how well one data set knows its own sigma)
            "jacobian_rel_scatter": std.std(axis=0, ddof=1) / std.mean(axis=0),
        }
    for (n, m), rec in sub.items():
        raw, jack, pred = (np.array(rec[k]) for k in ("raw", "jack", "pred"))
        out["subsets"][f"{n},{m}"] = {
            "n": n, "m": m, "total": rec["total"], "solved": min(rec["total"], cap), "draws": len(raw),
            "min_converged": int(min(rec["converged"])),
            "raw": np.sqrt(np.mean(raw ** 2, axis=0)), "jack": np.sqrt(np.mean(jack ** 2, axis=0)),
            "pred_raw": np.sqrt(np.mean(pred ** 2, axis=0)),
            "jack_rel_scatter": jack.std(axis=0, ddof=1) / jack.mean(axis=0),
            "jack_per_draw": jack,
        }
    return out


def tables(res: dict) -> str:
    c = res["corner"]
    names = uc.INTRINSICS
    text = [f"Corner error of the detector vs the true projections ({c['draws']} draws, {c['failed_draws']} draws "
            f"with a missed board): total RMS {c['total_rms_px']:.4f} px per coordinate = fixed part (same in every "
            f"draw) {c['fixed_rms_px']:.4f} px + noise part {c['noise_rms_px']:.4f} px; neighbour correlation "
            f"fixed {c['fixed_neighbour_corr']:.2f}, noise {c['noise_neighbour_corr']:.2f}. Noise-free render: RMS "
            f"{c['clean_rms_px']:.4f} px. Mean radial component of the fixed part by radius (px): "
            + ", ".join(f"r {r:.0f}: {v:+.4f} +- {e:.4f}" for r, v, e in zip(*c["radial"].values())) + ".\n"]
    header = ["N", "param", "truth", "bias", "bias / MC std", "bias of the noise-free solve", "MC std",
              "Jacobian std", "Jacobian / MC", "coverage of +-1.96 sigma_J"]
    rows = []
    for n, f in res["full"].items():
        for i, p in enumerate(names):
            rows.append([n, p, float(res["truth"][p]), float(f["bias"][i]), float(f["bias"][i] / f["mc"][i]),
                         float(f["clean_bias"][i]), float(f["mc"][i]), float(f["jacobian"][i]),
                         float(f["jacobian"][i] / f["mc"][i]),
                         f"{100 * f['coverage95'][i]:.0f} %"])
    text.append(uc.md_table(header, rows))
    header = ["N", "m", "subsets (of C(N,m))", "param", "raw spread / MC", "jackknife / MC", "jackknife / Jacobian",
              "linear prediction of raw / raw", "jackknife scatter over draws"]
    rows = []
    for key, s in res["subsets"].items():
        f = res["full"][s["n"]]
        for i, p in enumerate(names):
            rows.append([s["n"], s["m"], f"{s['solved']} of {s['total']}", p, float(s["raw"][i] / f["mc"][i]),
                         float(s["jack"][i] / f["mc"][i]), float(s["jack"][i] / f["jacobian"][i]),
                         float(s["pred_raw"][i] / s["raw"][i]), f"{100 * s['jack_rel_scatter'][i]:.0f} %"])
    text.append(uc.md_table(header, rows))
    return "\n".join(text)


def figure(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = uc.INTRINSICS
    keys = list(res["subsets"])
    fig, axes = plt.subplots(1, len(res["full"]), figsize=(4.2 * len(res["full"]), 3.8), sharey=True)
    for ax, n in zip(np.atleast_1d(axes), res["full"]):
        f = res["full"][n]
        x = np.arange(len(names))
        ax.axhline(1.0, color="k", lw=0.8)
        ax.plot(x, f["jacobian"] / f["mc"], "o-", label="Jacobian std")
        for key in keys:
            s = res["subsets"][key]
            if s["n"] != n:
                continue
            ax.plot(x, s["jack"] / f["mc"], "s--", label=f"jackknife-scaled spread, m={s['m']}")
            ax.plot(x, s["raw"] / f["mc"], "v:", label=f"raw subset spread, m={s['m']}")
        ax.set_xticks(x, names)
        ax.set_title(f"N = {n}")
        ax.set_ylim(0, 1.6)
    np.atleast_1d(axes)[0].set_ylabel("estimate / Monte Carlo std")
    np.atleast_1d(axes)[-1].legend(fontsize=7, loc="lower right")
    fig.suptitle("Uncertainty estimates over the Monte Carlo std (re-rendered sensor noise, re-detected corners)",
                 fontsize=10)
    fig.tight_layout()
    uc.FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(uc.FIGURES / "uncertainty_mc_ratios.png", dpi=110)
    plt.close(fig)

    # one data set's jackknife estimate scatters: per-draw values for each (N, m), parameter fx
    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    for j, key in enumerate(keys):
        s = res["subsets"][key]
        f = res["full"][s["n"]]
        r = s["jack_per_draw"][:, 0] / f["mc"][0]
        ax.plot(np.full(len(r), j) + np.random.default_rng(j).uniform(-0.15, 0.15, len(r)), r, ".", alpha=0.7)
        ax.plot([j - 0.3, j + 0.3], [f["jacobian"][0] / f["mc"][0]] * 2, "k-", lw=2)
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xticks(range(len(keys)), [f"N={res['subsets'][k]['n']}\nm={res['subsets'][k]['m']}" for k in keys])
    ax.set_ylabel("fx: jackknife std of one data set / MC std")
    ax.set_title("Per-data-set jackknife (dots) vs mean Jacobian std (bar)", fontsize=10)
    fig.tight_layout()
    fig.savefig(uc.FIGURES / "uncertainty_mc_jackknife_scatter.png", dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30 draws, subsets on 5 of them")
    parser.add_argument("--draws", type=int, default=100)
    parser.add_argument("--subset-draws", type=int, default=20)
    parser.add_argument("--cap", type=int, default=128, help="subsets per (N, m): all if C(N, m) <= cap")
    args = parser.parse_args()
    draws, subset_draws = (30, 5) if args.quick else (args.draws, args.subset_draws)
    res = run(draws=draws, subset_draws=subset_draws, cap=args.cap)
    md = tables(res)
    print(md)
    t = res["timings"]
    print(f"time: render {t['render_s']:.1f} s, detect {t['detect_s']:.1f} s, solve {t['solve_s']:.1f} s, "
          f"total {t['total_s']:.1f} s")
    uc.write_outputs("uncertainty_mc", md, res | {"full": {str(k): v for k, v in res["full"].items()}})
    figure(res)


if __name__ == "__main__":
    main()
