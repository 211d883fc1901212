"""(c) Calibration uncertainty on the real sets: which standard deviation to report.

For opencv_stereo (13 pairs) and rig640 (25 pairs), square = 1, model k1, k2, p1, p2, k3:
- each camera alone: the Jacobian standard deviation of the full-set solve; the view-robust ("sandwich")
  standard deviation; the raw spread over C(N, m) subsets (m = N - 3; all, or a seeded sample of `--cap`), the
  same after the thesis's IQR steps (re <= 0.5 px | p1, p2 1.5 IQR | k1, k2, k3 1.5 IQR | fx, fy, cx, cy 1 IQR,
  section 5.2), and its delete-d jackknife rescaling sqrt(m / (N - m)); a view bootstrap (`--boot` resamples of
  the N views with replacement, solved in one batched call of the engine's subset solver);
- the rig (fixed intrinsics, the thesis's path; and joint refinement): the same for RVx..Tz, |T| and |rv|;
- residual diagnostics of each camera's full solve: normal QQ of the residuals, correlation of the residuals of
  corners k apart on the board (k = 1..4 along rows, along columns), per-view RMS with the IQR outlier rule.

`python -m experiments.real_uncertainty [--quick]`; writes experiments/results/figures/real_uncertainty.{md,json}
and real_uncertainty_*.png.
"""

from __future__ import annotations

import argparse
import time

from experiments import _uncertainty_common as uc

import numpy as np  # noqa: E402

FREE = ("k1", "k2", "p1", "p2", "k3")
SETS = ("opencv_stereo", "rig640")
CHUNK = 16  # subsets per compiled call where the engine takes it (see `uc.solve_subsets_safe`)
RIG_COLUMNS = ("RVx", "RVy", "RVz", "Tx", "Ty", "Tz", "|rv|", "|T|")


def thesis_steps():
    from dstereo.config.calibration import Step

    return [Step(("re",), (0.5,)), Step(("p1", "p2"), (1.5, 1.5)), Step(("k1", "k2", "k3"), (1.5,) * 3),
            Step(("fx", "fy", "cx", "cy"), (1.0,) * 4)]


def mono_study(obj, obs, size, cap: int, boot: int) -> dict:
    from dstereo.calib import mono
    from dstereo.calib.robust_steps import run_steps
    from dstereo.calib.subsets import plan_subsets

    n = len(obs)
    m = n - 3
    full = mono.calibrate_full(obj, obs, size, FREE)
    plan = plan_subsets(n, m, cap=cap, seed=0)
    sub = uc.solve_subsets_safe(mono.solve_subsets, obj, obs, plan, full, chunk=CHUNK)
    ok = sub.converged
    table = np.column_stack([sub.rms, sub.values])
    filt = run_steps(table, ("re",) + full.names, thesis_steps(), usable=ok)
    kept = filt.survivors
    bplan = uc.bootstrap_plan(n, boot, seed=0)
    bsub = uc.solve_subsets_safe(mono.solve_subsets, obj, obs, bplan, full, chunk=CHUNK)
    bok = bsub.converged
    raw = uc.spread(sub.values[ok])
    return {
        "names": full.names, "values": full.values, "n": n, "m": m, "plan": plan.describe(), "rms": full.rms,
        "condition": full.conditioning.condition_number,
        "jacobian": full.std, "sandwich": uc.sandwich_std(full, obj, obs), "raw": raw,
        "raw_iqr": uc.spread(sub.values[kept]), "iqr_kept": int(kept.sum()), "subsets_ok": int(ok.sum()),
        "jack": uc.jackknife_factor(n, m) * raw, "boot": uc.spread(bsub.values[bok]), "boot_ok": int(bok.sum()),
        "residuals": full.residuals[:, 0], "per_view_rms": full.per_view_rms[:, 0],
        # per-coordinate noise estimate sigma^2 = SSE / (2 points - parameters), SSE = rms^2 points
        "sigma": full.rms * np.sqrt(obs.shape[0] * obs.shape[1] / (2 * obs.shape[0] * obs.shape[1]
                                                                  - len(full.values) - 6 * n)),
        "time_s": full.timings["solve_s"] + sub.timings["solve_s"] + bsub.timings["solve_s"],
    }


def _rig_columns(values: np.ndarray) -> np.ndarray:
    return np.column_stack([values[:, :6], np.linalg.norm(values[:, :3], axis=1),
                            np.linalg.norm(values[:, 3:6], axis=1)])


def _norm_std(v: np.ndarray, cov: np.ndarray) -> float:
    grad = v / np.linalg.norm(v)
    return float(np.sqrt(max(grad @ cov @ grad, 0.0)))


