"""`dstereo demo`: render a synthetic stereo experiment with known truth, calibrate, reconstruct, compare.

One run, all under `out/` (filled under a temporary name and renamed at the end):
    scenes/calibration/    chessboard pairs of the reduced Plasmatron rig (thesis layout) + truth.*
    scenes/sample/         the cork sample seen by both cameras, with each camera's true depth map
    calibration/           the `dstereo calibrate` stereo results folder (the thesis's path, below)
    calibration_joint/     stereo.yml / stereo.json of the joint refinement (below)
    reconstruction/        the `dstereo reconstruct` results folder of the sample pair (joint calibration,
                           sub-pixel refinement on, point sigmas from the joint covariance)
    comparison.json / .md  every estimate against its truth, with the bound it is held to
    report.html            comparison.md as one page for a browser, linking the calibration's and the reconstruction's

Calibration, the thesis's path (`jobs.calibrate_stereo`, as `dstereo calibrate` runs it): each camera alone
with C(N, m) subsets, the rig with those intrinsics held, its frame subsets filtered by the stereo steps of the
thesis's Figure 5.14; the thesis's answer is each camera's subset mean and the rig's mean over the surviving
subsets (what the comparison's "thesis path" shows; calibration/stereo.yml holds the job's joint solve on the
surviving frames, as every rig's `dstereo calibrate` writes). Then the demo's own joint refinement: both
cameras' intrinsics and the rig solved together on all pairs (`calib.multiview`, mode "joint", a flat board). The reduced rig
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

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dstereo.demo.comparison import compare
from dstereo.demo.report import markdown
from dstereo.demo.settings import DemoSettings, FULL, PATHS, QUICK, THESIS_STEREO_STEPS
from dstereo.demo.surface import rms_slope, surface_errors


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
        from dstereo.io.report_html import write_report_html

        write_report_html(tmp, source="comparison.md")  # the demo's page, as report.html
    return comparison


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


def thesis_config(board: dict, settings: DemoSettings, seed: int):
    """The calibration configuration of the thesis's stereo file (Figure 5.14) for the rendered board."""
    from dstereo.config.calibration import Config, validate

    return validate(Config(mode="stereo", pattern=tuple(board["pattern"]), square=float(board["square"]), unit="mm",
                           model=settings.model, per_set=settings.per_set, max_subsets=settings.max_subsets,
                           seed=seed, stereo_steps=THESIS_STEREO_STEPS,
                           final="mean"))  # the thesis's answer, shown as such beside the joint refinement


def calibrate_thesis(images: Path, folder: Path, board: dict, settings: DemoSettings, seed: int, report):
    """`dstereo calibrate`'s stereo job on images/images_left + images_right; writes its results folder."""
    from dstereo.jobs.calibrate_stereo import calibrate_stereo_project, stereo_sources
    from dstereo.io.cameras_files import write_results

    config = thesis_config(board, settings, seed)
    job = calibrate_stereo_project(stereo_sources(images, config), config, progress=report, use_cache=False)
    report("write calibration", 0, 1)
    write_results(folder, job)
    return job


def pair_corners(job) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(board, left corners, right corners, frame names) of the frames both cameras of a stereo job saw, as its
    rig solve read them (a view re-read reversed is in the solve's order)."""
    obs = job.solved_observations if job.solved_observations is not None else job.observations
    both = np.asarray(job.visible, bool).all(axis=1)
    return (job.cameras[0].detection.object_points, obs[both, 0], obs[both, 1],
            [f for f, b in zip(job.frames, both) if b])


@dataclass(frozen=True)
class JointRig:
    """The demo's joint refinement read as a stereo pair: the K = 2 joint solve (`calib.multiview.calibrate_views`,
    both cameras and the rig refined) with its values under stereo.yml's names (RVx..Tz of the right camera in the
    left's, then left.*, right.*: the solve's own order)."""

    solution: object  # calib.solution.Solution
    names: tuple[str, ...]
    R: np.ndarray
    T: np.ndarray
    E: np.ndarray
    F: np.ndarray

    @property
    def values(self) -> np.ndarray:
        return self.solution.values

    @property
    def poses(self) -> np.ndarray:
        return self.solution.poses

    @property
    def left(self):
        return self.solution.cameras[0]

    @property
    def right(self):
        return self.solution.cameras[1]

    @property
    def rms(self) -> float:
        return self.solution.rms

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.T))


