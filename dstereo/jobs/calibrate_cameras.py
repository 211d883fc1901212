"""The calibration job for any K (`calibrate_rig`): `dstereo calibrate --images DIR` (K = 1, `calibrate_images`),
`--cameras DIR` (`calibrate_cameras_project`) and a stereo rig (`jobs/calibrate_stereo.py`) all run it.

One camera (K = 1) is its camera stage alone (`jobs/calibrate_camera.py`: detection, the full-set solve, outliers,
`--model auto`, subsets and steps, the survivors' solve, cross-validation): there is no rig to solve.

The cameras come as sources (`jobs.rig_sources`): each camera's own images and its image of each rig frame. For
`--cameras DIR`, DIR's subfolders (sorted by name; the first is the reference) each hold one camera's images; an
image of the same name (stem) in two subfolders is one frame, seen by both; a camera may miss any frame. A stereo
rig's sources are its two cameras' individual images and the pairs (`rig_sources.stereo_pair_sources`). Each
camera is first calibrated alone by the one-camera pipeline (its own results: corners, outliers, subsets and steps
as configured, `--model auto` among the parametric lenses), then all cameras and frames together on the corners each
camera kept: the rig with every camera held at its own calibration, then everything jointly (`calib/multiview.py`). The
joint solve is what cameras.yml holds; the held one is reported beside it, and the joint one is tested against
each camera alone (`calib/rig_consistency.py`: do the frames show one board at one moment for every camera?);
a frame the rig cannot explain while the other frames can leaves the rig solve when the rig fails the test
(`reject_inconsistent_frames`, with outlier rejection). With images per set m, the rig's frame subsets and the
thesis's stereo steps on every adjacent pair come before (`calib/rig_subsets.py`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dstereo.calib.multiview import as_solved, calibrate_views
from dstereo.calib.solution import Solution
from dstereo.calib.calibrations import CameraCalibration, MultiviewJob, pair_indices
from dstereo.jobs.calibrate_camera import calibrate_camera, camera_of, list_camera_images
from dstereo.calib.rig_consistency import MAX_FRAME_ROUNDS, RIG_RMS_FACTOR, RigConsistency, of_multiview
from dstereo.calib.rig_cross_validation import cross_validate_rig
from dstereo.calib.rig_projection import rig_maps
from dstereo.calib.rig_subsets import run_rig_subsets
from dstereo.config.calibration import Config
from dstereo.errors import DstereoError
from dstereo.jobs.flat_board import flat_board_check
from dstereo.jobs.rig_sources import CameraSource, folder_sources

# A baseline below this fraction of the board's size (its inner corners' diagonal) is no baseline. Identical left
# and right images (a right folder holding copies of the left's) fit with |T| = 2.2e-9 mm; two cameras sit at least
# a lens apart, and a board is seen by both from a distance of a few board sizes at most (a 1e-3 board baseline:
# 0.24 mm against the 83 mm of the opencv_stereo rig, whose board is 236 mm across with 25 mm squares).
SAME_PLACE_BOARD_FRACTION = 1e-3


class _Prefixed:
    """A progress callback whose stages (and notes) are prefixed with the camera's label."""

    def __init__(self, progress, label: str):
        self.progress, self.label = progress, label

    def __call__(self, stage: str, done: int, total: int) -> None:
        self.progress(f"{self.label} {stage}", done, total)

    def note(self, text: str) -> None:
        if getattr(self.progress, "note", None) is not None:
            self.progress.note(f"{self.label} camera: {text}")


def _prefixed(progress, label: str):
    return None if progress is None else _Prefixed(progress, label)


def camera_folders(root: Path, config: Config) -> list[Path]:
    """The camera subfolders of `root` (sorted), each with images; refused with what was found otherwise."""
    root = Path(root)
    if not root.is_dir():
        raise DstereoError(f"cameras: {root} is not a folder; give a folder with one subfolder of images per camera")
    subs = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    with_images = [p for p in subs if _images(p, config)]
    if len(with_images) < 2:
        raise DstereoError(f"cameras: {root} has {len(with_images)} subfolder(s) with images "
                           f"({', '.join(p.name for p in subs) or 'none'}); a rig needs one subfolder per camera, "
                           "at least two")
    return with_images


def _images(folder: Path, config: Config) -> list[Path]:
    try:
        return list_camera_images(folder, config)
    except DstereoError:
        return []