def stereo_study(pairs, mode: str, cap: int, boot: int) -> dict:
    """The rig of two cameras (calib/multiview.py, K = 2) on a set's pairs, its frame subsets and bootstrap."""
    from dstereo.calib.mono import calibrate_full
    from dstereo.calib.multiview import calibrate_views, solve_view_subsets
    from dstereo.calib.subsets import plan_subsets

    obj, obs, sizes = pairs
    n = len(obs)
    m = n - 3
    sols = [calibrate_full(obj, obs[:, k], sizes[k], FREE) for k in range(2)]
    cams = [s.camera() for s in sols]
    vis = np.ones((n, 2), bool)
    full = calibrate_views(obj, obs, vis, sizes, mode=mode, cameras=cams)
    plan = plan_subsets(n, m, cap=cap, seed=0)
    sub = solve_view_subsets(obj, obs, vis, plan.index, full)
    bsub = solve_view_subsets(obj, obs, vis, uc.bootstrap_plan(n, boot, seed=0).index, full)
    ok, bok = sub.converged, bsub.converged
    raw = uc.spread(_rig_columns(sub.values[ok]))
    jac = np.concatenate([full.std_jacobian[:6], [_norm_std(full.values[:3], full.cov[:3, :3]),
                                                  _norm_std(full.values[3:6], full.cov[3:6, 3:6])]])
    return {
        "mode": mode, "n": n, "m": m, "plan": plan.describe(), "rms": full.rms,
        "values": _rig_columns(full.values[None])[0], "jacobian": jac, "raw": raw,
        "jack": uc.jackknife_factor(n, m) * raw, "boot": uc.spread(_rig_columns(bsub.values[bok])),
        "subsets_ok": int(ok.sum()), "boot_ok": int(bok.sum()),
        "time_s": full.timings["solve_s"] + sub.timings["solve_s"] + bsub.timings["solve_s"],
    }