def joint_rig(obj: np.ndarray, obs_left: np.ndarray, obs_right: np.ndarray, cameras) -> JointRig:
    """Both cameras (started at `cameras`) and the rig refined together on pairs seen by both (V, n, 2) each, on a
    flat board with every corner."""
    from dstereo.calib.multiview import calibrate_views
    from dstereo.calib.rig_pairs import pair_calibration
    from dstereo.models.rig import RIG_NAMES

    sol = calibrate_views(obj, np.stack([obs_left, obs_right], axis=1), np.ones((len(obs_left), 2), bool),
                          [c.image_size for c in cameras], mode="joint", cameras=list(cameras),
                          labels=("left", "right"))
    pair = pair_calibration(sol, 0, 1, obj)
    names = RIG_NAMES + sol.names[len(RIG_NAMES):]  # right.RVx.. -> RVx..: the right camera's pose is the rig
    return JointRig(sol, names, pair.R, pair.T, pair.E, pair.F)


def calibrate_joint(job, folder: Path, report):
    """Refine both cameras and the rig together on the job's pairs (a flat board, every corner), from its cameras;
    write stereo.yml and stereo.json (with `joint_covariance`'s standard deviations). Returns the `JointRig` and
    that covariance."""
    from dstereo.uncertainty.rig import JOINT_STRUCTURE
    from dstereo.io.results import atomic_folder, write_json
    from dstereo.io.stereo_files import write_stereo_yml

    from dstereo.jobs.calibrate_camera import camera_of

    report("joint refinement", 0, 1)
    obj, obs_l, obs_r, frames = pair_corners(job)
    s = joint_rig(obj, obs_l, obs_r, [camera_of(c) for c in job.cameras])
    sol = s.solution
    cov = joint_covariance(s, obj, obs_l, obs_r)
    with atomic_folder(folder, False) as tmp:
        write_stereo_yml(tmp / "stereo.yml", s.left.matrix(), s.left.coeffs(), s.right.matrix(), s.right.coeffs(),
                         s.R, s.T, s.E, s.F, s.left.image_size, s.right.image_size, rms=s.rms, cov=cov,
                         cov_names=s.names, cov_structure=JOINT_STRUCTURE + "; demo.joint_covariance",
                         unit="mm")  # the demo's board is in mm (demo_config)
        write_json(tmp / "stereo.json", {
            "mode": sol.mode, "status": sol.status_text, "names": s.names, "values": s.values,
            "std": np.sqrt(np.diag(cov)), "covariance": cov, "R": s.R, "T": s.T, "E": s.E, "F": s.F,
            "rms_px": s.rms, "stereo_re_px": float(np.mean(np.sqrt(np.nanmean(sol.per_view_rms ** 2, axis=1)))),
            "pairs": frames,
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


def reconstruct_sample(out: Path, rig, pair, settings: DemoSettings, report) -> dict:
    """Reconstruct the sample pair with the joint calibration (written to out/reconstruction), and with
    calibration/stereo.yml (key "thesis": `dstereo calibrate`'s) and the true calibrations (the latter: matching
    alone), all with the sub-pixel refinement; errors of each against the true surface, the joint and true ones also
    without the refinement (`*_sgbm`), and the joint reconstruction's predicted depth std (`sigma_z_mm`)."""
    from dstereo.io.calib_files import StereoCalibration, read_stereo_calibration
    from dstereo.io.reconstruction_files import write_atomically, write_pair
    from dstereo.stereo.reconstruct import ReconstructionConfig, reconstruct_calibrated
    from dstereo.io.images import read_image

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
