"""`--model auto`: the lens model chosen by how well it predicts views it was not fitted to.

For each candidate (CANDIDATES: k1k2, the 5-coefficient default, fisheye, rational, splined) the full set is solved, then
the views are split into folds (leave-one-view-out up to MAX_FOLDS views, else MAX_FOLDS folds of equal size):
each fold's training set is the full set with the fold's views weighted 0, so all folds of one model are one batch
of the same compiled solver as the full set (`mono.solve_subsets`; one compile per model). Each held-out view's
board pose is then refitted for that fold's fixed camera, and the RMS of its corners is the held-out error: the
error a user meets on a view the calibration never saw. Training RMS cannot do this: a richer model always
fits the training corners better, and on fisheye640 the 5-coefficient model's held-out error is 10x its RMS.

Choice rule (stated in the report):
1. usable: the full solve and every fold converged and every held-out error is finite;
2. best: the usable candidate of the lowest held-out RMS;
3. within noise: a candidate whose held-out mean square error exceeds the best's by at most one standard error
   of the paired per-view difference (the one-standard-error rule; the views are the samples) and whose training
   RMS is within FIT_MARGIN of the best's (the residual left on the corners must not visibly grow);
4. chosen: among those, the identifiable one (conditioning check) with the fewest parameters; ties: lower
   held-out RMS. Fewer parameters unless more buy a held-out error lower by more than its noise.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.errors import DstereoError
from dstereo.models.distortion import PRESETS, lens_model, model_label

PARAMETRIC: tuple[str, ...] = ("k1k2", "default", "fisheye", "rational")  # presets, fewest parameters first
# ... and the splined lens (models/splined.py, its default grid) for lenses none of them fits: with the most
# parameters it is chosen only where its held-out error beats theirs by more than the noise
CANDIDATES: tuple[str, ...] = PARAMETRIC + ("splined",)
MAX_FOLDS = 30  # up to this many views: leave one view out; beyond: this many folds of equal size
FIT_MARGIN = 0.01  # a chosen model's training RMS may exceed the held-out-best model's by at most 1 %
SPLINE_GATE_P = 1e-3  # residual-pattern p-value below which the splined lens is worth its minutes of solving
SPLINE_GATE_Z = 3.1  # ... or neighbour-correlation z above which (one-sided p ~ 1e-3 when errors are independent)
POSE_ITERATIONS = 40  # LM iterations of a held-out pose refit, from the full-set pose (converges in < 10)
WEAK_Z = 2.0  # a coefficient whose |value| is below WEAK_Z of its standard deviations is not told from zero
# Residual structure: corners in STRUCTURE_RINGS rings of equal count around the principal point; a ring whose
# mean radial residual (per view, then over views) is STRUCTURE_Z standard errors from zero shows a distortion
# the model does not follow. Measured (the cameras of the since-removed experiments/model_auto.py): fisheye640 with k1k2 /
# 5 coefficients: up to 5.2 / 4.0; models that fit (fisheye640 fisheye and rational, the narrow lenses of
# opencv_stereo and rig640 with every candidate): at most 2.3.
STRUCTURE_RINGS, STRUCTURE_Z, STRUCTURE_MIN_VIEWS = 5, 3.5, 6


@dataclass
class Candidate:
    """One model's entry in the table."""

    preset: str
    free: tuple[str, ...]
    n_params: int  # shared parameters: fx fy cx cy + the free coefficients
    rms: float  # full-set training RMS px
    heldout_rms: float  # sqrt(mean over held-out views of their corners' mean square error) px
    heldout_mse: np.ndarray  # (V,) per view, NaN for views never held out
    converged: bool  # full solve and every fold
    identifiable: bool
    condition_number: float
    weakest: tuple[str, float]  # (coefficient, |value| / std) of the least determined free coefficient
    diff_mse: float = float("nan")  # mean paired held-out MSE minus the best's, px^2
    diff_se: float = float("nan")  # its standard error
    note: str = ""
    solution: object = field(default=None, repr=False)  # calib.solution.Solution of the full set

    def identifiability_text(self) -> str:
        cond = f"cond {self.condition_number:.1e}"
        name, z = self.weakest
        weak = f", weakest {name}: value/sigma {z:.2g}" if name else ""  # no '|': it splits a markdown cell
        return f"{'yes' if self.identifiable else 'NO'} ({cond}{weak})"


