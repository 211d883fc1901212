"""`dstereo demo`: render a synthetic stereo experiment with known truth, calibrate, reconstruct, compare.

One run, all under `out/` (filled under a temporary name and renamed at the end):
    scenes/calibration/    chessboard pairs of the reduced Plasmatron rig (thesis layout) + truth.*
    scenes/sample/         the cork sample seen by both cameras, with each camera's true depth map
    calibration/           the `dstereo calibrate` stereo results folder (the thesis's path, below)
    calibration_joint/     stereo.yml / stereo.json of the joint refinement (below)
    reconstruction/        the `dstereo reconstruct` results folder of the sample pair (joint calibration,
                           sub-pixel refinement on, point sigmas from the joint covariance)
    comparison.json / .md  every estimate against its truth, with the bound it is held to

Calibration, the thesis's path (`calib.stereo_pipeline`, as `dstereo calibrate` runs it): each camera alone
with C(N, m) subsets, the rig with those intrinsics fixed, its subsets filtered by the stereo steps of the
thesis's Figure 5.14; the answer is the mean over the surviving subsets. Then the joint refinement: both
cameras' intrinsics and the rig solved together on all pairs (`calib.stereo`, mode "joint"). The reduced rig
sees 80 x 60 mm at 600 mm, a 7.6 deg field in which perspective barely shows on the board: one camera alone
pins its focal length to ~0.1 % and its principal point to ~10 px, while the two cameras together (the board's
distance triangulated by the rig) reach ~0.02 % and a few px. The joint refinement is the one held to the
bounds (`BOUNDS`: fixed, or 3 Jacobian standard deviations for the principal points and the rotation) and the
one the reconstruction uses; the thesis's path is shown beside it. The reconstruction refines SGBM's disparity
(`dstereo.stereo.subpixel`); the surface error without the refinement is reported beside it, and the median predicted
depth std (joint covariance + per-pixel disparity noise) beside the measured error. Library code: nothing here
prints.
"""

from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dstereo.config.calibration import Step

# Thesis Figure 5.14: stereo_re <= 3 px, then Tnorm and RVnorm within 0.75 IQR.
THESIS_STEREO_STEPS = (Step(("stereo_re",), (3.0,)), Step(("Tnorm",), (0.75,)), Step(("RVnorm",), (0.75,)))
# Fixed acceptance bounds; principal points and rotation also pass within `sigmas` standard deviations.
BOUNDS = {"focal_percent": 0.1, "principal_px": 0.5, "baseline_percent": 0.1, "rotation_deg": 0.05, "sigmas": 3.0}
# Allowed SGBM sub-pixel disparity error on the speckle, px (about 0.13 px measured with the true calibration).
DISPARITY_NOISE_PX = 0.2


@dataclass(frozen=True)
class DemoSettings:
    """Sizes of one demo run: the rig (reduced Plasmatron), the calibration set and the subset analysis."""

    image_size: tuple[int, int] = (640, 480)
    focal_px: float = 4800.0
    baseline_mm: float = 100.0
    distance_mm: float = 600.0
    n_views: int = 14
    per_set: int = 12
    max_subsets: int = 200
    model: tuple[str, ...] = ("k1", "k2", "p1", "p2")  # free distortion (the lenses have k3 = 0)


FULL = DemoSettings()
QUICK = DemoSettings(n_views=8, per_set=6, max_subsets=28)
PATHS = {"scenes": "scenes", "calibration": "calibration", "joint_yml": "calibration_joint/stereo.yml",
         "thesis_yml": "calibration/stereo.yml", "reconstruction": "reconstruction",
         "points": "reconstruction/points.npy", "comparison": "comparison.md"}


