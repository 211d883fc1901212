"""What a calibration run produced, for one camera, a stereo rig and N cameras (one `MultiviewJob` for any K, each
camera's `CameraCalibration` in it): the types the job (`dstereo.jobs`) fills and the writers (`dstereo.io`)
read. They live here, below both, so that io reads finished results by their type without importing the jobs that
make them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np

from dstereo.errors import DstereoError

if TYPE_CHECKING:  # annotations only: importing the solvers here would load scipy for every reader of a result
    from dstereo.calib.solution import Solution
    from dstereo.calib.rig_consistency import RigConsistency
    from dstereo.calib.rig_cross_validation import RigCrossValidation
    from dstereo.calib.rig_subsets import RigSubsets
    from dstereo.calib.coverage import Coverage
    from dstereo.calib.robust_steps import FilterResult
    from dstereo.config.calibration import Config


@dataclass
class CameraCalibration:
    """Everything one camera's run produced. `final` is what the camera file holds: with subsets the solve on
    the surviving subsets' views (or, with `final = "mean"`, the thesis's mean over surviving subsets, then in
    `subset_mean` too), else the full-set solve; `full` always holds the full-set solve."""

    config: Config
    folder: Path
    files: list[Path]
    detection: object  # dstereo.io.corners.Detection
    used: list[str]  # usable image names, in the order of `observations`
    observations: np.ndarray  # (V, n, 2) px
    full: object  # dstereo.calib.solution.Solution of the camera alone (K = 1)
    plan: object | None  # dstereo.calib.subsets.SubsetPlan
    subsets: object | None  # dstereo.calib.subsets.SubsetSolutions; None above KEEP_SOLUTIONS subsets (the
    # per-subset values and status are then only in `filtering.table`)
    filtering: FilterResult | None
    columns: tuple[str, ...]  # ("re", fx, fy, cx, cy, free coefficients...)
    final: dict[str, float]
    spread: dict[str, float]  # std over surviving subsets (NaN without subsets)
    coverage: Coverage
    model_advice: str | None
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    # With subsets: the survivors' solve, the thesis's subset mean and how they compare (calib/final_solution.py)
    final_solution: object | None = None
    subset_mean: dict[str, float] | None = None
    outliers: object | None = None  # dstereo.calib.outliers.OutlierReport: corners and views rejected
    residual_pattern: object | None = None  # dstereo.calib.misfit.ResidualPattern of the full-set solve (inliers)
    residual_pattern_all: object | None = None  # ... of the solve on every corner, before outlier rejection
    model_choice: object | None = None  # dstereo.calib.model_choice.ModelChoice with --model auto
    cross_validation: object | None = None  # dstereo.calib.cross_validation.CrossValidation (--cross-validate N)
    projection_method: str = "pose-compensated"  # of the projection-uncertainty map the results folder draws
    finished: object | None = None  # calib.finished.FinishedCamera: what the results folder shows

    @property
    def unconverged(self) -> list[int]:
        if self.filtering is None:
            return []
        return [int(i) for i in np.flatnonzero(~(self.filtering.table.status > 0))]

    @property
    def final_coefficients(self) -> np.ndarray:
        """(8,) distortion coefficients of `final`, OpenCV order (fisheye: cv2.fisheye's D in [:4]), zeros where
        not free."""
        from dstereo.models.distortion import coeff_slots

        return np.array([self.final.get(n, 0.0) if n else 0.0 for n in coeff_slots(tuple(self.config.model))])

    @property
    def final_camera_matrix(self) -> np.ndarray:
        f = self.final
        return np.array([[f["fx"], 0.0, f["cx"]], [0.0, f["fy"], f["cy"]], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class StereoSources:
    """Image files of the individual calibrations and of the stereo pairs (same lists when shared)."""

    mono_left: tuple[Path, ...]
    mono_right: tuple[Path, ...]
    stereo_left: tuple[Path, ...]
    stereo_right: tuple[Path, ...]
    description: str

    @property
    def shared(self) -> bool:
        return self.mono_left == self.stereo_left and self.mono_right == self.stereo_right


@dataclass
class MultiviewJob:
    """What the calibration job (`jobs.calibrate_cameras.calibrate_rig`) returns for any K: each camera's own
    calibration and, for K >= 2, the rig. One camera (K = 1) has no rig: `held` and `solution` are None, its frames
    are its views and `cameras[0]` is the whole result."""

    config: Config
    root: Path
    labels: tuple[str, ...]  # subfolder names, the reference first
    cameras: list[CameraCalibration]
    frames: list[str]  # frame names (image stems) seen by at least one camera
    visible: np.ndarray  # (F, K)
    observations: np.ndarray  # (F, K, n, 2), NaN where not seen
    held: Solution | None  # every camera held at its own calibration (None: one camera)
    solution: Solution | None  # the joint solve: cameras.yml (None: one camera)
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    inliers: np.ndarray | None = None  # (F, K, n) the corners the rig counted (each camera's kept ones); None: all
    consistency: RigConsistency | None = None  # calib/rig_consistency.py on the joint solve
    subsets: RigSubsets | None = None  # with `per_set`: the rig's frame subsets and stereo steps
    rejected_frames: list = field(default_factory=list)  # (frame, T_f / dof_f) the consistency test removed
    # the corners and inlier flags as the joint solve read them (views it re-read reversed: `multiview.as_solved`),
    # for writers that hand the solve on (mrcal's optimization inputs); None: `observations`, `inliers` as they are
    solved_observations: np.ndarray | None = None
    solved_inliers: np.ndarray | None = None
    cross_validation: RigCrossValidation | None = None  # --cross-validate N (calib/rig_cross_validation.py)
    pair_files: list = field(default_factory=list)  # calib.rig_pairs.PairCalibration of each stereo file (choose_pairs)
    pair_file: str | None = None  # the one pair's file name (a stereo rig's stereo.yml); None: stereo_<a>_<b>.yml
    sources: str | None = None  # where the images came from, in words (a stereo rig's flags or layout)
    # each camera's pose-compensated projection-uncertainty map of the joint solve (calib/rig_projection.py)
    projection: list | None = None

    @property
    def is_rig(self) -> bool:
        """K >= 2: a rig solve, its checks and files beside the cameras'."""
        return self.solution is not None

    def pairs(self, chosen: tuple[str, str] | None = None) -> list[tuple[int, int]]:
        """Camera index pairs that get a stereo.yml: `chosen` (two labels), else every adjacent pair."""
        return pair_indices(self.labels, self.root, chosen)

    def choose_pairs(self, chosen: tuple[str, str] | None = None) -> None:
        """The stereo files to write (`pairs`), each pair's rig and covariance computed (`calib.rig_pairs`)."""
        from dstereo.calib.rig_pairs import pair_calibration

        obj = self.cameras[0].detection.object_points
        self.pair_files = [pair_calibration(self.solution, a, b, obj) for a, b in self.pairs(chosen)]


def pair_indices(labels: tuple[str, ...], root: Path, chosen: tuple[str, str] | None) -> list[tuple[int, int]]:
    """`MultiviewJob.pairs`, from the camera labels alone (checked before the job runs)."""
    if chosen is None:
        return [(i, i + 1) for i in range(len(labels) - 1)]
    idx = []
    for name in chosen:
        if name not in labels:
            raise DstereoError(f"pair: no camera '{name}' under {root}; cameras are {', '.join(labels)}")
        idx.append(labels.index(name))
    if idx[0] == idx[1]:
        raise DstereoError(f"pair: {chosen[0]} twice; name two different cameras")
    return [tuple(idx)]
