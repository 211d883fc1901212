"""The one calibration problem: K cameras, a planar board, frames; its residuals, Jacobian and compiled solver.

A frame is one board pose, T_ref_board (rvec, tvec), seen by any subset of the K cameras; camera 0 is the
reference, camera c > 0 sits at x_c = R_c x_ref + T_c. The solver's shared vector is, in this order:

    [rvec_1, T_1, ..., rvec_{K-1}, T_{K-1}]  then, for each camera whose intrinsics are refined,
    [fx, fy, cx, cy, <its free distortion coefficients>]

so one camera (K = 1) is `Camera.free_vector()` and a stereo rig (K = 2) is [rig, left, right] (or the rig alone
with intrinsics held: the thesis's fixed-intrinsics stereo path). A frame's residuals are camera-major, then
corner, then (x, y). A corner a camera did not see is NaN in the observations: its residual and Jacobian are 0
(`jnp.where`, so an unseen camera's projection may be anything, even behind the camera) and callers give it
weight 0 (`residual_weights`), which also leaves it out of the residual count.

Compiled functions are cached per `Problem` (static: lens models, which cameras are refined) and options, so a
process compiles each shape once.
"""

from __future__ import annotations

import functools
import os
import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dstereo.runtime import watchdog
from dstereo.runtime.jax_workarounds import CALL_POINTS, MAX_CHUNK, MAX_CONCURRENT_CALLS
from dstereo.models import board, camera, fisheye, splined
from dstereo.models.distortion import coeff_slots, lens_model, with_free
from dstereo.models.pose import rodrigues, rodrigues_jacobian
from dstereo.runtime import aot, buckets
from dstereo.solver.lm import COMPILE_OPTIONS, LMOptions, solve_structured_batch

POSE_SIZE = 6  # rvec, tvec: of a frame's board pose and of a camera's extrinsics
WARP_SIZE = 2  # the board's sag along its x and y
WARP_NAMES = ("board_sag_x", "board_sag_y")


class CameraSpec(NamedTuple):
    """One camera of a problem: the distortion coefficients it solves (they name its lens model) and whether
    its intrinsics are refined at all (False: held at the values given in `shared`)."""

    free: tuple[str, ...]
    refined: bool = True

    @property
    def size(self) -> int:
        return 4 + len(self.free) if self.refined else 0


class Problem(NamedTuple):
    """Static layout of a calibration problem (hashable: the key of its compiled programs). With `board_warp`
    the shared vector ends with the board's two sag parameters (`board_sag`)."""

    cameras: tuple[CameraSpec, ...]
    board_warp: bool = False

    @classmethod
    def of(cls, frees, refined=True, board_warp: bool = False) -> "Problem":
        """From per-camera free sets (a list) and one `refined` flag or one per camera."""
        refined = [refined] * len(frees) if isinstance(refined, bool) else list(refined)
        return cls(tuple(CameraSpec(tuple(f), bool(r)) for f, r in zip(frees, refined)), bool(board_warp))

    @property
    def k(self) -> int:
        return len(self.cameras)

    @property
    def n_extrinsic(self) -> int:
        return POSE_SIZE * (self.k - 1)

    @property
    def n_shared(self) -> int:
        return self.n_extrinsic + sum(c.size for c in self.cameras) + (WARP_SIZE if self.board_warp else 0)

    @property
    def warp_slice(self) -> slice | None:
        return slice(self.n_shared - WARP_SIZE, self.n_shared) if self.board_warp else None

    def intrinsic_slices(self) -> tuple[slice | None, ...]:
        """Where each camera's [k, free coefficients] sit in the shared vector (None: held)."""
        out, at = [], self.n_extrinsic
        for c in self.cameras:
            out.append(slice(at, at + c.size) if c.refined else None)
            at += c.size
        return tuple(out)


def lens_functions(free: tuple[str, ...]):
    """(project, project_jacobian) of the lens model that `free` names, both on (k, coeffs (8,), p_cam): the
    fisheye model reads its k1..k4 from the first four slots (`distortion.coeff_slots`); the splined model's
    coefficients are its knots (as many as `free` names)."""
    if lens_model(free) == "splined":
        nx, ny = splined.grid_of(free)
        return ((lambda k, c, p: splined.project(k, c, p, nx, ny)),
                (lambda k, c, p: splined.project_jacobian(k, c, p, nx, ny)))
    if lens_model(free) == "fisheye":
        return (lambda k, c, p: fisheye.project(k, c[:4], p)), (lambda k, c, p: fisheye.project_jacobian(k, c[:4], p))
    return camera.project, camera.project_jacobian