def run_demo(out, force: bool = False, quick: bool = False, seed: int = 0, progress=None,
             settings: DemoSettings | None = None) -> dict:
    """Render, calibrate, reconstruct and compare; returns the comparison (also written to out/comparison.*).

    `progress(stage, done, total)` is called along the way. An existing `out` is refused (DstereoError)
    unless `force`; on error nothing is left behind.
    """
    from dstereo.io.results import atomic_folder, write_json
    from dstereo.synth import plasmatron_rig

    settings = settings or (QUICK if quick else FULL)
    report = progress or (lambda stage, done, total: None)
    timings, t0 = {}, time.perf_counter()
    with atomic_folder(out, force) as tmp:
        rig = plasmatron_rig(settings.image_size, settings.focal_px, settings.baseline_mm, settings.distance_mm)
        cset, pair = render_scenes(tmp / "scenes", rig, settings, seed, report)
        timings["render_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        job = calibrate_thesis(tmp / "scenes" / "calibration", tmp / "calibration", cset.truth["board"], settings,
                               seed, report)
        timings["calibrate_thesis_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        joint, cov = calibrate_joint(job, tmp / "calibration_joint", report)
        timings["calibrate_joint_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        surface = reconstruct_sample(tmp, rig, pair, settings, report)
        timings["reconstruct_s"] = time.perf_counter() - t1
        comparison = compare(rig, job, joint, cov, surface, settings)
        timings["total_s"] = time.perf_counter() - t0
        comparison |= {"out": str(Path(out).resolve()), "seed": seed, "quick": quick,
                       "settings": asdict(settings), "timings_s": timings, "paths": PATHS}
        write_json(tmp / "comparison.json", comparison)
        (tmp / "comparison.md").write_text(markdown(comparison))
    return comparison


# --- scenes ---------------------------------------------------------------------------------------------------


def render_scenes(folder: Path, rig, settings: DemoSettings, seed: int, report):
    """Chessboard pairs and the sample pair, written in the thesis layout under `folder`."""
    from dstereo.synth import calibration_set, sample_pair, write_calibration_set, write_stereo_renders

    report("render boards", 0, 2)
    cset = calibration_set(rig.left, rig.right, rig.T_right_left, n_views=settings.n_views, seed=seed)
    write_calibration_set(folder / "calibration", cset)
    report("render sample", 1, 2)
    pair = sample_pair(rig, seed=seed)
    write_stereo_renders(folder / "sample", [pair])
    report("render sample", 2, 2)
    return cset, pair


# --- calibration ----------------------------------------------------------------------------------------------


def thesis_config(board: dict, settings: DemoSettings, seed: int):
    """The calibration configuration of the thesis's stereo file (Figure 5.14) for the rendered board."""
    from dstereo.config.calibration import Config, validate

    return validate(Config(mode="stereo", pattern=tuple(board["pattern"]), square=float(board["square"]), unit="mm",
                           model=settings.model, per_set=settings.per_set, max_subsets=settings.max_subsets,
                           seed=seed, stereo_steps=THESIS_STEREO_STEPS,
                           final="mean"))  # the thesis's answer, shown as such beside the joint refinement


def calibrate_thesis(images: Path, folder: Path, board: dict, settings: DemoSettings, seed: int, report):
    """`dstereo calibrate`'s stereo job on images/images_left + images_right; writes its results folder."""
    from dstereo.calib.stereo_pipeline import calibrate_stereo_project, stereo_sources
    from dstereo.io.stereo_files import write_stereo_results

    config = thesis_config(board, settings, seed)
    job = calibrate_stereo_project(stereo_sources(images, config), config, progress=report, use_cache=False)
    report("write calibration", 0, 1)
    write_stereo_results(folder, job)
    return job


def calibrate_joint(job, folder: Path, report):
    """Refine both cameras and the rig together on the job's pairs, from its cameras; write stereo.yml and
    stereo.json (with `joint_covariance`'s standard deviations). Returns the solution and that covariance."""
    from dstereo.calib.stereo import calibrate_stereo
    from dstereo.uncertainty.rig import JOINT_STRUCTURE
    from dstereo.io.results import atomic_folder, write_json
    from dstereo.io.stereo_files import write_stereo_yml

    report("joint refinement", 0, 1)
    obj = job.detection.object_points
    obs_l, obs_r = job.detection.observations()
    s = calibrate_stereo(obj, obs_l, obs_r, job.full.left, job.full.right, "joint")
    cov = joint_covariance(s, obj, obs_l, obs_r)
    with atomic_folder(folder, False) as tmp:
        write_stereo_yml(tmp / "stereo.yml", s.left.matrix(), s.left.coeffs(), s.right.matrix(), s.right.coeffs(),
                         s.R, s.T, s.E, s.F, s.left.image_size, s.right.image_size, rms=s.rms, cov=cov,
                         cov_names=tuple(s.names), cov_structure=JOINT_STRUCTURE + "; demo.joint_covariance")
        write_json(tmp / "stereo.json", {
            "mode": s.mode, "status": s.status_text, "names": s.names, "values": s.values,
            "std": np.sqrt(np.diag(cov)), "covariance": cov, "R": s.R, "T": s.T, "E": s.E, "F": s.F,
            "rms_px": s.rms, "stereo_re_px": s.stereo_re, "pairs": job.detection.pairs,
            "std_note": "sigma^2 (J^T J)^-1 with J's columns scaled to unit norm, board poses as nuisance "
                        "parameters (demo.joint_covariance)"})
    report("joint refinement", 1, 1)
    return s, cov


def joint_covariance(s, obj: np.ndarray, obs_left: np.ndarray, obs_right: np.ndarray) -> np.ndarray:
    """(G, G) covariance of a joint solve's shared vector (`s.names`: rig, left and right intrinsics),
    sigma^2 (J^T J)^-1 over all pairs with the board poses as nuisance parameters. J's columns are scaled to
    unit norm before inverting: unscaled, J^T J spans ~15 orders of magnitude at this field of view (fx in px
    next to k2 at r^4 ~ 1e-5), where a truncated pseudo-inverse drops the weak principal-point directions."""
    import jax
    import jax.numpy as jnp

    from dstereo.models.rig import pair_residual

    obj = jnp.asarray(obj, float)
    obs_l, obs_r = jnp.asarray(obs_left, float), jnp.asarray(obs_right, float)
    n_g, n_l = len(s.values), len(s.left.free_vector())
    per_pair = jax.vmap(pair_residual, in_axes=(None, None, None, None, None, 0, None, 0, 0))

    def residuals(x):
        g = x[:n_g]
        left, right = s.left.with_free_vector(g[6:6 + n_l]), s.right.with_free_vector(g[6 + n_l:])
        return per_pair(left.k, left.dist.coeffs, right.k, right.dist.coeffs, g[:6], x[n_g:].reshape(-1, 6), obj,
                        obs_l, obs_r).ravel()

    x = jnp.concatenate([jnp.asarray(s.values, float), jnp.asarray(s.poses, float).ravel()])
    r, jac = (np.asarray(a) for a in jax.jit(lambda x: (residuals(x), jax.jacfwd(residuals)(x)))(x))
    scale = np.linalg.norm(jac, axis=0)
    scaled = jac / scale
    sigma2 = float(r @ r) / (len(r) - len(x))
    return (sigma2 * np.linalg.inv(scaled.T @ scaled) / np.outer(scale, scale))[:n_g, :n_g]


# --- reconstruction and its error against the true surface ----------------------------------------------------


def reconstruct_sample(out: Path, rig, pair, settings: DemoSettings, report) -> dict:
    """Reconstruct the sample pair with the joint calibration (written to out/reconstruction), and with the
    thesis's and the true calibrations (the latter: matching alone), all with the sub-pixel refinement; errors of
    each against the true surface, the joint and true ones also without the refinement (`*_sgbm`), and the joint
    reconstruction's predicted depth std (`sigma_z_mm`)."""
    from dstereo.io.calib_files import StereoCalibration, read_stereo_calibration
    from dstereo.io.reconstruction_files import write_atomically, write_pair
    from dstereo.stereo.pipeline import ReconstructionConfig, read_image, reconstruct_calibrated

    d = settings.distance_mm
    config = ReconstructionConfig(depth_range=(d - 50.0, d + 50.0), refine=True)
    sgbm_only = replace(config, refine=False, uncertainty=False)
    left = read_image(out / "scenes" / "sample" / "images_left" / "left_000.png")
    right = read_image(out / "scenes" / "sample" / "images_right" / "right_000.png")
    r, t = rig.rotation_translation()
    calibs = {key: replace(read_stereo_calibration(out / PATHS[path]), source=PATHS[path])
              for key, path in (("joint", "joint_yml"), ("thesis", "thesis_yml"))}
    calibs["true_calibration"] = StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(),
                                                   rig.right.coeffs(), r, t, tuple(rig.left.image_size), source="truth")
    depth = pair.truth_left["depth"]
    surface = {"rms_slope": rms_slope(depth, float(rig.left.k[0]))}
    for i, (key, calib) in enumerate(calibs.items()):
        report("reconstruct", i, len(calibs))
        result = reconstruct_calibrated(calib, left, right, replace(config, uncertainty=key == "joint"),
                                        name=f"sample ({key})")
        if key == "joint":
            write_atomically(out / "reconstruction", False, lambda tmp, result=result: write_pair(tmp, result, config))
            surface["valid_fraction"] = result.summary["valid_fraction"]
            surface["refine_dropped_fraction"] = result.summary["refine"]["dropped_fraction"]
            unc = result.summary["uncertainty"]
            surface["sigma_z_mm"] = {"median": unc["sigma_z_mm"]["median"], "p95": unc["sigma_z_mm"]["p95"],
                                     "calibration_at_median_mm": unc["median_point"]["calibration_mm"],
                                     "disparity_at_median_mm": unc["median_point"]["disparity_mm"],
                                     "sigma_d_px": unc["sigma_d_px"], "calibration_included": unc["calibration_included"]}
        surface[key] = surface_errors(result.points, rig.left, depth)
        if key != "thesis":
            plain = reconstruct_calibrated(calib, left, right, sgbm_only, name=f"sample ({key}, SGBM only)")
            surface[f"{key}_sgbm"] = surface_errors(plain.points, rig.left, depth)
    report("reconstruct", len(calibs), len(calibs))
    return surface


def bilinear(image: np.ndarray, q: np.ndarray) -> np.ndarray:
    """image (h, w) at pixels q (n, 2) (x, y; pixel centres at integers); NaN where a neighbour is NaN or q lies
    outside [0, w - 1] x [0, h - 1]."""
    h, w = image.shape
    inside = np.all(np.isfinite(q), axis=1) & (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] <= w - 1) & (q[:, 1] <= h - 1)
    qc = np.where(inside[:, None], q, 0.0)
    x0 = np.minimum(np.floor(qc[:, 0]).astype(int), w - 2)
    y0 = np.minimum(np.floor(qc[:, 1]).astype(int), h - 2)
    fx, fy = qc[:, 0] - x0, qc[:, 1] - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, np.nan)


