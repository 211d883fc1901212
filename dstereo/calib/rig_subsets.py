"""Subsets of a K-camera rig's frames and the thesis's stereo steps on every adjacent camera pair (`--cameras`).

With images per set m, the rig with every camera held at its own calibration (the stereo job's subsets hold the
intrinsics too) is solved on every C(F, m) subset of frames, or the capped sample, by the one subset runner
(`multiview.solve_view_subsets`). Each adjacent pair (a, b) gets the thesis's stereo columns
(`STEP_COLUMNS`) of b's pose relative to a in every subset: Tnorm, Tx, ..., RVz, and stereo_re, the mean over
the subset's frames of each frame's RMS over the two cameras' inlier corners; the columns are named `NAME@a-b`. A
stereo step NAME=MAX filters on NAME of every pair at once: a subset leaves when any pair's value lies outside, so
with two cameras it is the stereo job's step. The frames in no surviving subset then leave the rig solve: the
written rig is the survivors' solve, as for one camera and a stereo pair.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dstereo.calib.final_solution import surviving_views
from dstereo.calib.multiview import as_solved, solve_view_subsets
from dstereo.calib.solution import Solution
from dstereo.calib.subsets import SubsetSolutions
from dstereo.calib.problem import Problem, WARP_SIZE, batched_residuals, residual_weights, sagged_board, shared_data
from dstereo.runtime import buckets
from dstereo.calib.robust_steps import FilterResult, run_steps
from dstereo.config.steps import Step, is_absolute
from dstereo.errors import DstereoError
from dstereo.models.pose import rotation_vectors

# Thesis Figure 5.14's stereo step parameters, the named columns of a pair in a subset table.
STEP_COLUMNS: tuple[str, ...] = ("stereo_re", "Tnorm", "Tx", "Ty", "Tz", "RVnorm", "RVx", "RVy", "RVz")
SEP = "@"
RESIDUAL_BLOCK = 256  # subsets whose residuals are evaluated at once (C x m x K x 2n floats)


def column_names(labels, pairs) -> tuple[str, ...]:
    return tuple(f"{name}{SEP}{labels[a]}-{labels[b]}" for a, b in pairs for name in STEP_COLUMNS)


def pair_steps(steps, labels, pairs) -> list[Step]:
    """Each stereo step on every pair's columns at once (module docstring)."""
    out = []
    for step in steps:
        params, limits = [], []
        for name, limit in zip(step.parameters, step.max_error):
            for a, b in pairs:
                params.append(f"{name}{SEP}{labels[a]}-{labels[b]}")
                limits.append(limit)
        out.append(Step(tuple(params), tuple(limits), step.min_subsets))
    return out


def _relative(values: np.ndarray, k: int, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3) rotation vector and (C, 3) translation of camera b relative to a (x_b = R x_a + T) of every subset;
    values hold cameras 1..K-1's poses in the reference first (camera 0 is the reference)."""
    ext = np.concatenate([np.zeros((len(values), 1, 6)), values[:, :6 * (k - 1)].reshape(len(values), k - 1, 6)], 1)
    r_a, r_b = Rotation.from_rotvec(ext[:, a, :3]), Rotation.from_rotvec(ext[:, b, :3])
    r = r_b * r_a.inv()
    return rotation_vectors(r.as_matrix()), ext[:, b, 3:] - r.apply(ext[:, a, 3:])  # the one rotation log


