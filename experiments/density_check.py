"""The default's density check (issue 30, `dstereo.stereo.density_check`) measured before and after, on the ten
Middlebury rows it must not change for the worse and on harder cases none of its figures were tuned on.

Cases:
- Middlebury 2014 quarter size (the five shared scenes), as it is and relit (the right view through gain 0.7,
  gamma 1.3: `experiments.middlebury_lighting`): the ten existing rows;
- the same scenes with their texture weakened in BOTH views (lit alike, so `--cost auto` takes the grey levels):
  'contrast x0.25' (levels pulled to the image mean: I -> m + 0.25 (I - m), rounded to 8 bits: the texture
  drowns in the quantisation) and 'blur 2 px' (a Gaussian blur of sigma 2 px: fine texture gone);
- rendered outdoor scenes (`dstereo.synth.outdoor`, seeds 0 and 1, 480 x 320) with contrast x0.25 in both views;
- held out (`--held-out`, run after the check's threshold was set on the cases above): the Middlebury scenes with
  'contrast x0.4, blur 1 px' and 'noise 3 DN' (Gaussian, both views), outdoor renders seeds 2 and 3 at contrast
  x0.25;
- the shared real rigs (rig640: every 5th pair; opencv_stereo: every 4th), no truth but the chessboard in view: a
  robust plane fit to the 'before' map over the hull of its 9 x 6 corners stands in for it (as in
  experiments/default_matching_real.py); figures: summary.json's valid share, the board's pixels with an
  estimate and those within 1 px of its plane, and the filled board pixels' robust std about the plane over the
  RMS of their sigma.

Configurations, no other flags (`ReconstructionConfig(uncertainty=False)`):
- before: the default without the density check (its threshold set to 0: the grey levels' map always kept,
  unfilled: what `dstereo reconstruct` did before);
- after: the default with the check;
- rank fill: `--cost rank --fill` (what the check's second try computes, for reference).

Scored (Middlebury: mask0nocc.png == 255 with a finite truth; renders: the left pixels the right camera sees):
density = share with an estimate (%), median and p90 of |Z - Z_true| / Z_true (%) over the estimates, filled =
share of the estimates that were filled, filled obs / pred = the filled pixels' robust std of the disparity error
(1.4826 MAD, px) over the RMS of their sigma (the convention of experiments/middlebury_lighting.py). pass:
median <= 1 %, p90 <= 5 %, density >= 80 %. kept: the cost the default ended with and the check's own figures.

    python -m experiments.density_check [--out experiments/results/density_check.md] [--skip-renders]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `dstereo` runs (dstereo/cli.py), before numpy loads

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from dstereo.io.calib_files import read_middlebury_calib
from dstereo.io.images import read_image
from dstereo.stereo import density_check
from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
from experiments._validation import report
from experiments.middlebury import ground_truth
from experiments.middlebury_lighting import relit

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "middlebury2014q"
DEFAULT = ReconstructionConfig(uncertainty=False)
CONFIGS = {"before": DEFAULT, "after": DEFAULT, "rank fill": replace(DEFAULT, matching_cost="rank", fill=True)}
MAD_TO_STD = 1.4826


def contrast(image: np.ndarray, share: float = 0.25) -> np.ndarray:
    """Levels pulled towards the image's mean: m + share (I - m), rounded to 8 bits."""
    x = image.astype(np.float64)
    m = x.mean()
    return np.clip(np.rint(m + share * (x - m)), 0, 255).astype(np.uint8)