@functools.cache
def _projector():
    import jax

    from dstereo.models.camera import project

    return jax.jit(jax.vmap(project, in_axes=(None, None, 0)))


def ray_errors(p: np.ndarray, camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (n,) mm of points p (n, 3; left camera frame) from the true surface along the true left
    camera's ray through each (NaN off the sample), and their pixels (n, 2) in the true camera."""
    q = np.asarray(_projector()(camera.k, camera.dist.coeffs, p))
    return (p[:, 2] - bilinear(depth, q)) * np.linalg.norm(p, axis=1) / p[:, 2], q


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising |R a + t - b| over point pairs (n, 3) (Kabsch)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    return r, cb - r @ ca


def _stats(err: np.ndarray) -> dict:
    if not err.size:
        return {"rms_mm": float("nan")}
    a = np.abs(err)
    return {"rms_mm": float(np.sqrt(np.mean(err**2))), "mean_mm": float(np.mean(err)), "std_mm": float(np.std(err)),
            "median_abs_mm": float(np.median(a)), "p95_abs_mm": float(np.percentile(a, 95)),
            "over_1mm": int((a > 1.0).sum())}


def surface_errors(points: np.ndarray, camera, depth: np.ndarray, fit_iterations: int = 5) -> dict:
    """Errors (mm) of reconstructed points (h, w, 3; left camera frame) against the true surface, along the
    true left camera's rays (`ray_errors`), as they are and after the rigid motion that best fits them onto
    the surface (`shape_*`: what is left once the pose of the whole cloud is taken out; each fit pairs the
    points with the surface points on their current rays; the domed face is a spherical cap, so the fitted
    motion itself is not unique and is not reported). `coverage` is the fraction of the sample's pixels
    in the left image that a point lands on; points landing off the sample are counted, not measured."""
    p = points.reshape(-1, 3).astype(float)
    p = p[np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0)]
    err, q = ray_errors(p, camera, depth)
    on = np.isfinite(err)
    r, t, pts = np.eye(3), np.zeros(3), p[on]
    for _ in range(fit_iterations):
        moved = pts @ r.T + t
        e, _ = ray_errors(moved, camera, depth)
        ok = np.isfinite(e)
        r, t = rigid_fit(pts[ok], moved[ok] * (1.0 - e[ok] / np.linalg.norm(moved[ok], axis=1))[:, None])
    fitted, _ = ray_errors(pts @ r.T + t, camera, depth)
    face = np.isfinite(depth)
    hit = np.zeros_like(face)
    u, v = np.rint(q[on]).astype(int).T
    hit[v, u] = True
    shape = _stats(fitted[np.isfinite(fitted)])
    return {"points": int(len(p)), "on_sample": int(on.sum()), "off_sample": int((~on).sum()),
            "coverage": float((hit & face).sum() / max(face.sum(), 1)), **_stats(err[on]),
            "shape_rms_mm": shape["rms_mm"], "shape_median_abs_mm": shape.get("median_abs_mm", float("nan"))}


