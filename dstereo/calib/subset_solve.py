"""The one subset runner: every subset of frames of a calibration problem, solved in batched chunks.

A subset is the full set with the other frames weighted 0, so it reuses the full set's compiled solver, unless
subsets are less than half the set, or the whole plan leaves out at least GATHER_DROPPED frame solves (C (n - m),
given as `plan_size` by the caller, who sees the whole plan where blocks of it arrive here): then carrying the
unused frames would cost more than a second executable, and the subsets' frames are gathered instead. Measured at
m = 16 of 20 (rig640, C = 4845, 19380 frame solves left out, the noise-unit stop): gathered 2.82 s against masked
3.37 s (load ~5, one core's worth), ~16 %, for a second executable to load from disk (~0.08 s) or, in a cold run,
to compile (~1.5-2 s, once per shape and code version). Every subset starts at the full set's solution (a few iterations from
its own optimum; each still converges to its own least-squares solution) and, where given, reuses the full
set's linearisation there instead of linearising its start again (one pass of about six saved). Chunks run on
`problem.threads()` threads; XLA runs one chunk's loop mostly on one core. Used by one camera, a stereo rig and
N cameras alike.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import jax
import numpy as np

from dstereo.calib.problem import Problem, chunk_rows, frame_bucket, run, threads
from dstereo.runtime import buckets
from dstereo.solver.lm import LMOptions, LMResult

# Subsets stop once the Gauss-Newton model puts every parameter within sqrt(2 eps) = 1e-2 of its own standard
# deviation of the subset's optimum, and then take the model's step to it (lm._decrement_stop): the point returned
# is within c / (1 - c) sqrt(2 eps) std of the optimum, c the Gauss-Newton contraction per step, so at most 1e-2 std
# for c <= 0.5. Measured on rig640 left (20 views, 4845 subsets each of m = 10, 16, 19 against tight solves): c
# 0.07-0.09 median, 0.29 at most, the subsets within 2.3e-3 std of their optimum (1e-3 at m = 16, where the
# earlier 1e-3 stop without the step left 1e-3 too). The thesis statistics work on the subsets' scatter, 0.4-1.3
# std there: the spread moved <= 0.2 %, the means <= 0.1 % of the spread. Against eps = 5e-7 it saves one pass of
# four in every chunk of subsets (a chunk runs until its slowest subset stops): 4845 subsets 2.25 -> 1.75 s. ftol =
# 1e-12 alone ran every subset two to three passes further (5-7 passes each). A second rule stops where the
# contraction estimated from two decrements already puts the returned point within the same bound
# (lm._decrement_stop): with it, rig640's 4845 subsets of 16 stop after 1 (5 %), 2 (85 %) or 3 (9 %) passes where
# this rule alone needed 2 or 3 (43 / 57 %), their largest error against tight solves 5e-3 std (7.5e-3 at m = 10),
# within the same 1e-2. A caller's explicit `decrement_tol` (0: off, tight ftol convergence) wins.
SUBSET_DECREMENT_TOL = 0.5e-4
# Gathered subsets from this many frame solves left out (C (n - m)): at ~14-28 us each (measured, module docstring)
# the saving passes a second executable's load from disk (~0.08 s) about 3000-6000 frame solves in; twice that
# for margin. C = 4845 of m = 16 of 20 gathers (19380), C = 1140 of 17 of 20 does not (3420).
GATHER_DROPPED = 10_000
# Passes every chunk of subsets makes together; subsets still running then continue in chunks of their own. A
# chunk's loop runs until its slowest subset stops, so one subset that needs a third pass made its whole chunk of
# ~20 pay for it. Measured at rig640 left (4845 subsets of 16 of 20): 9 % of them need a third pass (most chunks
# held one), 85 % stop at the second, 5 % at the first (`lm._decrement_stop`); 4845 subsets 1.70 -> 1.46 s (measured
# with CONTRACTION_SAFETY 2).
FIRST_PASSES = 2


class SubsetStart(NamedTuple):
    """The full set's solution every subset starts from: shared vector (G,), frame poses (F, 6), and optionally
    its linearisation there (residuals (F, R), normal blocks (F, P1, P1); `LMResult.residuals` / `.normal`)."""

    values: np.ndarray
    poses: np.ndarray
    normal: tuple[np.ndarray, np.ndarray] | None = None


def solve_frame_subsets(problem: Problem, obs: np.ndarray, r_weight: np.ndarray, shared, index: np.ndarray,
                        start: SubsetStart, options: LMOptions = LMOptions(lambda0=1e-6), progress=None,
                        n_threads: int | None = None, plan_size: int | None = None) -> LMResult:
    """Solve each row of `index` (C, m) (frame indices; a repeated index counts a frame twice: bootstrap) as its
    own problem. obs (F, K, n, 2) (NaN: unseen), r_weight (F, K 2n) the full set's residual weights (an outlier
    there is left out of every subset). Returns the stacked `LMResult` (C leading) without per-frame residuals
    and normal blocks (C = 5000 would keep ~400 MB). `plan_size`: subsets in the whole plan these rows are a block of
    (chooses gathered frames, `gathers`; default: these rows alone)."""
    if options.decrement_tol is None:
        options = options._replace(decrement_tol=SUBSET_DECREMENT_TOL)
    index = np.asarray(index)
    n_sub, m = index.shape
    n_frames, n_obs = len(obs), int(np.prod(np.shape(obs)[1:3]))
    obs, poses = np.asarray(obs, float), np.asarray(start.poses, float)
    gathered = gathers(m, n_frames, n_sub if plan_size is None else plan_size)
    normal = start.normal

    if not gathered:
        # Every chunk of a masked plan shares the start, frames and linearisation; only the weights differ.
        # Put them on the device once, at the full chunk size, instead of copying them for every chunk.
        # At the frames' bucket (`problem.run`): padded frames unseen (NaN), of residual weight 0, at frame 0's pose.
        bucket = frame_bucket(n_frames)
        full_rows = chunk_rows(bucket, n_obs, problem)
        pad = lambda a, fill=None: buckets.pad_axis(a, bucket, 0, fill)  # noqa: E731 - one problem's frames
        put = lambda a: jax.device_put(np.ascontiguousarray(np.broadcast_to(a, (full_rows, *np.shape(a)))))  # noqa: E731
        common = (put(start.values), put(pad(poses)), put(pad(obs, np.nan)))
        lam_all = put(np.float64(options.lambda0))
        normal_all = None if normal is None else tuple(put(pad(a, 0.0)) for a in normal)
        r_weight_all = put(pad(r_weight, 0.0))

    def chunk_args(rows):
        c = len(rows)
        if gathered:
            g0 = np.broadcast_to(start.values, (c, len(start.values)))
            start_ne = None if normal is None else tuple(a[rows] for a in normal)
            return (g0, poses[rows], obs[rows], np.ones((c, m)), np.full(c, options.lambda0)), start_ne, r_weight[rows]
        return (*common, frame_weights(rows), lam_all), normal_all, r_weight_all

    def frame_weights(rows):
        weight = np.zeros((len(rows), n_frames))
        np.add.at(weight, (np.arange(len(rows))[:, None], rows), 1.0)  # counts: bootstrap resamples repeat frames
        return weight

    def first_round(rows):
        """The chunk's subsets for FIRST_PASSES passes; which are still running, and their point, passes and LM
        damping (those rows only)."""
        args, start_ne, r_w = chunk_args(rows)
        out = run(problem, options, *args, shared, start_ne, r_w, max_passes=FIRST_PASSES)
        running = np.flatnonzero(out.status == 0)
        held = tuple(a[running] for a in (out.g, out.p, out.iterations, out.damping))
        return out._replace(normal=None, residuals=None), running, held

    def second_round(rows, held):
        """Continue subsets (index rows) from where the first round left them (held: their g, p, iterations and LM
        damping; restarted at the initial damping, hard problems (a near-singular rational model) failed more
        often: 13 of 300 subsets against 6, measured on opencv_stereo right, m = 6)."""
        c = len(rows)
        if gathered:
            frames, weight, r_w = obs[rows], np.ones((c, m)), r_weight[rows]
        else:
            frames, weight = np.broadcast_to(obs, (c, *obs.shape)), frame_weights(rows)
            r_w = np.broadcast_to(r_weight, (c, *np.shape(r_weight)))
        g, p, iterations, damping = held
        out = run(problem, options, g, p, frames, weight, damping, shared, None, r_w)
        # a fresh start: its pass 0 linearises their point again (not counted: iterations are steps)
        return out._replace(normal=None, residuals=None, iterations=out.iterations + iterations)

    rows = chunk_rows(m if gathered else n_frames, n_obs, problem)
    starts = range(0, n_sub, rows)
    outs, late, held, done = [], [], [], 0
    with ThreadPoolExecutor(min(threads(n_threads), len(starts))) as pool:
        for at, (out, running, kept) in zip(starts, pool.map(first_round, (index[c: c + rows] for c in starts))):
            outs.append(out)
            late.append(at + running)
            held.append(kept)
            done += len(out.status) - len(running)
            if progress is not None:
                progress(done, n_sub)
        result = jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)
        late = np.concatenate(late)
        if len(late):
            # The subsets the first round left running, in chunks of their own (module docstring).
            held = tuple(np.concatenate(a) for a in zip(*held))
            blocks = [slice(c, c + rows) for c in range(0, len(late), rows)]

            def continue_block(b):
                return second_round(index[late[b]], tuple(a[b] for a in held))

            for b, out in zip(blocks, pool.map(continue_block, blocks)):
                for name, value in out._asdict().items():
                    if value is not None:
                        getattr(result, name)[late[b]] = value
                done += len(late[b])
                if progress is not None:
                    progress(done, n_sub)
    return result


def chunk_size(problem_frames: int, m: int, n_obs: int, plan_size: int | None = None) -> int:
    """The chunk `solve_frame_subsets` uses for subsets of m of `problem_frames` frames of n_obs corner
    observations each, in a plan of `plan_size` subsets (callers size their blocks of subsets to a multiple of it)."""
    return chunk_rows(m if gathers(m, problem_frames, plan_size) else problem_frames, n_obs)


def gathers(m: int, n_frames: int, plan_size: int | None = None) -> bool:
    """Whether subsets of m of n_frames frames, `plan_size` of them in the whole plan, are gathered (module
    docstring): less than half the frames, or at least GATHER_DROPPED frame solves left out in all."""
    return 2 * m < n_frames or (plan_size is not None and plan_size * (n_frames - m) >= GATHER_DROPPED)