def frame_table(cams: list[CameraCalibration], sources: list[CameraSource],
                others: list) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(frame names, visible (F, K), observations (F, K, n, 2), inliers (F, K, n)) of the sources' frames. A frame
    image among its camera's own images gives the corners that camera's calibration used, and its outlier mask (a
    rejected corner is no inlier of the rig either: the rig is solved on the corners each camera kept); one its
    calibration did not use (no board, or rejected whole by outlier rejection) is not seen. Another image (a stereo
    pair beside the individual images) gives its own detection (`others[k]`, `frame_detections`), every corner."""
    n = cams[0].observations.shape[1]
    seen: list[dict[str, tuple[np.ndarray, np.ndarray]]] = []
    for cal, source, other in zip(cams, sources, others):
        row = {name: i for i, name in enumerate(cal.used)}
        own = {Path(f).resolve(): Path(f).name for f in cal.files}
        views = {}
        for frame, path in source.frames:
            name = own.get(Path(path).resolve())
            if name is not None:
                if name in row:
                    i = row[name]
                    views[frame] = (cal.observations[i], np.ones(n, bool) if cal.full.inliers is None
                                    else cal.full.camera_inliers()[i])
            elif other is not None and Path(path).name in other.corners:
                views[frame] = (other.corners[Path(path).name], np.ones(n, bool))
        seen.append(views)
    frames = sorted(set().union(*seen))
    obs = np.full((len(frames), len(cams), n, 2), np.nan)
    inliers = np.zeros((len(frames), len(cams), n), bool)
    for k, views in enumerate(seen):
        for f, frame in enumerate(frames):
            if frame in views:
                obs[f, k], inliers[f, k] = views[frame]
    return frames, np.isfinite(obs[..., 0, 0]), obs, inliers


def frame_detections(cams: list[CameraCalibration], sources: list[CameraSource], config: Config,
                     use_cache: bool = True) -> list:
    """Per camera, the detection of its frame images that are not among its own images (None when all are): the
    stereo pairs of a thesis layout with separate individual and stereo folders. One camera has one image size."""
    from dstereo.io.corners import detect_folder

    out = []
    for cal, source in zip(cams, sources):
        own = {Path(f).resolve() for f in cal.files}
        files = [Path(p) for _, p in source.frames if Path(p).resolve() not in own]
        if not files:
            out.append(None)
            continue
        det = detect_folder(files[0].parent, config.pattern, config.square, files=files, use_cache=use_cache)
        if det.corners and det.image_size != cal.detection.image_size:
            raise DstereoError(f"camera {source.label}: its own images are {cal.detection.image_size} px but its "
                               f"frame images ({files[0].parent}) are {det.image_size} px; one camera has one image "
                               "size")
        out.append(det)
    return out


def calibrate_images(folder: Path, config: Config, progress=None, use_cache: bool = True, scratch: Path | None = None,
                     after_steps=None, cross_validate: int = 0, projection_range: float | None = None,
                     projection_method: str = "pose-compensated") -> MultiviewJob:
    """`--images DIR` (or PROJECT/images): the job (`calibrate_rig`) on a rig of one camera, DIR's images."""
    folder = Path(folder)
    files = tuple(list_camera_images(folder, config))
    source = CameraSource(folder.name or "camera", files, (), str(folder))
    return calibrate_rig([source], config, folder, progress, use_cache, scratch, cross_validate, projection_range,
                         after_steps=after_steps, projection_method=projection_method)


def calibrate_cameras_project(root: Path, config: Config, progress=None, use_cache: bool = True,
                              scratch: Path | None = None, cross_validate: int = 0,
                              projection_range: float | None = None,
                              pairs: tuple[str, str] | None = None) -> MultiviewJob:
    """`--cameras DIR`: the rig of DIR's camera subfolders (module docstring, `calibrate_rig`)."""
    _check_steps(config)
    folders = camera_folders(root, config)
    sources = folder_sources(folders, lambda folder: list_camera_images(folder, config))
    return calibrate_rig(sources, config, Path(root), progress, use_cache, scratch, cross_validate,
                         projection_range, pairs)


def _check_steps(config: Config) -> None:
    if config.stereo_steps and config.per_set is None:
        raise DstereoError("stereo steps need subsets of frames; set images per set (`per_set` m)")