def rms_slope(depth: np.ndarray, focal_px: float) -> float:
    """RMS over the sample of its depth slope |grad Z| per mm across the view (edges, where a neighbour is
    background, excluded): how much a sideways shift of the cloud shows as depth error."""
    gy, gx = np.gradient(depth)
    slope = np.hypot(gx, gy) * focal_px / depth
    return float(np.sqrt(np.nanmean(slope**2)))


# --- comparison -----------------------------------------------------------------------------------------------


def rotation_error_deg(r_est: np.ndarray, r_true: np.ndarray) -> float:
    """Angle of R_est R_true^T, degrees (through the one rotation log: arccos of the trace loses half the digits
    at the small angles compared here)."""
    from dstereo.models.pose import rotation_vector

    return float(np.degrees(np.linalg.norm(rotation_vector(np.asarray(r_est) @ np.asarray(r_true).T))))


def _norm_sigma(v: np.ndarray, cov: np.ndarray) -> float:
    """Standard deviation of |v| for v with covariance `cov` (first order)."""
    grad = v / np.linalg.norm(v)
    return float(np.sqrt(grad @ cov @ grad))


def surface_bound(s, cov: np.ndarray, settings: DemoSettings, slope: float) -> dict:
    """Surface RMS bounds (mm). Matching alone (the true calibration, or the shape after a rigid fit) is held
    to the depth noise of DISPARITY_NOISE_PX at the sample, Z^2 / (f B) sigma_d. The joint calibration adds, in
    quadrature, what 3 sigma of it can do: a depth scale error (left focal length, baseline), Z sigma_scale,
    and a turn of the whole cloud with the left camera's pointing (principal point / f), which slides the
    domed face sideways by Z sigma_pointing and shows as depth error `slope` (RMS over the face) times that."""
    z, f, b = settings.distance_mm, settings.focal_px, settings.baseline_mm
    matching = z * z / (f * b) * DISPARITY_NOISE_PX
    std = dict(zip(s.names, np.sqrt(np.diag(cov))))
    k = BOUNDS["sigmas"]
    scale = k * z * np.hypot(std["left.fx"] / float(s.left.k[0]), _norm_sigma(s.T, cov[3:6, 3:6]) / s.baseline)
    pointing = k * z * slope * np.hypot(std["left.cx"], std["left.cy"]) / float(s.left.k[0])
    return {"matching_mm": matching, "scale_mm": float(scale), "pointing_mm": float(pointing),
            "joint_mm": float(np.linalg.norm([matching, scale, pointing]))}