def blurred(image: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    import cv2

    return np.clip(np.rint(cv2.GaussianBlur(image.astype(np.float64), (0, 0), sigma)), 0, 255).astype(np.uint8)


def robust_std(x: np.ndarray) -> float:
    return float(MAD_TO_STD * np.median(np.abs(x - np.median(x))))


def reconstruct(name: str, calib, left, right, config) -> tuple[object, float]:
    """One run; 'before' is the default with the check's threshold at 0 (never tries the rank cost)."""
    saved = density_check.DENSE_ENOUGH
    if name == "before":
        density_check.DENSE_ENOUGH = 0.0
    try:
        t0 = time.perf_counter()
        result = reconstruct_calibrated(calib, left, right, config, name)
        return result, time.perf_counter() - t0
    finally:
        density_check.DENSE_ENOUGH = saved


def score(result, seconds: float, scored: np.ndarray, z_true: np.ndarray, d_true: np.ndarray) -> dict:
    est = scored & np.isfinite(result.depth) & np.isfinite(result.disparity)
    rel = np.abs(result.depth - z_true)[est] / z_true[est]
    filled = est & (result.filled if result.filled is not None else False)
    check = result.summary.get("density_check") or {}
    tries = check.get("tries") or []
    ratio = (tries[1].get("fill_check") or {}).get("ratio") if len(tries) > 1 else None
    row = {"density_pct": 100.0 * est.sum() / scored.sum(), "median_pct": 100.0 * float(np.median(rel)),
           "p90_pct": 100.0 * float(np.percentile(rel, 90)), "filled_pct": 100.0 * filled.sum() / max(est.sum(), 1),
           "obs_pred": None, "cost": result.summary["search_range"]["matching_cost"]["cost"], "seconds": seconds,
           "map_density_pct": 100.0 * tries[0]["density"] if tries else None, "check_ratio": ratio}
    if filled.sum() >= 100:
        err = result.disparity[filled].astype(np.float64) - d_true[filled]
        row["obs_pred"] = robust_std(err) / float(np.sqrt(np.mean(result.fill_sigma[filled] ** 2)))
    return row


def passes(r: dict) -> bool:
    return r["median_pct"] <= 1.0 and r["p90_pct"] <= 5.0 and r["density_pct"] >= 80.0


def run_case(calib, left, right, scored, z_true, d_true) -> dict:
    return {n: score(*reconstruct(n, calib, left, right, c), scored, z_true, d_true) for n, c in CONFIGS.items()}


def noisy(image: np.ndarray, std: float = 3.0, seed: int = 0) -> np.ndarray:
    """Gaussian noise of `std` DN added, rounded to 8 bits (a darker exposure's shot and read noise)."""
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(image + rng.normal(0.0, std, image.shape)), 0, 255).astype(np.uint8)


# Texture weakened in BOTH views (lit alike). 'weakened': the first harder set; 'held out': a second one, run after
# FILL_CHECK_MAX was set on the first (`stereo.density_check`: why).
WEAKENED = {"contrast x0.25": lambda x, k: contrast(x), "blur 2 px": lambda x, k: blurred(x)}
HELD_OUT = {"contrast x0.4, blur 1 px": lambda x, k: contrast(blurred(x, 1.0), 0.4),
            "noise 3 DN": lambda x, k: noisy(x, 3.0, k)}


def middlebury_cases(data: Path, variants: dict, existing: bool = True):
    for scene in sorted(p for p in data.iterdir() if (p / "calib.txt").is_file()):
        calib = read_middlebury_calib(scene / "calib.txt")
        left, right = read_image(scene / "im0.png"), read_image(scene / "im1.png")
        gt, nocc, z_gt = ground_truth(scene, calib)
        pairs = {"as is": (left, right), "relit (gain 0.7, gamma 1.3)": (left, relit(right))} if existing else {}
        pairs |= {name: (f(left, 0), f(right, 1)) for name, f in variants.items()}
        for variant, pair in pairs.items():
            yield scene.name, variant, (calib, *pair, nocc, z_gt, gt)


def render_cases(seeds=(0, 1)):
    from dstereo.synth.outdoor import OutdoorRig, outdoor_pair, true_disparity, visible_in_right

    rig = OutdoorRig()
    for seed in seeds:
        render = outdoor_pair(rig, seed)
        d_true = true_disparity(render, rig)
        yield (f"outdoor render {seed}", "contrast x0.25",
               (rig.calibration(), contrast(render.left), contrast(render.right), visible_in_right(render, rig),
                render.truth_left["depth"], d_true))