def _intrinsics(problem: Problem, g, shared):
    """Per camera (k (4,), coeffs (8,)): the refined ones read from g over the held values in `shared`."""
    _, ks, coeffs = shared
    out = []
    for c, (spec, sl) in enumerate(zip(problem.cameras, problem.intrinsic_slices())):
        if sl is None:
            out.append((ks[c], coeffs[c]))
        else:
            gc = g[sl]
            out.append((gc[:4], with_free(coeffs[c], spec.free, gc[4:])))
    return out


def sag_basis(obj):
    """`models.board.sag_basis` in traced code (jax.numpy)."""
    return board.sag_basis(obj, jnp)


def board_points(problem: Problem, g, obj):
    """The board's corners (n, 3), sagged by the shared vector's warp parameters when the problem has them."""
    if not problem.board_warp:
        return obj
    obj = jnp.asarray(obj)
    return obj.at[:, 2].add(sag_basis(obj) @ g[problem.warp_slice])


def sagged_board(obj, sag) -> np.ndarray:
    """(n, 3) numpy: the board's corners sagged by (sag_x, sag_y) (`models.board.sagged`); the flat board for None.
    The board a camera solved with the sag was fitted on (refits, held-sag subsets, corners.npz)."""
    return board.sagged(obj, sag)


def _seen(obs_c):
    """(n,) corners this camera saw, and its observations with the unseen ones at 0."""
    seen = jnp.isfinite(obs_c[:, 0])
    return seen, jnp.where(seen[:, None], obs_c, 0.0)


@functools.lru_cache(maxsize=None)
def frame_residual(problem: Problem):
    """Residuals (K 2n,) of one frame: (g, pose (6,), obs (K, n, 2), shared = (obj (n, 3), ks (K, 4),
    coeffs (K, 8)))."""

    def residual(g, pose, obs_v, shared):
        obj = board_points(problem, g, shared[0])
        p_ref = obj @ rodrigues(pose[:3]).T + pose[3:6]
        out = []
        for c, (k, coeffs) in enumerate(_intrinsics(problem, g, shared)):
            p = p_ref
            if c > 0:
                e = g[POSE_SIZE * (c - 1): POSE_SIZE * c]
                p = p_ref @ rodrigues(e[:3]).T + e[3:6]
            project = lens_functions(problem.cameras[c].free)[0]
            q = jax.vmap(project, in_axes=(None, None, 0))(k, coeffs, p)
            seen, o = _seen(obs_v[c])
            out.append(jnp.where(seen[:, None], q - o, 0.0).ravel())
        return jnp.concatenate(out)

    return residual


@functools.lru_cache(maxsize=None)
def batched_residuals(problem: Problem):
    """(C, V) frames -> (C, V, K 2n) residuals: (g (C, G), poses (C, V, 6), obs (C, V, K, n, 2), shared)."""
    per_view = jax.vmap(frame_residual(problem), in_axes=(None, 0, 0, None))
    return jax.jit(jax.vmap(per_view, in_axes=(0, 0, 0, None)))


def _rotate(rot, d_rot, x):
    """R x (3, n) and d(R x)/d rvec (3 i, 3 k, n) from (R, dR_ij/drvec_k); products over 3-vectors as sums of
    broadcasts: XLA's CPU dot emitter compiles tiny dots into far more code than these fused loops."""
    rx = sum(rot[:, j, None] * x[j] for j in range(3))
    return rx, sum(d_rot[:, j, :, None] * x[j] for j in range(3))