def _row(parameter: str, unit: str, truth, joint, error, bound, sigma=None, thesis=None, thesis_error=None,
         error_unit: str | None = None) -> dict:
    return {"parameter": parameter, "unit": unit, "error_unit": error_unit or unit, "truth": truth,
            "thesis": thesis, "thesis_error": thesis_error, "estimate": joint, "error": error, "sigma": sigma,
            "bound": bound, "ok": bool(np.isfinite(error) and abs(error) <= bound)}


def compare(rig, job, s, cov: np.ndarray, surface: dict, settings: DemoSettings) -> dict:
    """One row per parameter: truth, the thesis's path (estimate, error), the joint refinement (estimate, error,
    sigma), the bound and whether the joint error is within it; then the subset and surface summaries. Rotation:
    truth and estimates are rotation angles, errors the angle of R_est R_true^T. Focal lengths and the baseline
    have errors in %, and their sigma too."""
    k_sig = BOUNDS["sigmas"]
    std = dict(zip(s.names, np.sqrt(np.diag(cov))))
    rows = []
    for side, true_cam, thesis_cam, cam in (("left", rig.left, job.full.left, s.left),
                                            ("right", rig.right, job.full.right, s.right)):
        kt, kh, ke = (np.asarray(c.k, float) for c in (true_cam, thesis_cam, cam))
        for j, name in enumerate(("fx", "fy", "cx", "cy")):
            sig = std[f"{side}.{name}"]
            if j < 2:
                pct = lambda v: 100 * (v / kt[j] - 1)  # noqa: E731
                rows.append(_row(f"{side} {name}", "px", kt[j], ke[j], pct(ke[j]), BOUNDS["focal_percent"],
                                 100 * sig / kt[j], kh[j], pct(kh[j]), "%"))
            else:
                rows.append(_row(f"{side} {name}", "px", kt[j], ke[j], ke[j] - kt[j],
                                 max(BOUNDS["principal_px"], k_sig * sig), sig, kh[j], kh[j] - kt[j]))
    r_true, t_true = rig.rotation_translation()
    b_true, b_thesis = float(np.linalg.norm(t_true)), float(np.linalg.norm(job.T))
    rows.append(_row("baseline |T|", "mm", b_true, s.baseline, 100 * (s.baseline / b_true - 1),
                     BOUNDS["baseline_percent"], 100 * _norm_sigma(s.T, cov[3:6, 3:6]) / s.baseline, b_thesis,
                     100 * (b_thesis / b_true - 1), "%"))
    rot_sigma = float(np.degrees(np.sqrt(np.trace(cov[0:3, 0:3]))))
    from dstereo.models.pose import rotation_vector

    angle = lambda r: float(np.degrees(np.linalg.norm(rotation_vector(r))))  # noqa: E731
    rows.append(_row("rotation R", "deg", angle(r_true), angle(s.R), rotation_error_deg(s.R, r_true),
                     max(BOUNDS["rotation_deg"], k_sig * rot_sigma), rot_sigma, angle(job.R),
                     rotation_error_deg(job.R, r_true)))
    bound = surface_bound(s, cov, settings, surface["rms_slope"])
    joint, thesis, ref = surface["joint"], surface["thesis"], surface["true_calibration"]
    rows.append(_row("surface RMS", "mm", 0.0, joint["rms_mm"], joint["rms_mm"], bound["joint_mm"],
                     thesis=thesis["rms_mm"], thesis_error=thesis["rms_mm"]))
    rows.append(_row("surface RMS, rigid fit", "mm", 0.0, joint["shape_rms_mm"], joint["shape_rms_mm"],
                     bound["matching_mm"], thesis=thesis["shape_rms_mm"], thesis_error=thesis["shape_rms_mm"]))
    rows.append(_row("surface RMS, true calibration", "mm", 0.0, ref["rms_mm"], ref["rms_mm"], bound["matching_mm"]))
    f = job.filtering
    stats = f.stats(len(f.steps))
    subsets = {
        "plan": job.plan.describe(), "per_set": int(job.plan.index.shape[1]), "solved": int(len(f.table)),
        "converged": int(f.usable.sum()), "survivors": int(f.survivors.sum()),
        "steps": [o.message for o in f.steps],
        "after_steps": {c: {"mean": stats[c]["mean"], "std": stats[c]["std"]} for c in ("stereo_re", "Tnorm",
                                                                                        "RVnorm")},
        "individual": {side: {"plan": c.plan.describe(), "rms_px": float(c.full.rms)}
                       for side, c in (("left", job.left), ("right", job.right))},
    }
    warnings = [f"{r['parameter']}: error {_num(r['error'])} {r['error_unit']} exceeds the bound "
                f"{_num(r['bound'])} {r['error_unit']}" for r in rows if not r["ok"]]
    return {"rows": rows, "ok": not warnings, "warnings": warnings, "calibration_warnings": list(job.warnings),
            "subsets": subsets, "surface": surface, "surface_bound": bound, "bounds": BOUNDS,
            "disparity_noise_px": DISPARITY_NOISE_PX,
            "stereo": {"pairs": len(job.detection.pairs), "dropped": len(job.detection.dropped),
                       "thesis_rms_px": job.full.rms, "joint_rms_px": s.rms, "joint_status": s.status_text}}


