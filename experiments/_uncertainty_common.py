"""Shared pieces of the uncertainty experiments (`uncertainty_mc`, `model_choice`, `real_uncertainty`, `projection_mc_rendered`).

- the synthetic camera with a known truth (`dstereo.synth.board_views.webcam`), its rendered board views and an end-to-end noise draw (fresh sensor
  noise on the stored radiance, then the project's own corner detector);
- the real sets of ../shared/data as (object points, corners, image size, names);
- the subset-spread scalings (delete-d jackknife), view-bootstrap plans for the engine's batched subset solver,
  a view-robust ("sandwich") covariance, and a pose-only solve for held-out views (optimistix LM);
- where results and figures go.

Nothing here prints; the scripts do.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from dstereo.calib.subsets import SubsetPlan  # noqa: E402
from dstereo.synth.board_views import webcam  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "experiments" / "results"
FIGURES = RESULTS / "figures"
PATTERN = (9, 6)
INTRINSICS = ("fx", "fy", "cx", "cy", "k1", "k2")


# --- synthetic camera with a known truth -------------------------------------------------------------------------

@dataclass
class SyntheticViews:
    """Board views of one camera: the pre-exposure radiance of each view (rendered once), the true corners, and
    how each noise draw is exposed. `draw(seed)` gives fresh sensor noise and re-detected corners."""

    camera: object  # dstereo.models.camera.Camera, the truth
    poses: np.ndarray  # (V, 6) T_cam_board
    radiance: list  # V arrays (h, w) in [0, 1]
    truth: np.ndarray  # (V, n, 2) true corner pixels
    obj: np.ndarray  # (n, 3) board points (mm)
    options: object  # RenderOptions with sensor noise

    def draw(self, seed: int) -> tuple[np.ndarray | None, list[int]]:
        """(V, n, 2) detected corners for one sensor-noise draw, or None plus the views the detector missed."""
        from dstereo.io.corners import _detect_one  # the project's detector (findChessboardCorners + cornerSubPix)
        from dstereo.synth.sensor import expose

        rng = np.random.default_rng([seed, 7919])
        pp = np.asarray(self.camera.k[2:4])
        out, missed = [], []
        for i, rad in enumerate(self.radiance):
            q, _ = _detect_one(expose(rad, pp, self.options, rng), PATTERN)
            if q is None:
                missed.append(i)
            out.append(q)
        return (None, missed) if missed else (np.stack(out), missed)

    def detect_clean(self) -> np.ndarray | None:
        """(V, n, 2) corners detected on the noise-free exposures: the detector's own fixed error."""
        from dataclasses import replace

        from dstereo.io.corners import _detect_one
        from dstereo.synth.sensor import expose

        clean = replace(self.options, full_well=0.0, read_noise_dn=0.0)
        pp = np.asarray(self.camera.k[2:4])
        out = [_detect_one(expose(rad, pp, clean, np.random.default_rng(0)), PATTERN)[0] for rad in self.radiance]
        return None if any(q is None for q in out) else np.stack(out)


truth_camera = webcam  # the synthetic camera with a known truth (dstereo.synth.board_views)


# Sensor noise: Poisson shot noise (1000 e- at white) plus 2 DN read noise, the usual 1 px lens blur.
NOISE_OPTIONS = dict(supersample=2, defocus_sigma_px=1.0, full_well=1000.0, read_noise_dn=2.0)


def render_views(camera, n_views: int, seed: int = 0, square: float = 20.0) -> SyntheticViews:
    """Render `n_views` board poses (the generator of `dstereo.synth`, covering centre, corners and edges) once."""
    from dstereo.synth import Board, board_pose_set, camera_rays, object_points, true_corners
    from dstereo.synth.render import board_radiance
    from dstereo.synth.sensor import RenderOptions

    board = Board(PATTERN, square, square)
    poses = board_pose_set([camera], [np.zeros(6)], board, n_views, seed)
    options = RenderOptions(**NOISE_OPTIONS)
    rays = camera_rays(camera, options.supersample)
    radiance = [np.asarray(board_radiance(rays, jnp.asarray(p), board)) for p in poses]
    truth = np.stack([true_corners(camera, p, PATTERN, square) for p in poses])
    return SyntheticViews(camera, poses, radiance, truth, object_points(PATTERN, square), options)


# --- real data ----------------------------------------------------------------------------------------------------

def real_views(name: str, side: str):
    """(obj, obs (V, n, 2), image size, image names) of ../shared/data/<name>/<side>*.jpg, square = 1."""
    from dstereo.io.corners import detect_folder

    folder = DATA / name
    det = detect_folder(folder, PATTERN, 1.0, files=sorted(folder.glob(f"{side}*.jpg")))
    names = [n for n in det.names if n in det.corners]
    return det.object_points, np.stack([det.corners[n] for n in names]), det.image_size, names


def real_pairs(name: str):
    """(obj, obs (V, 2, n, 2), [left size, right size]) of the pairs of ../shared/data/<name> (square = 1): the
    images paired by name, the pairs where both cameras found the board."""
    from dstereo.io.corners import detect_folder
    from dstereo.io.pairing import pair_by_name

    folder = DATA / name
    left, right = sorted(folder.glob("left*.jpg")), sorted(folder.glob("right*.jpg"))
    dets = [detect_folder(folder, PATTERN, 1.0, files=files) for files in (left, right)]
    pairs = [(a.name, b.name) for a, b in pair_by_name(left, right).pairs
             if a.name in dets[0].corners and b.name in dets[1].corners]
    obs = np.stack([np.stack([dets[0].corners[a], dets[1].corners[b]]) for a, b in pairs])
    return dets[0].object_points, obs, [dets[0].image_size, dets[1].image_size]


