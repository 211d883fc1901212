"""The two-camera calibration from image folders alone (pairs, each camera's full-set solve, the rig, optionally
subsets of pairs), without the configuration and steps of `stereo_pipeline` (which `dstereo calibrate` runs):
the short path tests and experiments take to a calibrated rig from real images."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dstereo.calib.mono import CameraSolution, calibrate_full
from dstereo.calib.stereo import (StereoSolution, StereoSubsetSolutions, calibrate_stereo, camera_from_solution,
                                  solve_stereo_subsets)
from dstereo.calib.subsets import plan_subsets
from dstereo.errors import DstereoError
from dstereo.io.corners import Detection, detect_folder
from dstereo.io.stereo_files import DroppedPair, StereoDetection, detect_pairs, image_files
from dstereo.models.camera import Camera
from dstereo.models.distortion import COEFF_NAMES, PRESETS


@dataclass
class StereoCalibrationResult:
    """Individual calibrations, the rig on all pairs and (optionally) on subsets of pairs. Nothing printed."""

    detection: StereoDetection  # the stereo pairs, their corners and the dropped pairs
    mono_left: CameraSolution  # individual calibrations (full set)
    mono_right: CameraSolution
    mono_detection_left: Detection  # the images the individual calibrations used
    mono_detection_right: Detection
    stereo: StereoSolution
    subsets: StereoSubsetSolutions | None = None
    timings: dict = field(default_factory=dict)

    @property
    def pairs(self) -> list[tuple[str, str]]:
        return self.detection.pairs

    @property
    def dropped(self) -> list[DroppedPair]:
        return self.detection.dropped

    def to_dict(self) -> dict:
        """JSON-ready summary: cameras, rig with Jacobian standard deviations, E, F, per-pair errors."""
        s = self.stereo
        cams = {side: {"fx": float(c.k[0]), "fy": float(c.k[1]), "cx": float(c.k[2]), "cy": float(c.k[3]),
                       "coeffs": dict(zip(COEFF_NAMES, map(float, c.dist.coeffs))), "free": list(c.dist.free),
                       "image_size": list(c.image_size)} for side, c in (("left", s.left), ("right", s.right))}
        out = {
            "mode": s.mode, "status": s.status_text, "iterations": s.iterations, "cameras": cams,
            "R": s.R, "rvec": s.rvec, "T": s.T, "E": s.E, "F": s.F,
            "parameters": {n: {"value": float(v), "std": float(e)} for n, v, e in zip(s.names, s.values, s.std)},
            "baseline": {"value": s.baseline, "std": s.baseline_std},
            "rotation_angle_rad": {"value": float(np.linalg.norm(s.rvec)), "std": s.angle_std},
            "rms_px": s.rms, "stereo_re_px": s.stereo_re, "conditioning": s.conditioning.message(),
            "pairs": [{"left": a, "right": b, "rms_px": float(e)} for (a, b), e in zip(self.pairs, s.per_pair_rms)],
            "dropped": [{"left": d.left, "right": d.right, "reason": d.reason} for d in self.dropped],
            "individual": {side: {"rms_px": m.rms, "status": m.status_text, "images": len(m.poses),
                                  **{n: {"value": float(v), "std": float(e)}
                                     for n, v, e in zip(m.names, m.values, m.std)}}
                           for side, m in (("left", self.mono_left), ("right", self.mono_right))},
        }
        if self.subsets is not None:
            sub, ok = self.subsets, self.subsets.converged
            cols = sub.columns()
            out["subsets"] = {"plan": sub.plan.describe(), "per_set": int(sub.plan.index.shape[1]),
                              "converged": int(ok.sum()), "total": len(ok),
                              **{k: {"mean": float(np.mean(v[ok])), "std": float(np.std(v[ok], ddof=1))}
                                 for k, v in cols.items() if ok.sum() > 1}}
        return out


def _calibrate_one(det: Detection, free: tuple[str, ...], side: str) -> CameraSolution:
    names = [n for n in det.names if n in det.corners] or sorted(det.corners)
    try:
        return calibrate_full(det.object_points, np.stack([det.corners[n] for n in names]), det.image_size, free)
    except DstereoError as exc:
        raise DstereoError(f"{side} camera: {exc}") from None


def calibrate_stereo_folders(
    left,
    right,
    pattern: tuple[int, int],
    square: float,
    free_left: tuple[str, ...] = PRESETS["default"],
    free_right: tuple[str, ...] = PRESETS["default"],
    per_set: int | None = None,
    *,
    mono_left=None,
    mono_right=None,
    mode: str = "fixed",
    cameras: tuple[Camera, Camera] | None = None,
    max_subsets: int = 2000,
    seed: int = 0,
    suffix: str | None = None,
    use_cache: bool = True,
    progress=None,
) -> StereoCalibrationResult:
    """Stereo calibration from image folders (or image lists), pairs matched by name (`io.pairing`).

    The individual calibrations use `mono_left`/`mono_right` when given (the thesis's images_left/right), else
    every image of `left`/`right` that shows the board; `cameras` skips them and fixes the intrinsics to the
    given models. Then the rig on all pairs (`mode` "fixed" or "joint") and, with `per_set` = m, on the
    C(pairs, m) subsets (at most `max_subsets`, seeded sample beyond). `progress(stage, done, total)` is called
    along the way. Errors (DstereoError): left/right counts differ, mixed image sizes in one camera, no pair
    with the board in both images, too few views.
    """
    report = (lambda stage: (lambda d, t: progress(stage, d, t))) if progress else (lambda stage: None)  # noqa: E731
    t0 = time.perf_counter()
    det = detect_pairs(left, right, pattern, square, suffix, use_cache, report("detect stereo pairs"))
    mono_dets = []
    for side, source, stereo_det in (("left", mono_left, det.left), ("right", mono_right, det.right)):
        if source is None:
            mono_dets.append(stereo_det)
            continue
        files = image_files(source, suffix)
        mono_det = detect_folder(files[0].parent, pattern, square, files=files, use_cache=use_cache,
                                 progress=report(f"detect {side}"))
        if mono_det.image_size != stereo_det.image_size:
            raise DstereoError(
                f"{side} camera: individual calibration images are {mono_det.image_size[0]}x{mono_det.image_size[1]} "
                f"but stereo images are {stereo_det.image_size[0]}x{stereo_det.image_size[1]}; one camera has one size"
            )
        mono_dets.append(mono_det)
    timings = {"detect_s": time.perf_counter() - t0}
    t1 = time.perf_counter()
    mono_l = _calibrate_one(mono_dets[0], tuple(free_left), "left")
    mono_r = _calibrate_one(mono_dets[1], tuple(free_right), "right")
    cam_l, cam_r = cameras if cameras is not None else (camera_from_solution(mono_l), camera_from_solution(mono_r))
    timings["individual_s"] = time.perf_counter() - t1
    obs_l, obs_r = det.observations()
    stereo = calibrate_stereo(det.object_points, obs_l, obs_r, cam_l, cam_r, mode)
    timings["stereo_s"] = stereo.timings["solve_s"]
    subsets = None
    if per_set is not None:
        plan = plan_subsets(len(det.pairs), per_set, cap=max_subsets, seed=seed)
        subsets = solve_stereo_subsets(det.object_points, obs_l, obs_r, plan, stereo, progress=report("subsets"))
        timings["subsets_s"] = subsets.timings["solve_s"]
    return StereoCalibrationResult(det, mono_l, mono_r, mono_dets[0], mono_dets[1], stereo, subsets, timings)