# --- rendering the comparison (shared by comparison.md and the console) ---------------------------------------


def _num(value, digits: int = 4) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.1f}"


TABLE_HEADER = ("parameter", "truth", "thesis path", "error", "joint", "error", "sigma", "bound", "check")


def table_rows(comparison: dict) -> list[tuple[str, ...]]:
    """One tuple of strings per row, in the columns of `TABLE_HEADER`."""
    out = []
    for r in comparison["rows"]:
        eu = " " + r["error_unit"]
        digits = 6 if r["unit"] == "px" and r["error_unit"] == "%" else 4

        def value(v):
            return "-" if v is None else (f"{v:.{digits}g}" if r["unit"] != "mm" or v > 10 else f"{v:.4f}")

        truth = "-" if r["parameter"].startswith("surface") else value(r["truth"])
        thesis_error = "" if r["thesis_error"] is None else _num(r["thesis_error"], 3) + eu
        out.append((f"{r['parameter']} [{r['unit']}]", truth, value(r["thesis"]), thesis_error, value(r["estimate"]),
                    _num(r["error"], 3) + eu, "" if r["sigma"] is None else _num(r["sigma"], 2) + eu,
                    _num(r["bound"], 3) + eu, "ok" if r["ok"] else "WARNING"))
    return out


def notes(comparison: dict) -> list[str]:
    """How to read the table, one sentence a line."""
    b, sb = comparison["bounds"], comparison["surface_bound"]
    return [
        "thesis path: each camera alone, then the rig with those intrinsics fixed (mean over the subsets surviving "
        "the stereo steps); joint: both cameras and the rig refined together. The check applies to the joint.",
        "sigma: the joint solve's standard deviation (Jacobian with scaled columns; corner noise from the fit).",
        f"bounds: fx, fy within {b['focal_percent']:g} %, baseline within {b['baseline_percent']:g} %; principal "
        f"points and rotation within max({b['principal_px']:g} px / {b['rotation_deg']:g} deg, {b['sigmas']:g} "
        "sigma), since a 7.6 deg field barely shows perspective on the board.",
        "rotation: truth and estimates are rotation angles; errors the angle of R_est R_true^T.",
        "surface: distance from the true surface along the true left camera's rays; 'rigid fit' after the best "
        "rigid motion of the cloud (its shape alone).",
        f"surface bounds: disparity noise {comparison['disparity_noise_px']:g} px -> {sb['matching_mm']:.3f} mm; "
        f"the joint calibration adds {b['sigmas']:g} sigma of depth scale ({sb['scale_mm']:.3f} mm) and of "
        f"pointing ({sb['pointing_mm']:.3f} mm) in quadrature.",
    ]