def board_plane(result):
    """(hull mask, plane disparity) of the chessboard (9 x 6 corners) on `result`'s rectified left image: a robust
    plane fit (four re-weightings at 3 robust stds) to its disparity over the corners' hull; None without a board."""
    import cv2

    from dstereo.stereo.pair_result import grey

    found, corners = cv2.findChessboardCorners(grey(result.left_rect), (9, 6))
    if not found:
        return None
    mask = np.zeros(result.disparity.shape, np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    hull = mask.astype(bool)
    d = result.disparity
    v, u = np.nonzero(hull & np.isfinite(d))
    basis = np.stack([np.ones_like(u), u, v], axis=1).astype(float)
    keep = np.ones(len(u), bool)
    for _ in range(4):
        coef = np.linalg.lstsq(basis[keep], d[v, u][keep].astype(float), rcond=None)[0]
        r = d[v, u] - basis @ coef
        keep = np.abs(r) <= 3 * max(MAD_TO_STD * np.median(np.abs(r)), 0.1)
    vv, uu = np.mgrid[:d.shape[0], :d.shape[1]]
    return hull, coef[0] + coef[1] * uu + coef[2] * vv


def real_rows(pairs_step=(("rig640", 5), ("opencv_stereo", 4))):
    """[(rig pair, {before, after: figures})] on the shared real rigs (the module: the board's plane as truth)."""
    from dstereo.io.calib_files import read_stereo_calibration
    from experiments.default_matching_real import DATA as REAL, pairs

    rows = []
    for rig, step in pairs_step:
        calib = read_stereo_calibration(REAL / rig / "intrinsics.yml")
        for name, left_path, right_path in list(pairs(rig))[::step]:
            left, right = read_image(left_path), read_image(right_path)
            runs = {n: reconstruct(n, calib, left, right, DEFAULT) for n in ("before", "after")}
            board = board_plane(runs["before"][0])
            figures = {}
            for n, (result, seconds) in runs.items():
                check = result.summary.get("density_check") or {}
                tries = check.get("tries") or []
                f = {"valid_pct": 100 * result.summary["valid_fraction"], "seconds": seconds,
                     "cost": result.summary["search_range"]["matching_cost"]["cost"],
                     "map_density_pct": 100 * tries[0]["density"] if tries else None,
                     "check_ratio": (tries[1].get("fill_check") or {}).get("ratio") if len(tries) > 1 else None,
                     "board_pct": None, "on_plane_pct": None, "filled_board": 0, "board_obs_pred": None}
                if board is not None:
                    hull, plane = board
                    est = hull & np.isfinite(result.disparity)
                    f["board_pct"] = 100 * est.sum() / hull.sum()
                    f["on_plane_pct"] = 100 * float(np.mean(np.abs(result.disparity[est] - plane[est]) <= 1.0))
                    if result.filled is not None:
                        filled = est & result.filled
                        f["filled_board"] = int(filled.sum())
                        if filled.sum() >= 100:
                            r = (result.disparity - plane)[filled].astype(np.float64)
                            rms = float(np.sqrt(np.mean(result.fill_sigma[filled] ** 2)))
                            f["board_obs_pred"] = robust_std(r) / rms
                figures[n] = f
            rows.append((f"{rig} {name}", figures))
            print(real_table(rows[-1:]).splitlines()[-1], flush=True)
    return rows


def real_table(rows) -> str:
    fmt = lambda v, spec=".1f": "-" if v is None else format(v, spec)  # noqa: E731
    text = ("| pair | grey levels' map density % | after: kept (check ratio) | valid % before / after | "
            "board with an estimate % before / after | of them within 1 px of the plane % before / after | "
            "filled board px after | filled board: robust std about the plane / RMS sigma | s before / after |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    for pair, r in rows:
        b, a = r["before"], r["after"]
        text += (f"| {pair} | {fmt(a['map_density_pct'])} | {a['cost']} ({fmt(a['check_ratio'], '.2f')}) | "
                 f"{b['valid_pct']:.1f} / {a['valid_pct']:.1f} | {fmt(b['board_pct'])} / {fmt(a['board_pct'])} | "
                 f"{fmt(b['on_plane_pct'])} / {fmt(a['on_plane_pct'])} | {a['filled_board']} | "
                 f"{fmt(a['board_obs_pred'], '.2f')} | {b['seconds']:.1f} / {a['seconds']:.1f} |\n")
    return text


def table(rows) -> str:
    names = list(CONFIGS)
    all_ = " / ".join(names)
    fmt = lambda v, spec=".2f": "-" if v is None else format(v, spec)  # noqa: E731
    each = lambda r, key, spec: " / ".join(fmt(r[n][key], spec) for n in names)  # noqa: E731
    text = (f"| scene | variant | grey levels' map density % | after: kept (check ratio) | density % {all_} | "
            f"median % {all_} | p90 % {all_} | filled % {all_} | filled obs / pred {all_} | s {all_} | "
            f"pass {all_} |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    for scene, variant, r in rows:
        text += (f"| {scene} | {variant} | {fmt(r['after']['map_density_pct'], '.1f')} | {r['after']['cost']} "
                 f"({fmt(r['after']['check_ratio'])}) | {each(r, 'density_pct', '.1f')} | "
                 f"{each(r, 'median_pct', '.2f')} | {each(r, 'p90_pct', '.2f')} | {each(r, 'filled_pct', '.1f')} | "
                 f"{each(r, 'obs_pred', '.2f')} | {each(r, 'seconds', '.1f')} | "
                 f"{' / '.join('yes' if passes(r[n]) else 'no' for n in names)} |\n")
    return text


def totals(rows, label: str) -> str:
    n = len(rows)
    met = {k: sum(passes(r[k]) for _, _, r in rows) for k in CONFIGS}
    sig = {k: (sum(r[k]["obs_pred"] is not None and 0.67 <= r[k]["obs_pred"] <= 1.5 for _, _, r in rows),
               sum(r[k]["obs_pred"] is not None for _, _, r in rows)) for k in CONFIGS}
    return (f"{label} ({n} rows): pass " + ", ".join(f"{k} {v}" for k, v in met.items())
            + "; filled obs / pred within 0.67..1.5: " + ", ".join(f"{k} {a} of {b} filled rows"
                                                                    for k, (a, b) in sig.items()) + ".")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--skip-renders", action="store_true")
    parser.add_argument("--only-real", action="store_true", help="the real rigs' table only")
    parser.add_argument("--held-out", action="store_true", help="the held-out harder cases only")
    args = parser.parse_args()
    load = os.getloadavg()
    if args.only_real:
        text = real_table(real_rows()) + (f"\nbefore: the default without the density check; after: the default. "
                                          f"Load average at the start {load[0]:.2f}, at the end "
                                          f"{os.getloadavg()[0]:.2f} (shared 2-core machine, `nice`).\n")
        print(text)
        if args.out is not None:
            args.out.write_text(text)
        return
    rows = []
    if args.held_out:
        cases = list(middlebury_cases(args.data, HELD_OUT, existing=False)) + list(render_cases((2, 3)))
    else:
        cases = list(middlebury_cases(args.data, WEAKENED)) + ([] if args.skip_renders else list(render_cases()))
    for scene, variant, case in cases:
        rows.append((scene, variant, run_case(*case)))
        print(table(rows[-1:]).splitlines()[-1], flush=True)
    existing = [r for r in rows if r[1].startswith(("as is", "relit"))]
    harder = [r for r in rows if not r[1].startswith(("as is", "relit"))]
    text = (table(rows) + "\n" + (totals(existing, "Existing Middlebury rows") + "\n\n" if existing else "")
            + totals(harder, "Harder cases (texture weakened; renders)" if not args.held_out else
                     "Held-out cases (run after the check's threshold was set)") + "\n\n"
            f"before: the default without the density check; after: the default (no flags); rank fill: `--cost rank "
            f"--fill`. grey levels' map density: the check's own figure (share of the pixels with a source in both "
            f"images and an SGBM block that is not blank (two grey levels or more) the grey levels matched, after "
            f"the rank check and before any fill; not the scored mask). "
            f"check ratio: the rank try's fills against the grey levels' matches ({density_check.FILL_CHECK_MAX:g} at "
            f"most to be kept; '-': not made, the rank try was not denser, or the check did not run). "
            f"s: seconds per reconstruction, one BLAS thread, under `nice` on a shared 2-core machine (load "
            f"average at the start {load[0]:.2f}, at the end {os.getloadavg()[0]:.2f}).\n")
    report(text, args.out)


if __name__ == "__main__":
    main()