@functools.lru_cache(maxsize=None)
def frame_linearize(problem: Problem):
    """Residuals and transposed Jacobian [d/dg, d/dpose]' (G + 6, K 2n) of one frame by the chain rule: per
    point the hand-written d q / d(k, coeffs, p_cam) (`camera.project_jacobian`), each rotation's derivative
    once per frame (`pose.rodrigues_jacobian`).

    Written on whole coordinate arrays (3, n) with static slices rather than vmapped per point: the frame is
    then a few elementwise loops, which traces and compiles about twice as fast as per-point vmaps and autodiff
    (compile time dominates a cold calibration); tests check it against autodiff and finite differences."""
    n_g = problem.n_shared
    slices = problem.intrinsic_slices()

    def linearize(g, pose, obs_v, shared):
        obj = board_points(problem, g, shared[0])
        n = obj.shape[0]
        rot_b, d_rot_b = rodrigues_jacobian(pose[:3])
        p_ref, dref_drot = _rotate(rot_b, d_rot_b, obj.T)
        p_ref = p_ref + pose[3:6, None]
        if problem.board_warp:  # d p_ref / d sag_j = (board z axis in the camera) * basis_j: (3, 2, n)
            dref_dw = rot_b[:, 2, None, None] * sag_basis(shared[0]).T[None]
        blocks = []
        for c, (k, coeffs) in enumerate(_intrinsics(problem, g, shared)):
            spec = problem.cameras[c]
            p, dp_drot, dp_dt = p_ref, dref_drot, None  # dp_dt None: the identity
            if c > 0:
                e = g[POSE_SIZE * (c - 1): POSE_SIZE * c]
                rot_c, d_rot_c = rodrigues_jacobian(e[:3])
                p, dp_de_rot = _rotate(rot_c, d_rot_c, p_ref)
                p = p + e[3:6, None]
                # d p / d(board pose) through R_c: rows i of R_c times the reference derivatives
                dp_drot = sum(rot_c[:, j, None, None] * dref_drot[j] for j in range(3))
                dp_dt = rot_c
            dp_dw = None
            if problem.board_warp:
                dp_dw = dref_dw if c == 0 else sum(rot_c[:, j, None, None] * dref_dw[j] for j in range(3))
            q, dk, dc, dq_dp = lens_functions(spec.free)[1](k, coeffs, p)  # (2,n) (2,4,n) (2,8|4|knots,n) (2,3,n)
            # d q / d(one coordinate of a 3-vector x) given d p / d x as (3, n): (2, n)
            chain = lambda d_i: sum(dq_dp[:, i, :] * d_i[i] for i in range(3))  # noqa: E731
            zero = jnp.zeros((2, n))
            rows = []  # one (2, n) row per parameter, in the shared vector's order, then the pose's, then r
            for c2 in range(1, problem.k):
                if c2 == c:
                    rows += [chain(dp_de_rot[:, j]) for j in range(3)] + [dq_dp[:, j] for j in range(3)]
                else:
                    rows += [zero] * POSE_SIZE
            for c2, spec2 in enumerate(problem.cameras):
                if slices[c2] is None:
                    continue
                if c2 != c:
                    rows += [zero] * spec2.size
                elif lens_model(spec.free) == "splined":  # its coefficients are its free knots, in order
                    rows += [dk[:, j] for j in range(4)] + [dc[:, j] for j in range(dc.shape[1])]
                else:
                    slots = coeff_slots(spec.free)
                    rows += [dk[:, j] for j in range(4)] + [dc[:, slots.index(name)] for name in spec.free]
            if dp_dw is not None:
                rows += [chain(dp_dw[:, j]) for j in range(WARP_SIZE)]
            rows += [chain(dp_drot[:, j]) for j in range(3)]
            rows += [dq_dp[:, j] for j in range(3)] if dp_dt is None else \
                [sum(dq_dp[:, i] * dp_dt[i, j] for i in range(3)) for j in range(3)]
            seen, o = _seen(obs_v[c])
            rows.append(q - o.T)
            # One stack of elementwise rows: XLA writes it in one loop (slice-by-slice updates of a zero
            # array were five passes over the frame's memory, measured), then (P + 1, n, 2) in residual order.
            full = jnp.where(seen[None, None, :], jnp.stack(rows, axis=1), 0.0)
            blocks.append(jnp.transpose(full, (1, 2, 0)).reshape(n_g + POSE_SIZE + 1, 2 * n))
        a = jnp.concatenate(blocks, axis=1)
        return a[-1], a[:-1]

    return linearize


def prior_matrix(problem: Problem) -> np.ndarray | None:
    """The solver's quadratic prior (G + 1, G + 1) on the shared vector (`lm.solve_structured_batch`): the rows of
    each refined splined camera's `splined.prior_rows` on its knots; None when no camera has one (the other lens
    models have no prior: their solves are as before)."""
    blocks = [(sl, spec.free) for spec, sl in zip(problem.cameras, problem.intrinsic_slices())
              if sl is not None and lens_model(spec.free) == "splined"]
    if not blocks:
        return None
    rows = []
    for sl, free in blocks:
        a = splined.prior_rows(*splined.grid_of(free))
        full = np.zeros((len(a), problem.n_shared + 1))
        full[:, sl.start + 4:sl.stop] = a
        rows.append(full)
    a = np.concatenate(rows)
    return a.T @ a


# --- the compiled solver and how it is called --------------------------------------------------------------