def calibrate_rig(sources: list[CameraSource], config: Config, where: Path, progress=None, use_cache: bool = True,
                  scratch: Path | None = None, cross_validate: int = 0, projection_range: float | None = None,
                  pairs: tuple[str, str] | None = None, warnings: list[str] | None = None,
                  pair_file: str | None = None, after_steps=None,
                  projection_method: str = "pose-compensated") -> MultiviewJob:
    """Run the job of the module docstring on K camera sources (`jobs.rig_sources`; `where`: the rig's folder, for
    messages). Raises DstereoError for folders, boards or frames that cannot make one rig. `cross_validate`: that
    many random halvings of the frames (`calib/rig_cross_validation.py`). `pairs`: the two cameras (labels) that
    get a stereo file, else every adjacent pair (`choose_pairs`). `warnings`: the sources' own, reported first.
    `pair_file`: the one pair's file name (a stereo rig's `stereo.yml`), else stereo_<a>_<b>.yml.

    K = 1 (`calibrate_images`): the camera's stage is the whole job, with the one-camera settings: `cross_validate`
    halves its views (`calib/cross_validation.py`), its projection-uncertainty map by `projection_method`, and
    `after_steps(filtering, full)` once its subsets' steps are done (`calibrate_camera`)."""
    if len(sources) == 1:
        return _one_camera(sources[0], config, where, progress, use_cache, scratch, cross_validate,
                           projection_range, after_steps, projection_method)
    t0 = time.perf_counter()
    _check_steps(config)
    labels = tuple(s.label for s in sources)
    pair_indices(labels, Path(where), pairs)  # a wrong --pair is refused before any work
    cams, warnings, timings = [], list(warnings or []), {}
    for source in sources:
        t = time.perf_counter()
        label, cfg = source.label, source.config if source.config is not None else config
        try:
            cal = calibrate_camera(Path(source.images[0]).parent if source.images else Path(source.where), cfg,
                                   files=list(source.images), progress=_prefixed(progress, label),
                                   use_cache=use_cache, scratch=scratch, in_rig=True,
                                   projection_range=projection_range)
        except DstereoError as exc:
            raise DstereoError(f"camera {label} ({source.where}): {exc}") from None
        cams.append(cal)
        warnings += [f"camera {label}: {w}" for w in cal.warnings if w not in config.warnings]
        timings[f"{label}_s"] = time.perf_counter() - t
    shapes = {cal.detection.object_points.shape for cal in cams}
    if len(shapes) != 1 or any(not np.allclose(c.detection.object_points, cams[0].detection.object_points)
                               for c in cams):
        raise DstereoError("cameras: the cameras' boards differ (pattern or square); one rig calibrates from one board")
    if not config.board_sag:
        flat_board_check(dict(zip(labels, cams)), warnings)
    frames, visible, obs, inliers = frame_table(cams, sources, frame_detections(cams, sources, config,
                                                                             use_cache))
    shared = visible.sum(axis=1)
    lonely = [frames[f] for f in np.flatnonzero(shared < 2)]
    if len(lonely) == len(frames):
        raise DstereoError(f"cameras: no image name occurs in two camera folders under {where}; frames are matched by "
                           "file name (cam0/0001.png with cam1/0001.png)")
    if lonely:
        warnings.append(f"{len(lonely)} of {len(frames)} frames are seen by one camera only ({', '.join(lonely[:5])}"
                        f"{', ...' if len(lonely) > 5 else ''}): they refine that camera's lens but not the rig")
    t = time.perf_counter()
    if progress is not None:
        progress("rig solve", 0, 2)
    start = [camera_of(c) for c in cams]
    sizes = [c.detection.image_size for c in cams]
    obj = cams[0].detection.object_points
    sag = config.board_sag
    rig_inliers = None if inliers[visible].all() else inliers
    held = calibrate_views(obj, obs, visible, sizes, mode="fixed", cameras=start, labels=labels, board_warp=sag,
                           inliers=rig_inliers)
    if progress is not None:
        progress("rig solve", 1, 3)
    subsets = None
    if config.per_set is not None:
        subsets = run_rig_subsets(config, held, obj, obs, visible, rig_inliers, labels, frames, scratch, progress)
        warnings += subsets.warnings
        if config.final == "mean":
            warnings.append("--final mean: each camera's file holds its subset mean; the rig in cameras.yml is the "
                            "solve on the surviving frames (a K-camera rig has no one subset mean: each pair's is in "
                            "cameras.json, rig_subsets.statistics)")
        if subsets.left_out:  # final = the survivors' solve: the frames in no surviving subset leave the rig
            keep = subsets.frames
            frames, visible, obs = [f for f, k in zip(frames, keep) if k], visible[keep], obs[keep]
            inliers = inliers[keep]
            rig_inliers = None if rig_inliers is None else rig_inliers[keep]
            held = calibrate_views(obj, obs, visible, sizes, mode="fixed", cameras=start, labels=labels,
                                   board_warp=sag, inliers=rig_inliers)
    # Frame rejection by the consistency test, with outlier rejection: only from a rig that fails the test
    # (`RigConsistency.outlying_frames`; a passing rig's highest frame is a view's own detection error)
    rig = reject_inconsistent_frames(obj, obs, visible, sizes, start, labels, sag, inliers, rig_inliers, frames,
                                     config.outlier_rejection, progress)
    joint, consistency, rejected = rig.joint, rig.consistency, rig.rejected
    frames, visible, obs, inliers, rig_inliers = rig.frames, rig.visible, rig.obs, rig.inliers, rig.rig_inliers
    if rejected:
        held = calibrate_views(obj, obs, visible, sizes, mode="fixed", cameras=start, labels=labels, board_warp=sag,
                               inliers=rig_inliers)
        warnings.append(f"{len(rejected)} frame(s) the rig cannot explain (the others can) left the rig solve: "
                        + ", ".join(f"{n} ({r:.1f}x its constraints)" for n, r in rejected)
                        + "; check their exposures (simultaneous?) or pairing; --no-outlier-rejection keeps them")
    if progress is not None:
        progress("rig solve", 3, 3)
    timings["rig_s"] = time.perf_counter() - t
    cv = None
    if cross_validate:
        t = time.perf_counter()
        if progress is not None:
            progress("rig cross-validation", 0, 1)
        cv = cross_validate_rig(obj, obs, visible, sizes, start, labels, cross_validate, seed=config.seed or 0,
                                inliers=rig_inliers, board_warp=sag)
        if progress is not None:
            progress("rig cross-validation", 1, 1)
        timings["rig_cross_validation_s"] = time.perf_counter() - t
    solved_obs, solved_inliers = as_solved(obs, rig_inliers, joint.flipped)
    t = time.perf_counter()
    maps = rig_maps(joint, obj, solved_obs, solved_inliers, projection_range)
    timings["rig_projection_s"] = time.perf_counter() - t
    job = MultiviewJob(config, Path(where), labels, cams, frames, visible, obs, held, joint, warnings, timings,
                       inliers=rig_inliers, consistency=consistency, cross_validation=cv, subsets=subsets,
                       rejected_frames=rejected, solved_observations=solved_obs, solved_inliers=solved_inliers,
                       pair_file=pair_file, projection=maps)
    _check(job)
    job.choose_pairs(pairs)
    timings["total_s"] = time.perf_counter() - t0
    return job