def _pair_rms(subs: SubsetSolutions, start: Solution, obj, obs, weights, pairs) -> np.ndarray:
    """(C, P) each pair's stereo_re in every subset (module docstring); held-sag columns are not parameters."""
    k, n = obs.shape[1], obs.shape[2]
    sag = start.board_sag
    board = obj if sag is None else sagged_board(obj, sag)
    g = subs.values[:, :-WARP_SIZE] if sag is not None else subs.values
    problem = Problem.of([tuple(c.dist.free) for c in start.cameras], refined=False)
    shared = shared_data(board, np.stack([np.asarray(c.k) for c in start.cameras]),
                         np.stack([np.asarray(c.dist.coeffs) for c in start.cameras]))
    residual = batched_residuals(problem)
    out = []
    # one program for every plan: blocks of RESIDUAL_BLOCK subsets (the last one padded with copies of its first)
    # and m frames padded to their bucket (runtime/buckets.py; copies of the first frame); the padding is cut off
    size = buckets.views(subs.index.shape[1])
    buckets.note("rig_residuals", (problem, shared, g.shape[1]), tag=(problem, g.shape[1], obs.shape[1:]))
    pad = lambda a: buckets.pad_axis(buckets.pad_rows(a, RESIDUAL_BLOCK), size, 1)  # noqa: E731
    for c in range(0, len(g), RESIDUAL_BLOCK):
        rows = subs.index[c:c + RESIDUAL_BLOCK]
        w = weights[rows]  # (C, m, K 2n)
        r = np.asarray(residual(buckets.pad_rows(g[c:c + RESIDUAL_BLOCK], RESIDUAL_BLOCK),
                                pad(subs.poses[c:c + RESIDUAL_BLOCK]), pad(obs[rows]), shared))
        r = r[:len(rows), :rows.shape[1]] * w
        sq = np.sum((r ** 2).reshape(*r.shape[:2], k, 2 * n), axis=-1)  # (C, m, K)
        seen = np.sum(w.reshape(*w.shape[:2], k, 2 * n), axis=-1) / 2  # inlier corners
        per = []
        for a, b in pairs:
            with np.errstate(invalid="ignore", divide="ignore"):
                frame = np.sqrt((sq[..., a] + sq[..., b]) / (seen[..., a] + seen[..., b]))
            per.append(np.nanmean(np.where(np.isfinite(frame), frame, np.nan), axis=1))
        out.append(np.stack(per, axis=1))
    return np.concatenate(out)


def subset_table(subs: SubsetSolutions, start: Solution, obj, obs, visible, inliers,
                 pairs) -> np.ndarray:
    """(C, 9 P) the stereo columns of every pair in `column_names` order."""
    k = visible.shape[1]
    obs, inliers = as_solved(obs, inliers, start.flipped)  # the full solve re-read these views reversed; so do these
    data = np.where(visible[:, :, None, None], obs, np.nan)
    mask = visible[:, :, None] if inliers is None else visible[:, :, None] & inliers
    weights = residual_weights(np.broadcast_to(mask, obs.shape[:3]))
    re = _pair_rms(subs, start, obj, data, weights, pairs)
    cols = []
    for p, (a, b) in enumerate(pairs):
        rv, t = _relative(subs.values, k, a, b)
        named = {"stereo_re": re[:, p], "Tnorm": np.linalg.norm(t, axis=1), "Tx": t[:, 0], "Ty": t[:, 1],
                 "Tz": t[:, 2], "RVnorm": np.linalg.norm(rv, axis=1), "RVx": rv[:, 0], "RVy": rv[:, 1],
                 "RVz": rv[:, 2]}
        cols += [named[name] for name in STEP_COLUMNS]
    return np.column_stack(cols)