# --- spreads and their scalings -----------------------------------------------------------------------------------

def jackknife_factor(n: int, m: int) -> float:
    """Delete-d jackknife: Var(theta_N) ~ m / (N - m) * Var_S(theta_S) over subsets S of m views out of N."""
    return math.sqrt(m / (n - m))


def spread(values: np.ndarray) -> np.ndarray:
    """Per-column standard deviation (ddof = 1), the thesis's subset spread."""
    return np.std(values, axis=0, ddof=1)


def bootstrap_plan(n: int, draws: int, seed: int = 0) -> SubsetPlan:
    """`draws` resamples of n views with replacement, in the layout of the engine's subset plans (a repeated
    view is simply a view observed twice, i.e. weight 2)."""
    rng = np.random.default_rng(seed)
    index = np.sort(rng.integers(0, n, size=(draws, n)), axis=1).astype(np.int32)
    return SubsetPlan(index, n ** n, False, seed)


def sandwich_std(sol, obj: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """View-robust standard deviations of a mono solve: S^-1 (N/(N-1) sum_v s_v s_v') S^-1 with s_v the view's
    gradient on the shared parameters (its pose gradient is zero at the optimum, so this is also its score after
    eliminating the pose) and S the Schur complement. It is the infinitesimal (delete-1) jackknife: no assumption
    that corner errors are independent within a view, only between views."""
    from dstereo.calib.mono import view_linearize_for
    from dstereo.uncertainty.covariance import scaled_inverse

    lin = jax.jit(jax.vmap(view_linearize_for(sol.camera().dist.free), in_axes=(None, 0, 0, None)))
    shared = (jnp.asarray(obj, float), jnp.zeros(8))
    r, jac = lin(jnp.asarray(sol.values), jnp.asarray(sol.poses), jnp.asarray(obs, float), shared)
    r, jac = np.asarray(r), np.swapaxes(np.asarray(jac), 1, 2)  # the solver's layout is (V, P, R)
    g = len(sol.values)
    jg, jp = jac[:, :, :g], jac[:, :, g:]
    s = np.einsum("vrg,vr->vg", jg, r)  # (V, G)
    # Schur complement per view: Jg'Jg - Jg'Jp (Jp'Jp)^-1 Jp'Jg
    u = np.einsum("vrg,vrh->gh", jg, jg)
    w = np.einsum("vrg,vrb->vgb", jg, jp)
    vv = np.einsum("vra,vrb->vab", jp, jp)
    schur = u - np.einsum("vgb,vbh->gh", w, np.linalg.solve(vv, np.swapaxes(w, 1, 2)))
    s_inv = scaled_inverse(schur)
    n = len(s)
    meat = n / (n - 1) * s.T @ s
    return np.sqrt(np.maximum(np.diag(s_inv @ meat @ s_inv), 0.0))


def solve_subsets_safe(solver, *args, chunk: int | None = None):
    """`solver(*args)` (mono.solve_subsets or multiview.solve_view_subsets) on one thread and, where the engine
    version still takes it, with `chunk` subsets per call. jaxlib 0.10.2's CPU runtime deadlocked (0 % CPU for
    minutes) on rig640 (25 views, m = 22) when the reworked mono solver ran two chunks on two threads, and with
    the older solver at 32 subsets x 22-25 views per call; one thread, and 16 per call, ran through."""
    import inspect

    params = inspect.signature(solver).parameters
    kw = {"chunk": chunk} if chunk and "chunk" in params else {}
    if "threads" in params:
        kw["threads"] = 1
    return solver(*args, **kw)


# --- pose-only solve for held-out views --------------------------------------------------------------------------

def _pose_residual(pose, args):
    from dstereo.models.camera import project_view

    k, coeffs, obj, obs = args
    q = jax.vmap(project_view, in_axes=(None, None, None, 0))(k, coeffs, pose, obj)
    return (q - obs).ravel()


@jax.jit
def _pose_solve_batch(k, coeffs, obj, obs, pose0):
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)

    def one(k_, c_, obs_, p0):
        sol = optx.least_squares(_pose_residual, solver, p0, args=(k_, c_, obj, obs_), max_steps=200, throw=False)
        r = _pose_residual(sol.value, (k_, c_, obj, obs_))
        return sol.value, jnp.sum(r * r), sol.result == optx.RESULTS.successful

    return jax.vmap(one)(k, coeffs, obs, pose0)


def solve_poses(k: np.ndarray, coeffs: np.ndarray, obj: np.ndarray, obs: np.ndarray, pose0: np.ndarray):
    """Pose of each view with its camera fixed: k (V, 4), coeffs (V, 8), obs (V, n, 2), pose0 (V, 6).
    Returns (poses (V, 6), SSE (V,), converged (V,)). optimistix's LM, vmapped over views."""
    out = _pose_solve_batch(*(jnp.asarray(a, float) for a in (k, coeffs)), jnp.asarray(obj, float),
                            jnp.asarray(obs, float), jnp.asarray(pose0, float))
    return tuple(np.asarray(a) for a in out)


# --- output ----------------------------------------------------------------------------------------------------------

def write_outputs(stem: str, tables_md: str, data: dict) -> tuple[Path, Path]:
    """Write figures/<stem>.md (the tables the results page quotes) and figures/<stem>.json (all numbers)."""
    FIGURES.mkdir(parents=True, exist_ok=True)
    md, js = FIGURES / f"{stem}.md", FIGURES / f"{stem}.json"
    md.write_text(tables_md)
    js.write_text(json.dumps(data, indent=1, default=_jsonable))
    return md, js


def _jsonable(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(type(x))


def md_table(header: list[str], rows: list[list]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"