@dataclass
class ModelChoice:
    candidates: list[Candidate]
    chosen: str  # preset name
    best: str  # lowest held-out RMS
    folds: int
    heldout_views: int
    rule: str
    timings: dict = field(default_factory=dict)

    @property
    def chosen_candidate(self) -> Candidate:
        return next(c for c in self.candidates if c.preset == self.chosen)

    def as_dict(self) -> dict:
        return {"chosen": self.chosen, "chosen_model": list(self.chosen_candidate.free),
                "lowest_heldout": self.best, "folds": self.folds, "heldout_views": self.heldout_views,
                "rule": self.rule, "timings": dict(self.timings),
                "candidates": [{"preset": c.preset, "model": list(c.free), "parameters": c.n_params,
                                "rms_px": c.rms, "heldout_rms_px": c.heldout_rms, "converged": c.converged,
                                "identifiable": c.identifiable, "condition_number": c.condition_number,
                                "weakest_coefficient": c.weakest[0] or None, "weakest_value_over_sigma": c.weakest[1],
                                "heldout_mse_minus_best_px2": c.diff_mse, "standard_error_px2": c.diff_se,
                                "chosen": c.preset == self.chosen, "note": c.note} for c in self.candidates]}

    def table_markdown(self) -> list[str]:
        lines = ["| model | parameters | RMS px | held-out RMS px | held-out MSE - best (+- 1 SE) px^2 | "
                 "identifiable | chosen |", "|---|---|---|---|---|---|---|"]
        for c in self.candidates:
            diff = "best" if c.preset == self.best else (
                f"{c.diff_mse:.2e} +- {c.diff_se:.1e}" if np.isfinite(c.diff_mse) else "-")
            mark = "**chosen**" if c.preset == self.chosen else (c.note or "")
            lines.append(f"| {c.preset} ({model_label(c.free)}) | {c.n_params} | {c.rms:.4f} | {c.heldout_rms:.4f} | "
                         f"{diff} | {c.identifiability_text()} | {mark} |")
        return lines


RULE = ("lowest held-out RMS defines the best; candidates whose held-out MSE is within one standard error (paired "
        f"over views) of the best's and whose RMS is within {100 * FIT_MARGIN:g} % of the best's are within noise; "
        "of those the identifiable one with the fewest parameters is chosen")


def fold_plan(n_views: int):
    """(SubsetPlan of the training views, (F, h) held-out views per fold): leave one view out up to MAX_FOLDS
    views, else MAX_FOLDS folds of h = n // MAX_FOLDS views (every 1/MAX_FOLDS-th view in order; the remainder is
    always trained on, so every training set has the same size and all folds share one compiled solver)."""
    from dstereo.calib.subsets import SubsetPlan

    h = max(1, n_views // MAX_FOLDS)
    folds = n_views // h if h == 1 else MAX_FOLDS
    held = np.arange(folds * h).reshape(h, folds).T  # fold f holds views f, f + F, f + 2F, ...
    train = np.stack([np.setdiff1d(np.arange(n_views), row) for row in held])
    return SubsetPlan(train, folds, True, 0), held


@functools.lru_cache(maxsize=None)
def _pose_refit(free: tuple[str, ...]):
    """Compiled: per view, its pose refitted by LM for its own fixed camera (k, coeffs); returns the SSE."""
    from dstereo.calib.mono import lens_functions
    from dstereo.models.pose import rodrigues

    project = lens_functions(free)[0]

    def one(pose0, k, coeffs, obs_v, obj):
        def res(pose):
            p = obj @ rodrigues(pose[:3]).T + pose[3:6]
            return (jax.vmap(project, in_axes=(None, None, 0))(k, coeffs, p) - obs_v).ravel()

        def body(_, state):
            pose, lam, cost = state
            r, jac = res(pose), jax.jacfwd(res)(pose)
            a = jac.T @ jac
            trial = pose + jnp.linalg.solve(a + lam * jnp.diag(jnp.diag(a) + 1e-12), -(jac.T @ r))
            c = jnp.sum(res(trial) ** 2)
            better = jnp.isfinite(c) & (c < cost)
            return (jnp.where(better, trial, pose), jnp.where(better, lam * 0.3, lam * 10.0),
                    jnp.where(better, c, cost))

        return jax.lax.fori_loop(0, POSE_ITERATIONS, body, (pose0, 1e-3, jnp.sum(res(pose0) ** 2)))[2]

    from dstereo.runtime import buckets  # one program per bucket of held-out view counts: rows padded with copies

    return buckets.per_row(jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None))), (0, 1, 2, 3), kind=("pose_refit", (free,)))