def surface_lines(comparison: dict) -> list[str]:
    """Surface RMS before/after the sub-pixel refinement, and the predicted depth std beside the measured error."""
    s = comparison["surface"]
    sz = s["sigma_z_mm"]
    return [
        f"surface RMS vs truth, SGBM -> refined: joint calibration {s['joint_sgbm']['rms_mm']:.4f} -> "
        f"{s['joint']['rms_mm']:.4f} mm, true calibration {s['true_calibration_sgbm']['rms_mm']:.4f} -> "
        f"{s['true_calibration']['rms_mm']:.4f} mm (mean {s['true_calibration_sgbm']['mean_mm']:+.4f} -> "
        f"{s['true_calibration']['mean_mm']:+.4f} mm); the refinement dropped "
        f"{100 * s['refine_dropped_fraction']:.2f} % of SGBM's pixels.",
        f"predicted depth std (joint covariance + per-pixel disparity noise, median {sz['sigma_d_px']:.3g} px): median "
        f"sigma_z {sz['median']:.4f} mm (calibration {sz['calibration_at_median_mm']:.4f}, disparity "
        f"{sz['disparity_at_median_mm']:.4f} mm at the median point) against the measured surface RMS "
        f"{s['joint']['rms_mm']:.4f} mm (true calibration, matching alone: {s['true_calibration']['rms_mm']:.4f} mm)."
        + ("" if sz["calibration_included"] else " Calibration uncertainty NOT included."),
    ]