def residual_diagnostics(res: np.ndarray, per_view_rms: np.ndarray, sigma: float) -> dict:
    """res (V, n, 2) projected - observed."""
    from scipy import stats

    cols, rows = uc.PATTERN
    grid = res.reshape(res.shape[0], rows, cols, 2)
    along_rows = [float(np.corrcoef(grid[:, :, :-k].ravel(), grid[:, :, k:].ravel())[0, 1]) for k in range(1, 5)]
    along_cols = [float(np.corrcoef(grid[:, :-k].ravel(), grid[:, k:].ravel())[0, 1]) for k in range(1, 5)]
    z = res.ravel() / sigma
    q1, q3 = np.percentile(per_view_rms, [25, 75])
    outliers = np.flatnonzero(per_view_rms > q3 + 1.5 * (q3 - q1))
    # heavy tails: share of the SSE carried by the worst 1 % of the corners (2-D normal residuals: 5.6 %)
    sq = np.sort(np.sum(res ** 2, axis=2).ravel())[::-1]
    tail = float(np.sum(sq[: max(1, len(sq) // 100)]) / np.sum(sq))
    return {"corr_rows": along_rows, "corr_cols": along_cols, "excess_kurtosis": float(stats.kurtosis(z)),
            "shapiro_p": float(stats.shapiro(z[:5000])[1]), "outlier_views": outliers.tolist(),
            "tail_share": tail, "z": z}


def tables(res: dict) -> str:
    out = []
    header = ["set", "camera", "param", "value", "Jacobian", "sandwich / J", "raw spread / J", "raw after IQR / J",
              "jackknife / J", "bootstrap / J"]
    rows = []
    for key, r in res["mono"].items():
        for i, p in enumerate(r["names"]):
            j = r["jacobian"][i]
            rows.append([*key.split("/"), p, float(r["values"][i]), float(j), float(r["sandwich"][i] / j),
                         float(r["raw"][i] / j), float(r["raw_iqr"][i] / j), float(r["jack"][i] / j),
                         float(r["boot"][i] / j)])
    out.append(uc.md_table(header, rows))
    header = ["set", "camera", "N", "subsets (m)", "after IQR", "bootstrap draws ok", "RMS px", "neighbour corr. "
              "(rows, cols)", "lag-4 corr.", "SSE share of worst 1 % corners", "excess kurtosis", "outlier views"]
    rows = []
    for key, r in res["mono"].items():
        d = r["diag"]
        rows.append([*key.split("/"), r["n"], f"{r['subsets_ok']} ({r['m']}; {r['plan']})", r["iqr_kept"],
                     r["boot_ok"], f"{r['rms']:.3f}", f"{d['corr_rows'][0]:.2f}, {d['corr_cols'][0]:.2f}",
                     f"{d['corr_rows'][3]:.2f}, {d['corr_cols'][3]:.2f}",
                     f"{100 * d['tail_share']:.0f} %",
                     f"{d['excess_kurtosis']:.2f}", ", ".join(r["view_names"][i] for i in d["outlier_views"])
                     or "-"])
    out.append(uc.md_table(header, rows))
    header = ["set", "mode", "param", "value", "Jacobian", "raw spread / J", "jackknife / J", "bootstrap / J"]
    rows = []
    for key, r in res["stereo"].items():
        for i, p in enumerate(RIG_COLUMNS):
            j = r["jacobian"][i]
            rows.append([*key.split("/"), p, float(r["values"][i]), float(j), float(r["raw"][i] / j),
                         float(r["jack"][i] / j), float(r["boot"][i] / j)])
    out.append(uc.md_table(header, rows))
    return "\n".join(out)


def figures(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy import stats

    keys = list(res["mono"])
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.4), sharey=True, squeeze=False)
    for ax, key in zip(axes[0], keys):
        r = res["mono"][key]
        x = np.arange(len(r["names"]))
        ax.axhline(1.0, color="k", lw=0.8)
        for name, marker in (("sandwich", "^-"), ("jack", "s--"), ("boot", "o-"), ("raw_iqr", "v:")):
            label = {"sandwich": "sandwich", "jack": "jackknife-scaled", "boot": "bootstrap",
                     "raw_iqr": "thesis: raw spread after IQR"}[name]
            ax.plot(x, r[name] / r["jacobian"], marker, label=label)
        ax.set_xticks(x, r["names"], fontsize=7)
        ax.set_title(key, fontsize=9)
    axes[0, 0].set_ylabel("std / Jacobian std")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    uc.FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(uc.FIGURES / "real_uncertainty_mono.png", dpi=110)
    plt.close(fig)

    keys = list(res["stereo"])
    fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.4), sharey=True, squeeze=False)
    for ax, key in zip(axes[0], keys):
        r = res["stereo"][key]
        x = np.arange(len(RIG_COLUMNS))
        ax.axhline(1.0, color="k", lw=0.8)
        ax.plot(x, r["jack"] / r["jacobian"], "s--", label="jackknife-scaled")
        ax.plot(x, r["boot"] / r["jacobian"], "o-", label="bootstrap")
        ax.plot(x, r["raw"] / r["jacobian"], "v:", label="raw subset spread")
        ax.set_xticks(x, RIG_COLUMNS, fontsize=7)
        ax.set_title(key, fontsize=9)
    axes[0, 0].set_ylabel("std / Jacobian std")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(uc.FIGURES / "real_uncertainty_stereo.png", dpi=110)
    plt.close(fig)

    keys = list(res["mono"])
    fig, axes = plt.subplots(3, len(keys), figsize=(3.4 * len(keys), 9.0), squeeze=False)
    for c, key in enumerate(keys):
        r, d = res["mono"][key], res["mono"][key]["diag"]
        z = np.sort(d["z"])
        theo = stats.norm.ppf((np.arange(1, len(z) + 1) - 0.5) / len(z))
        axes[0, c].plot(theo, z, ".", ms=2)
        axes[0, c].plot(theo, theo, "k-", lw=0.8)
        axes[0, c].set_title(f"{key}: QQ (residual / sigma)", fontsize=8)
        lags = np.arange(1, 5)
        axes[1, c].plot(lags, d["corr_rows"], "o-", label="along rows")
        axes[1, c].plot(lags, d["corr_cols"], "s-", label="along columns")
        axes[1, c].axhline(0, color="k", lw=0.8)
        axes[1, c].set_ylim(-0.3, 1.0)
        axes[1, c].set_title("residual correlation vs corner distance", fontsize=8)
        axes[1, c].set_xlabel("corners apart")
        pv = r["per_view_rms"]
        colors = ["r" if i in d["outlier_views"] else "C0" for i in range(len(pv))]
        axes[2, c].bar(np.arange(len(pv)), pv, color=colors)
        axes[2, c].set_title("per-view RMS px (red: > Q3 + 1.5 IQR)", fontsize=8)
    axes[1, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(uc.FIGURES / "real_uncertainty_residuals.png", dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="opencv_stereo only, 100 bootstrap draws")
    parser.add_argument("--boot", type=int, default=200)
    parser.add_argument("--cap", type=int, default=1000)
    args = parser.parse_args()
    boot = 100 if args.quick else args.boot
    t0 = time.perf_counter()
    res = {"mono": {}, "stereo": {}}
    for name in SETS[:1] if args.quick else SETS:
        for side in ("left", "right"):
            obj, obs, size, names = uc.real_views(name, side)
            r = mono_study(obj, obs, size, args.cap, boot)
            r["diag"] = residual_diagnostics(r["residuals"], r["per_view_rms"], r["sigma"])
            r["view_names"] = names
            res["mono"][f"{name}/{side}"] = r
            print(f"  {name} {side}: {r['time_s']:.0f} s")
        pairs = uc.real_pairs(name)
        for mode in ("fixed", "joint"):
            r = stereo_study(pairs, mode, args.cap, boot)
            res["stereo"][f"{name}/{mode}"] = r
            print(f"  {name} rig [{mode}]: {r['time_s']:.0f} s")
    md = tables(res)
    print(md)
    print(f"total {time.perf_counter() - t0:.0f} s")
    slim = {"mono": {k: {kk: vv for kk, vv in v.items() if kk not in ("residuals",)} | {
        "diag": {kk: vv for kk, vv in v["diag"].items() if kk != "z"}} for k, v in res["mono"].items()},
        "stereo": res["stereo"]}
    uc.write_outputs("real_uncertainty", md, slim)
    figures(res)


if __name__ == "__main__":
    main()