def evaluate(preset: str, obj, obs, image_size) -> Candidate:
    """Full-set solve, the folds as one batch, held-out pose refits: one candidate's row."""
    from dstereo.calib.mono import calibrate_full, solve_subsets
    from dstereo.models.distortion import coeff_slots

    free = PRESETS[preset]
    full = calibrate_full(obj, obs, image_size, free=free)
    plan, held = fold_plan(len(obs))
    sub = solve_subsets(obj, obs, plan, full)
    coeffs = np.zeros((len(plan), len(coeff_slots(free))))  # 8, or a splined lens's knots
    coeffs[:, [coeff_slots(free).index(n) for n in free]] = sub.values[:, 4:]
    f_idx = np.repeat(np.arange(len(plan)), held.shape[1])
    views = held.ravel()
    sse = np.asarray(_pose_refit(free)(full.poses[views], sub.values[f_idx, :4], coeffs[f_idx], obs[views], obj))
    mse = np.full(len(obs), np.nan)
    mse[views] = sse / obs.shape[1]  # per corner, both coordinates: the square of OpenCV's RMS
    z = np.abs(full.values[4:]) / np.maximum(full.std[4:], 1e-300)
    weakest = (free[int(np.argmin(z))], float(np.min(z))) if free else ("", float("inf"))
    converged = bool(full.converged and np.all(sub.converged) and np.all(np.isfinite(sse)))
    note = "" if converged else (f"did not converge (full set: {full.status_text}; {int(np.sum(~sub.converged))} of "
                                 f"{len(plan)} folds unconverged): not a candidate")
    return Candidate(preset=preset, free=free, n_params=4 + len(free), rms=float(full.rms),
                     heldout_rms=float(np.sqrt(np.nanmean(mse))), heldout_mse=mse, converged=converged,
                     identifiable=bool(full.conditioning.identifiable),
                     condition_number=float(full.conditioning.condition_number), weakest=weakest, note=note,
                     solution=full)


def choose(candidates: list[Candidate]) -> tuple[str, str]:
    """(chosen, best) preset names by the module's rule; fills each candidate's diff_mse, diff_se and note."""
    usable = [c for c in candidates if c.converged and np.isfinite(c.heldout_rms)]
    for c in candidates:
        if c not in usable and not c.note:
            c.note = "did not converge on every fold: not a candidate"
    if not usable:
        raise DstereoError("model auto: no candidate lens model converged on every fold; choose one with `model` "
                           "and check the images (see the full-set warnings)")
    best = min(usable, key=lambda c: c.heldout_rms)
    near = []
    for c in usable:
        d = (c.heldout_mse - best.heldout_mse)[np.isfinite(best.heldout_mse)]
        c.diff_mse = float(np.mean(d))
        c.diff_se = float(np.std(d, ddof=1) / np.sqrt(len(d))) if c is not best and len(d) > 1 else 0.0
        if c.diff_mse > c.diff_se:
            c.note = "held-out error above the best's by more than its noise"
        elif c.rms > (1 + FIT_MARGIN) * best.rms:
            c.note = f"RMS more than {100 * FIT_MARGIN:g} % above the best's"
        else:
            near.append(c)
    chosen = min(near, key=lambda c: (not c.identifiable, c.n_params, c.heldout_rms))
    for c in near:
        if c is not chosen:
            c.note = "within noise of the best; more parameters" if c.n_params > chosen.n_params else "within noise"
    if best is not chosen and not best.note:
        best.note = "lowest held-out error"
    return chosen.preset, best.preset


def choose_model(obj, obs, image_size, candidates: tuple[str, ...] = CANDIDATES, progress=None) -> ModelChoice:
    """Evaluate every candidate preset on the views (obj (n, 3), obs (V, n, 2) px) and choose one."""
    obj, obs = np.asarray(obj, float), np.asarray(obs, float)
    if len(obs) < 4:
        raise DstereoError(f"model auto: {len(obs)} usable views; choosing a model by held-out views needs at "
                           "least 4 (better 10+): choose one with `model`")
    t0 = time.perf_counter()
    rows = []
    for i, preset in enumerate(candidates):
        if progress is not None:
            progress(i, len(candidates))
        skip = _spline_not_needed(rows, obs) if preset == "splined" else None
        if skip is not None:
            rows.append(_left_out(preset, len(obs), skip))
            continue
        try:
            rows.append(evaluate(preset, obj, obs, image_size))
        except DstereoError as exc:  # a model whose full-set solve fails outright is out, with the reason
            rows.append(_left_out(preset, len(obs), f"failed: {exc}"))
    if progress is not None:
        progress(len(candidates), len(candidates))
    chosen, best = choose(rows)
    _, held = fold_plan(len(obs))
    return ModelChoice(rows, chosen, best, folds=len(held), heldout_views=int(held.size), rule=RULE,
                       timings={"model_choice_s": time.perf_counter() - t0})