def markdown(comparison: dict) -> str:
    """comparison.md: the table, the subset steps, the surface statistics and where everything is."""
    lines = ["# dstereo demo: estimates against the truth", "",
             "| " + " | ".join(TABLE_HEADER) + " |", "|" + "---|" * len(TABLE_HEADER)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(comparison)]
    sub = comparison["subsets"]
    lines += [""] + [f"- {n}" for n in notes(comparison)]
    lines += ["", f"## Stereo subsets, thesis path ({sub['plan']}, m = {sub['per_set']})", ""]
    lines += [f"- {m}" for m in sub["steps"]]
    lines += [f"- after the steps: {k} = {v['mean']:.6g} +- {v['std']:.3g}" for k, v in sub["after_steps"].items()]
    lines += ["", "## Sub-pixel refinement and predicted error", ""] + [f"- {n}" for n in surface_lines(comparison)]
    for key in ("joint", "thesis", "true_calibration", "joint_sgbm", "true_calibration_sgbm"):
        lines += ["", f"## Surface ({key.replace('_', ' ').replace('sgbm', 'SGBM only, no refinement')})", ""]
        lines += [f"- {k}: {_num(v) if isinstance(v, float) else v}" for k, v in comparison["surface"][key].items()]
    lines += ["", "## Files", ""] + [f"- {k}: `{v}`" for k, v in comparison["paths"].items()]
    if comparison["warnings"] or comparison["calibration_warnings"]:
        lines += ["", "## Warnings", ""]
        lines += [f"- {w}" for w in comparison["warnings"] + comparison["calibration_warnings"]]
    return "\n".join(lines) + "\n"