@dataclass
class RigSubsets:
    """The rig's frame subsets, the stereo steps on them and which frames survive."""

    plan: object  # calib.subsets.SubsetPlan
    columns: tuple[str, ...]
    filtering: FilterResult
    frames: np.ndarray  # (F,) bool: frames in at least one surviving subset
    left_out: list[str]  # the names of the others
    warnings: list[str]
    seconds: float

    def stats(self) -> dict[str, dict[str, float]]:
        return self.filtering.stats(len(self.filtering.steps))

    def as_dict(self) -> dict:
        kept = int(self.filtering.survivors.sum())
        return {"subsets": len(self.plan), "per_set": int(self.plan.per_set), "exhaustive": bool(self.plan.exhaustive),
                "usable": int(self.filtering.usable.sum()), "surviving": kept,
                "steps": [s.message for s in self.filtering.steps],
                "left_out_frames": list(self.left_out),
                "statistics": self.stats(), "seconds": self.seconds}

    def lines(self) -> list[str]:
        usable, kept = int(self.filtering.usable.sum()), int(self.filtering.survivors.sum())
        out = [f"rig subsets: {len(self.plan)} of m = {self.plan.per_set} frames, {usable} converged, {kept} "
               f"survive the stereo steps; {len(self.left_out)} frame(s) in no surviving subset"
               + (f" left the rig solve ({', '.join(self.left_out[:6])}{', ...' if len(self.left_out) > 6 else ''})"
                  if self.left_out else "")]
        return out + [f"  rig {s.message}" for s in self.filtering.steps]


def run_rig_subsets(config, start: Solution, obj, obs, visible, inliers, labels, frame_names,
                    scratch=None, progress=None) -> RigSubsets:
    """Solve the rig's frame subsets from `start` (the held solve), filter them by the configuration's stereo
    steps on every adjacent pair, and find the frames that survive. Raises DstereoError when no subset converges
    or a step would leave none."""
    from dstereo.calib.subset_runs import NOTE_ABOVE, check_subset_run, solve_in_blocks
    from dstereo.calib.subset_solve import chunk_size
    from dstereo.calib.subsets import plan_subsets

    t0 = time.perf_counter()
    n_frames, k = visible.shape
    pairs = [(a, a + 1) for a in range(k - 1)]
    columns = column_names(labels, pairs)
    check_subset_run(n_frames, config.per_set, config.max_subsets, len(columns) + len(start.names), scratch,
                     getattr(progress, "note", None), label="rig ")
    plan = plan_subsets(n_frames, config.per_set, cap=config.max_subsets, seed=config.seed)
    report = None if progress is None else (lambda d, n: progress("rig subsets", d, n))

    def solve_block(block, block_progress):
        subs = solve_view_subsets(obj, obs, visible, block.index, start, progress=block_progress, inliers=inliers)
        return subset_table(subs, start, obj, obs, visible, inliers, pairs), subs.status, None

    # block by block (calib/subset_runs.py): bounded memory, and on a Dask cluster where the command says so
    table, _ = solve_in_blocks(plan, columns, solve_block,
                               chunk_size(n_frames, plan.per_set, int(np.prod(obs.shape[1:3])), len(plan)),
                               scratch, progress=report,
                               note=getattr(progress, "note", None) if len(plan) > NOTE_ABOVE else None,
                               key=(obj, obs, visible, "all" if inliers is None else inliers, start.values,
                                    start.poses, tuple(start.names)))
    usable = table.status > 0
    for j in range(len(columns)):
        usable &= np.isfinite(table.column(j))
    warnings = []
    if not usable.any():
        raise DstereoError(f"none of the {len(plan)} rig subset solves converged (m = {plan.per_set} frames); raise "
                           "`per_set` or check the frames")
    if not usable.all():
        warnings.append(f"{int((~usable).sum())} of {len(plan)} rig subset solves did not converge (or a camera saw "
                        "none of their frames) and are left out of the statistics")
    absolute = tuple(c for c in columns if is_absolute(c))  # stereo_re@a-b: px, as the stereo job's stereo_re
    filtering = run_steps(table, columns, pair_steps(config.stereo_steps, labels, pairs), usable, config.min_subsets,
                          absolute=absolute)
    warnings += [f"rig {s.message}" for s in filtering.steps if s.stopped_by_minimum]
    frames = surviving_views(filtering, plan, n_frames)
    left_out = [frame_names[i] for i in np.flatnonzero(~frames)]
    return RigSubsets(plan, columns, filtering, frames, left_out, warnings, time.perf_counter() - t0)