def _left_out(preset: str, n_views: int, note: str) -> Candidate:
    return Candidate(preset, PRESETS[preset], 4 + len(PRESETS[preset]), float("nan"), float("nan"),
                     np.full(n_views, np.nan), False, False, float("nan"), ("", float("nan")), note=note)


def _spline_not_needed(rows: list[Candidate], obs) -> str | None:
    """Why the splined lens is not evaluated (None: evaluate it). Its folds cost minutes where a parametric
    model's cost seconds, and it can only win where the best parametric model leaves structure: so it is solved
    when the best parametric candidate's residuals show a pattern across the image (`calib.misfit`, p below
    SPLINE_GATE_P, far looser than the warning's 1e-6) or vary smoothly along the board (neighbouring corners'
    residuals alike: z above SPLINE_GATE_Z), or when no parametric candidate is usable."""
    from dstereo.calib.misfit import neighbour_correlation, solution_pattern

    usable = [c for c in rows if c.converged and np.isfinite(c.heldout_rms) and c.solution is not None]
    if not usable:
        return None
    best = min(usable, key=lambda c: c.heldout_rms)
    sol = best.solution
    pattern = solution_pattern(obs, sol)
    rho, z = neighbour_correlation(obs, sol.residuals[:, 0], sol.camera_inliers())
    if pattern.p_value < SPLINE_GATE_P or not z <= SPLINE_GATE_Z:
        return None
    return (f"not evaluated: the best parametric model ({best.preset}) leaves residuals like noise (no pattern "
            f"across the image, p = {pattern.p_value:.2g}; neighbouring corners' residuals correlate {rho:+.2f}, "
            f"z = {z:.1f} <= {SPLINE_GATE_Z:g}), so no spline can predict held-out views better")


def choice_warning(choice: ModelChoice) -> str | None:
    """A warning when the chosen model is not identifiable (chosen anyway: nothing simpler predicts as well)."""
    c = choice.chosen_candidate
    if c.identifiable:
        return None
    return (f"model auto chose {c.preset} ({model_label(c.free)}), which is not identifiable from these views "
            f"({c.identifiability_text()}), because no simpler model predicts held-out views as well "
            f"({c.heldout_rms:.4f} px); add views that tilt the board and fill the image corners")


def residual_structure(obs, residuals, k) -> str | None:
    """A sentence when the full-set residuals (V, n, 2) px of corners obs (V, n, 2) show a radial pattern around
    the principal point k[2:4] that the lens model leaves (see STRUCTURE_*), else None."""
    obs, residuals = np.asarray(obs, float), np.asarray(residuals, float)
    d = obs - np.asarray(k, float)[2:4]
    r = np.linalg.norm(d, axis=2)
    radial = np.sum(residuals * d, axis=2) / np.maximum(r, 1e-9)  # (V, n) outward component
    edges = np.quantile(r, np.linspace(0.0, 1.0, STRUCTURE_RINGS + 1))
    worst = None
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (r >= lo) & (r <= hi)
        per_view = np.array([radial[v][inside[v]].mean() for v in range(len(obs)) if inside[v].sum() >= 3])
        if len(per_view) < STRUCTURE_MIN_VIEWS:
            continue
        z = per_view.mean() / max(per_view.std(ddof=1) / np.sqrt(len(per_view)), 1e-12)
        if abs(z) > STRUCTURE_Z and (worst is None or abs(z) > abs(worst[2])):
            worst = (lo, hi, z, per_view.mean())
    if worst is None:
        return None
    lo, hi, z, mean = worst
    return (f"the residuals show a radial pattern the lens model does not follow: corners {lo:.0f}-{hi:.0f} px from "
            f"the principal point sit {mean:+.3f} px off radially on average ({z:+.1f} standard errors over views); "
            "let held-out views choose the lens model (--model auto)")


def is_fisheye(preset: str) -> bool:
    return lens_model(PRESETS[preset]) == "fisheye"