def _one_camera(source: CameraSource, config: Config, where: Path, progress, use_cache: bool, scratch,
                cross_validate: int, projection_range, after_steps, projection_method: str) -> MultiviewJob:
    """A rig of one camera: its calibration (`calibrate_camera`) and no rig (`MultiviewJob.solution` None)."""
    cal = calibrate_camera(Path(source.where), config, files=list(source.images), progress=progress,
                           use_cache=use_cache, scratch=scratch, after_steps=after_steps,
                           cross_validate=cross_validate, projection_range=projection_range,
                           projection_method=projection_method)
    return MultiviewJob(config, Path(where), (source.label,), [cal], list(cal.used),
                        np.ones((len(cal.used), 1), bool), cal.observations[:, None], None, None,
                        warnings=cal.warnings, timings=cal.timings)


@dataclass
class RigFrames:
    """The joint rig solve, its consistency test and the frames it was solved on."""

    joint: Solution
    consistency: RigConsistency
    frames: list[str]
    visible: np.ndarray
    obs: np.ndarray
    inliers: np.ndarray
    rig_inliers: np.ndarray | None
    rejected: list  # (frame, T_f / dof_f), in the order removed


def reject_inconsistent_frames(obj, obs, visible, sizes, start, labels, sag, inliers, rig_inliers, frames,
                               reject: bool = True, progress=None) -> RigFrames:
    """The joint solve and its consistency test; with `reject`, the worst frame the rig cannot explain and the
    others can (`RigConsistency.outlying_frames`) leaves and the rig is solved again, one frame a round (one bad
    frame pulls the rig and raises the others' statistics with it), until none is left, MAX_FRAME_ROUNDS, or four
    frames seen by two cameras remain. A rig still inconsistent after its removals keeps every frame (the first
    solve, with a note): its cause is not a frame, and removing some would only lose data (rendered K = 3 rigs with
    the board moved 0.5 mm between exposures lost 0-5 frames each and stayed inconsistent).
    On exact-corner renders (24 frames, one exposed 1 mm away by every camera but the reference): that frame
    removed and the rest consistent on 17 of 18 seeds of K = 2, 3, 4 (the 18th: nothing removed, consistent);
    simultaneous: nothing removed on 18 of 18. Rendered images, OpenCV-detected corners:
    `experiments/rig_frame_rejection_rendered.py`."""
    rejected, first = [], None
    while True:
        joint = calibrate_views(obj, obs, visible, sizes, mode="joint", cameras=start, labels=labels,
                                board_warp=sag, inliers=rig_inliers)
        if progress is not None:
            progress("rig solve", 2, 3)
        consistency = of_multiview(joint, obj, obs, rig_inliers, frames)
        now = RigFrames(joint, consistency, frames, visible, obs, inliers, rig_inliers, list(rejected))
        first = now if first is None else first
        bad = consistency.outlying_frames() if reject else []
        if not bad or len(rejected) == MAX_FRAME_ROUNDS or int((visible.sum(axis=1) >= 2).sum()) <= 4:
            if rejected and not consistency.consistent:
                first.consistency.notes.append(
                    f"removing the frame(s) the rig could not explain ({', '.join(n for n, _ in rejected)}) in turn "
                    "did not make it consistent: every frame is kept (the cause is not one frame)")
                return first
            return now
        f = bad[0]
        rejected.append((frames[f], float(consistency.frame_statistic[f] / consistency.frame_dof[f])))
        keep = np.arange(len(frames)) != f
        frames, visible, obs, inliers = [n for n, k in zip(frames, keep) if k], visible[keep], obs[keep], inliers[keep]
        rig_inliers = None if rig_inliers is None else rig_inliers[keep]


