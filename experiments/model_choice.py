"""(b) Distortion model choice by held-out views (leave-one-view-out cross-validation).

For each model of the ladder none; k1; k1,k2; k1,k2,p1,p2; k1,k2,p1,p2,k3; rational k1..k6,p1,p2:
- the full-set solve gives the training RMS and the identifiability flag (scale-free condition number of the
  Schur complement, `dstereo.uncertainty.covariance`);
- the N leave-one-out training sets are solved in one batched call of the engine's subset solver
  (`mono.solve_subsets` with the plan of all C(N, N-1) subsets);
- each held-out view's pose is solved with that fold's intrinsics and distortion fixed (optimistix LM, vmapped
  over the folds), and its RMS is the held-out error of the model.

Choice: among models that are identifiable and converged on every fold, the simplest whose held-out mean squared
error is within one standard error (paired over views) of the best model's (the one-standard-error rule); the
model with the lowest held-out RMS is reported too. Real sets: opencv_stereo and rig640, left and right cameras
(square = 1); synthetic sets rendered with a known model (13 views, sensor noise, corners re-detected).

`python -m experiments.model_choice [--quick]`; writes experiments/results/figures/model_choice.{md,json,png}.
"""

from __future__ import annotations

import argparse
import time

from experiments import _uncertainty_common as uc

import numpy as np  # noqa: E402

LADDER: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("none", ()),
    ("k1", ("k1",)),
    ("k1k2", ("k1", "k2")),
    ("k1k2p1p2", ("k1", "k2", "p1", "p2")),
    ("k1k2p1p2k3", ("k1", "k2", "p1", "p2", "k3")),
    ("rational", ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
)

# Synthetic truths: (label, OpenCV-order coefficients k1 k2 p1 p2 k3, the ladder model that generated them)
SYNTHETIC = (
    ("synthetic k1k2", (-0.25, 0.12), "k1k2"),
    ("synthetic k1k2p1p2", (-0.25, 0.12, 0.002, -0.0015), "k1k2p1p2"),
    ("synthetic k1k2p1p2k3", (-0.25, 0.12, 0.002, -0.0015, -0.08), "k1k2p1p2k3"),
)


def cross_validate(obj: np.ndarray, obs: np.ndarray, size, free: tuple[str, ...]) -> dict:
    """Leave-one-view-out cross-validation of one distortion model."""
    from dstereo.calib import mono
    from dstereo.calib.subsets import plan_subsets
    from dstereo.models.distortion import COEFF_NAMES

    n, n_pts = obs.shape[0], obs.shape[1]
    full = mono.calibrate_full(obj, obs, size, free)
    plan = plan_subsets(n, n - 1, cap=n)
    held = np.array([np.setdiff1d(np.arange(n), row)[0] for row in plan.index])
    sub = uc.solve_subsets_safe(mono.solve_subsets, obj, obs, plan, full)
    coeffs = np.zeros((n, 8))
    if free:
        coeffs[:, [COEFF_NAMES.index(c) for c in free]] = sub.values[:, 4:]
    _, sse, pose_ok = uc.solve_poses(sub.values[:, :4], coeffs, obj, obs[held], full.poses[held])
    mse = np.full(n, np.nan)
    mse[held] = sse / n_pts  # per point, both coordinates (OpenCV's RMS squared)
    return {
        "train_rms": full.rms, "full_status": full.status, "identifiable": full.conditioning.identifiable,
        "condition": full.conditioning.condition_number, "weak": full.conditioning.weak_parameters,
        "folds_unconverged": int((~sub.converged).sum()), "poses_unconverged": int((~pose_ok).sum()),
        "heldout_mse": mse, "heldout_rms": float(np.sqrt(np.mean(mse))), "fold_train_rms": float(np.mean(sub.rms)),
    }


def choose(results: dict) -> dict:
    """One-standard-error rule over the usable models, in ladder order."""
    usable = [k for k, r in results.items()
              if r["identifiable"] and r["full_status"] > 0 and r["folds_unconverged"] == 0
              and r["poses_unconverged"] == 0]
    best = min(usable, key=lambda k: results[k]["heldout_rms"])
    for k in results:
        d = results[k]["heldout_mse"] - results[best]["heldout_mse"]
        results[k]["diff_vs_best_mse"] = float(np.mean(d))
        results[k]["diff_se"] = float(np.std(d, ddof=1) / np.sqrt(len(d))) if k != best else 0.0
    chosen = next(k for k in results if k in usable
                  and results[k]["diff_vs_best_mse"] <= results[k]["diff_se"])
    return {"best": best, "chosen": chosen, "usable": usable}