def chunk_rows(n_frames: int, n_points: int, problem: Problem | None = None) -> int:
    """Problems per compiled call for frames of `n_points` corner observations (all cameras together), fixed
    per shape bucket (`frame_bucket`) so one compile: as many as fit CALL_POINTS, at most MAX_CHUNK (`jax_workarounds`). A `problem` with
    a splined camera gets fewer, in proportion to the square of its shared parameters against a rational camera's
    (each frame's normal block is (G + 7)^2; the one chunked call pads a single full-set solve to this many
    problems: a splined full-set solve would otherwise compute ~20 copies of itself, 103 s instead of 7 s)."""
    rows = int(max(1, min(MAX_CHUNK, CALL_POINTS // max(1, frame_bucket(n_frames) * n_points))))
    if problem is not None and any(lens_model(c.free) == "splined" for c in problem.cameras):
        rational = 4 + 8 + POSE_SIZE + 1
        rows = max(1, rows * rational ** 2 // (problem.n_shared + POSE_SIZE + 1) ** 2)
    return rows


def threads(requested: int | None = None) -> int:
    """Compiled calls run at once: `requested`, DSTEREO_THREADS, or one per core; at most MAX_CONCURRENT_CALLS."""
    env = os.environ.get("DSTEREO_THREADS")
    n = requested or (int(env) if env and env.isdigit() else None) or os.cpu_count() or 1
    return max(1, min(n, MAX_CONCURRENT_CALLS))


_solver_lock = threading.Lock()


def compiled_solver(problem: Problem, options: LMOptions):
    """`_compiled_solver` under a lock: the subset runner's threads make their first calls together, and two of
    them through the cache at once built two functions that each loaded the executable from disk (measured: two
    0.07-0.2 s loads at once)."""
    with _solver_lock:
        return _compiled_solver(problem, options)


@functools.lru_cache(maxsize=None)
def _compiled_solver(problem: Problem, options: LMOptions):
    """The one compiled program behind the full set and every subset of a problem: CHUNK problems of F frames,
    each with its own start, frame weights (0 = left out), residual weights (0 = unseen or an outlier) and
    initial damping. The full set and subsets of the same frames share its shape, so a calibration with subsets
    compiles once (compile time dominates a cold run), whatever the outlier mask. `decrement_tol` is traced too
    (0: off, the full set; > 0: the subsets' noise-unit stop), so both run one program."""
    res, lin, prior = frame_residual(problem), frame_linearize(problem), prior_matrix(problem)

    def batch(g0, p0, obs, weight, lambda0, normal0, r_weight, shared, decrement_tol, max_passes):
        return solve_structured_batch(res, g0, p0, obs, shared, options._replace(decrement_tol=decrement_tol), lin,
                                      weight, lambda0, normal0, r_weight, None if prior is None else jnp.asarray(prior),
                                      max_passes)

    # kept on disk as an executable: a new process skips tracing it too (runtime/aot.py)
    return aot.jit(batch, "calib.problem.compiled_solver", (problem, options), COMPILE_OPTIONS)


def residual_weights(mask: np.ndarray) -> np.ndarray:
    """(..., F, K, n) corner mask (True: seen and an inlier) -> (..., F, K 2n) residual weights in the
    residual's order."""
    mask = np.asarray(mask, float)
    return np.repeat(mask, 2, axis=-1).reshape(*mask.shape[:-2], -1)


def shared_data(obj: np.ndarray, ks: np.ndarray, coeffs: np.ndarray):
    """The solver's constant data: board points (n, 3), held intrinsics (K, 4) and coefficients (K, 8) (the
    refined cameras' non-free coefficients stay at these values). numpy, not jnp: no eager JAX op."""
    return (np.asarray(obj, float), np.asarray(ks, float).reshape(-1, 4), np.asarray(coeffs, float).reshape(-1, 8))


def pad_frames(a, n_frames: int, fill=None):
    """numpy per-problem array (B, F, ...) padded along its frame axis to `n_frames` (`buckets.pad_axis`: with
    `fill`, or copies of the first frame for None)."""
    return buckets.pad_axis(a, n_frames, 1, fill)


def run(problem: Problem, options: LMOptions, g0, p0, obs, weight, lambda0, shared, normal0=None, r_weight=None,
        rows: int | None = None, max_passes: int | None = None):
    """Call the compiled solver on one chunk given as per-problem arrays (leading axis <= chunk_rows): g0 (B, G),
    p0 (B, F, 6), obs (B, F, K, n, 2) (NaN: unseen), weight (B, F), lambda0 (B,).

    `normal0 = (r, m)`, per problem, is the linearisation at (g0, p0) from an earlier solve (`LMResult.residuals`
    and `.normal`); the solver then skips linearising the start. Without it, the same compiled program linearises
    the start itself (a traced flag, not a second compile). An argument that is already a device array is taken
    as it is, at the chunk's full size and `frame_bucket(F)` frames: subsets pass what all their chunks share once.
    `weight` is always per chunk, numpy, and gives the number of problems and of frames F. `r_weight` (B, F, K 2n),
    default: 1 where seen. `rows`: problems per compiled call (default `chunk_rows`, the program subsets of these
    frames share; fewer problems are padded to it and computed all the same: a single solve that shares no program
    with subsets passes 1). `max_passes`: see `lm.solve_structured_batch` (problems still running come back with
    status 0; default: no limit).

    The frames are padded to their bucket (`runtime/buckets.py`): frames of weight 0, unseen (NaN corners, residual
    weight 0), at the first frame's pose; they take no part in any sum, count or step (`lm`), and the results are
    cut back to F frames, so a caller sees the solve of its F frames, and one compiled program serves every F of
    the bucket."""
    n, n_real = np.shape(weight)[:2]
    n_frames = frame_bucket(n_real)
    k, n_pts = np.shape(obs)[2:4]
    rows = chunk_rows(n_frames, k * n_pts, problem) if rows is None else int(rows)
    if n > rows:  # more problems than one call may carry (jax_workarounds): call after call
        cut = lambda a, i: a if a is None or isinstance(a, jax.Array) else a[i:i + rows]  # noqa: E731
        parts = [run(problem, options, *(cut(a, i) for a in (g0, p0, obs, weight, lambda0)), shared,
                     None if normal0 is None else tuple(cut(a, i) for a in normal0), cut(r_weight, i), rows, max_passes)
                 for i in range(0, n, rows)]
        return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *parts)

    def prep(a, frame_fill=(), device_frames=True):
        """Padded to `rows` problems (copies of the first) and, where `frame_fill` is given, to `n_frames` frames
        with that fill (None: copies of the first frame). A device array is checked, not copied."""
        if isinstance(a, jax.Array):
            if device_frames and frame_fill != () and a.shape[:2] != (rows, n_frames):
                raise ValueError(f"problem.run: a device array of shape {a.shape} where ({rows}, {n_frames}, ...) "
                                 "(chunk rows, frames padded to their bucket) is expected")
            return a
        a = np.asarray(a, float)
        if frame_fill != ():
            a = pad_frames(a, n_frames, frame_fill)
        # numpy in, not jnp.asarray: that compiles a small staging program per new shape (~10 ms each, measured)
        return np.ascontiguousarray(np.concatenate([a, np.repeat(a[:1], rows - n, axis=0)]) if n < rows else a)

    n_p1 = problem.n_shared + POSE_SIZE + 1
    given = normal0 is not None
    if not given:
        normal0 = (np.zeros((n, n_real, 2 * k * n_pts)), np.zeros((n, n_real, n_p1, n_p1)))
    if r_weight is None and not isinstance(obs, jax.Array):
        r_weight = residual_weights(np.isfinite(np.asarray(obs)[..., 0]))
    key = options._replace(lambda0=0.0, decrement_tol=None)  # both traced, not compiled in
    if buckets.enabled():  # what jobs/prebuild.py builds ahead for the other buckets: this program at every count
        buckets.note("solver", (problem, key, rows == 1, int(k), int(n_pts), shared),
                     tag=(problem, key, rows == 1, int(k), int(n_pts)), size=n_frames)
    args = [prep(g0), prep(p0, None), prep(obs, np.nan), prep(weight, 0.0), prep(lambda0),
            prep(normal0[0], 0.0), prep(normal0[1], 0.0), prep(r_weight, 0.0)]
    limit = np.int32(np.iinfo(np.int32).max if max_passes is None else max_passes)
    solver = compiled_solver(problem, key)
    # the compiled call and its results' transfer (where a hung call waits) under the watchdog, keyed by program
    # and shapes: the allowance comes from the longest such call before it (dstereo/runtime/watchdog.py)
    what = f"a chunk of {rows} problem(s) of {problem.k} camera(s), {n_real} view(s) x {n_pts} corner(s)"
    with watchdog.watched((problem, key, rows, n_frames, k * n_pts, max_passes is None), what):
        out = solver(*args[:5], (*args[5:7], np.full(rows, given)), args[7], shared,
                     np.float64(options.decrement_tol or 0.0), limit)
        out = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], out)
    # the padded frames cut off: their poses, residuals (0) and normal blocks (weight 0: no part in the solve)
    return out._replace(p=out.p[:, :n_real], residuals=out.residuals[:, :n_real], normal=out.normal[:, :n_real])


def frame_bucket(n_frames: int) -> int:
    """The frames a problem of `n_frames` is solved with: its shape bucket (`runtime/buckets.py`)."""
    return buckets.views(n_frames)