def _check(job: MultiviewJob) -> None:
    """Refuse a rig that does not fit its frames; warn of what the user should know."""
    sol = job.solution
    own = np.array([float(c.full.rms) for c in job.cameras])
    if sol.rms > max(RIG_RMS_FACTOR * own.max(), 1.0):
        per = ", ".join(f"{lab} {r:.3g}" for lab, r in zip(job.labels, sol.camera_rms()))
        raise DstereoError(
            f"cameras: the rig fits its {len(job.frames)} frames with RMS {sol.rms:.3g} px (per camera: {per}) while "
            f"the cameras alone fit theirs with {', '.join(f'{r:.3g}' for r in own)} px: images of one name do not "
            "show the board at one moment (check the names and the cameras' synchronisation); nothing written")
    _check_camera_baselines(job)
    for name, s in (("held", job.held), ("joint", sol)):
        if not s.converged:
            job.warnings.append(f"the {name} rig solve did not converge ({s.status_text}); its values are unreliable")
    if job.consistency is not None and job.consistency.warning() is not None:
        job.warnings.append(job.consistency.warning())
    if job.cross_validation is not None and not job.cross_validation.trusted:
        job.warnings.append(job.cross_validation.verdict())
    if sol.flipped:
        views = ", ".join(f"{job.labels[c]}/{job.frames[f]}" for f, c in sol.flipped[:6])
        job.warnings.append(f"{len(sol.flipped)} view(s) had their corners in reversed order against the other "
                            f"cameras' and were re-read reversed ({views})")


def _check_camera_baselines(job: MultiviewJob) -> None:
    """Two cameras at one place (one camera's images copied into another's folder) are refused
    (SAME_PLACE_BOARD_FRACTION of the board's size)."""
    board = job.cameras[0].detection.board
    size = board.square * float(np.hypot(board.cols - 1, board.rows - 1))
    n = len(job.labels)
    for a in range(n):
        for b in range(a + 1, n):
            baseline = float(np.linalg.norm(np.asarray(job.solution.relative(a, b)[1], float)))
            if baseline < SAME_PLACE_BOARD_FRACTION * size:
                raise DstereoError(
                    f"cameras {job.labels[a]} and {job.labels[b]}: baseline {baseline:.3g} {job.config.unit} (the "
                    f"board is {size:.3g} {job.config.unit} across): their images show the board from the same "
                    "place: are they the same images? Give each camera's own images; nothing written")