def run_set(label: str, obj, obs, size, ladder=LADDER, progress=print) -> dict:
    t0 = time.perf_counter()
    results = {}
    for name, free in ladder:
        results[name] = cross_validate(obj, obs, size, free)
    out = {"label": label, "views": int(obs.shape[0]), "models": results, **choose(results),
           "time_s": time.perf_counter() - t0}
    if progress:
        progress(f"  {label}: chosen {out['chosen']} (lowest held-out RMS {out['best']}), {out['time_s']:.0f} s")
    return out


def synthetic_set(coeffs, n_views: int = 13, seed: int = 0):
    cam = uc.truth_camera(coeffs, free=())
    views = uc.render_views(cam, n_views, seed=seed)
    obs, missed = views.draw(seed)
    if obs is None:
        raise RuntimeError(f"synthetic set: the detector missed views {missed}")
    return views.obj, obs, cam.image_size


def tables(sets: list[dict]) -> str:
    header = ["set", "views", "model", "training RMS px", "held-out RMS px", "held-out - best (MSE, px^2)",
              "1 SE", "identifiable (condition)", "unconverged folds", "choice"]
    rows = []
    for s in sets:
        for name, r in s["models"].items():
            mark = []
            if name == s["chosen"]:
                mark.append("**chosen**")
            if name == s["best"]:
                mark.append("lowest held-out")
            if s.get("truth") == name:
                mark.append("truth")
            rows.append([s["label"], s["views"], name, f"{r['train_rms']:.4f}", f"{r['heldout_rms']:.4f}",
                         f"{r['diff_vs_best_mse']:.2e}", f"{r['diff_se']:.1e}",
                         f"{'yes' if r['identifiable'] else 'NO'} ({r['condition']:.1e})",
                         r["folds_unconverged"] + r["poses_unconverged"], ", ".join(mark)])
    return uc.md_table(header, rows)


def figure(sets: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(len(sets), 4)
    rows = -(-len(sets) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.2 * rows), squeeze=False)
    for ax, s in zip(axes.ravel(), sets):
        names = list(s["models"])[1:]  # "none" is off the scale everywhere; its RMS goes into the title
        x = np.arange(len(names))
        m = s["models"]
        best = m[s["best"]]["heldout_rms"]
        tr = [m[k]["train_rms"] for k in names]
        ho = [m[k]["heldout_rms"] for k in names]
        se = [m[k]["diff_se"] / (2 * best) for k in names]  # 1 SE of the paired MSE difference, in RMS px
        ax.plot(x, tr, "o-", label="training RMS")
        ax.errorbar(x, ho, yerr=se, fmt="s-", capsize=3, label="held-out RMS (+-1 SE vs best)")
        for i, k in enumerate(names):
            if not m[k]["identifiable"]:
                ax.plot(i, ho[i], "rx", ms=10, mew=2)
        c = names.index(s["chosen"])
        ax.plot(c, ho[c], "o", mfc="none", mec="g", ms=14, mew=2)
        ax.set_xticks(x, names, rotation=40, fontsize=7)
        lo = min(tr + ho)
        ax.set_ylim(lo * 0.97, min(max(ho), 1.25 * lo) * 1.02)
        ax.set_title(f"{s['label']} (none: {m['none']['heldout_rms']:.2f} px)", fontsize=8)
    for ax in axes.ravel()[len(sets):]:
        ax.axis("off")
    axes[0, 0].set_ylabel("RMS px")
    axes[0, 0].legend(fontsize=6)
    fig.suptitle("Leave-one-view-out: green ring = chosen model (1-SE rule), red x = not identifiable", fontsize=10)
    fig.tight_layout()
    uc.FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(uc.FIGURES / "model_choice.png", dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="opencv_stereo left and one synthetic set only")
    parser.add_argument("--replot", action="store_true", help="only redraw the figure from the saved JSON")
    args = parser.parse_args()
    if args.replot:
        import json

        figure(json.loads((uc.FIGURES / "model_choice.json").read_text())["sets"])
        return
    t0 = time.perf_counter()
    sets = []
    real = [("opencv_stereo", "left")] if args.quick else [("opencv_stereo", "left"), ("opencv_stereo", "right"),
                                                            ("rig640", "left"), ("rig640", "right")]
    for name, side in real:
        obj, obs, size, _ = uc.real_views(name, side)
        sets.append(run_set(f"{name} {side}", obj, obs, size))
    for label, coeffs, truth in SYNTHETIC[:1] if args.quick else SYNTHETIC:
        obj, obs, size = synthetic_set(coeffs)
        sets.append(run_set(label, obj, obs, size) | {"truth": truth})
    md = tables(sets)
    print(md)
    print(f"total {time.perf_counter() - t0:.0f} s")
    uc.write_outputs("model_choice", md, {"sets": sets})
    figure(sets)


if __name__ == "__main__":
    main()
