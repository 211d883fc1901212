"""Frame rejection by the rig-consistency test on rendered images with OpenCV-detected corners (issue 29): the
K = 3 ring rig (`synth.multiview`), 24 frames, each camera's image rendered and detected, then the `--cameras` job's
joint solve and `jobs.calibrate_cameras.reject_inconsistent_frames`. Simultaneous frames against a board moved
SHIFT mm (a random direction per frame and camera) between the reference's exposure and the others'.

    python -m experiments.rig_frame_rejection_rendered [SEEDS]

Per seed and case: the rig flagged (the consistency test fails before any removal), the frames the job's rule
removes and whether the rig is consistent after, and the frames the per-frame rule alone (the rule before the job
asked the rig's own test first) picks in the first round, whatever the rig's p. Writes
results/rig_frame_rejection_rendered.json.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

SHIFTS = (0.0, 0.5)
K, FRAMES = 3, 24


def _render(folder: Path, seed: int, shift: float) -> None:
    from dstereo.synth.multiview import MULTIVIEW_BOARD, MULTIVIEW_OPTIONS, multiview_poses, ring_rig
    from dstereo.synth.poses import compose
    from dstereo.synth.render import camera_rays, render_board

    rig = ring_rig(K)
    poses, visible, _ = multiview_poses(rig, MULTIVIEW_BOARD, FRAMES, seed)
    rng = np.random.default_rng([seed, 11])
    for k, (cam, t_cam_ref) in enumerate(zip(rig.cameras, rig.T_cam_ref)):
        (folder / f"cam{k}").mkdir(parents=True)
        rays = camera_rays(cam, MULTIVIEW_OPTIONS.supersample)
        centre = camera_rays(cam, 1)
        for f, pose in enumerate(poses):
            if not visible[f, k]:
                continue
            seen = np.array(pose, float)
            if k > 0 and shift:
                step = rng.normal(size=3)
                seen[3:] += shift * step / np.linalg.norm(step)
            image, _ = render_board(cam, compose(t_cam_ref, seen), MULTIVIEW_BOARD, MULTIVIEW_OPTIONS,
                                    seed=[seed, k, f], rays=rays, centre_rays=centre)
            cv2.imwrite(str(folder / f"cam{k}" / f"frame_{f:03d}.png"), image)


def _old_rule(c) -> list[int]:
    """The frames the rule before this change removed: the same per-frame test, whatever the rig's own p."""
    from scipy import stats

    from dstereo.calib.rig_consistency import FRAME_ROBUST_SIGMAS

    shared = np.flatnonzero(c.frame_dof > 0)
    if len(shared) < 4:
        return []
    ratio = c.frame_statistic[shared] / c.frame_dof[shared]
    med = float(np.median(ratio))
    mad = 1.4826 * float(np.median(np.abs(ratio - med)))
    p = stats.chi2.sf(c.frame_statistic[shared], c.frame_dof[shared])
    return [int(f) for f in shared[(p < c.alpha / len(shared)) & (ratio > med + FRAME_ROBUST_SIGMAS * max(mad, 1e-12))]]


def one(seed: int, shift: float) -> dict:
    import dstereo.jobs.calibrate_cameras as job
    from dstereo.config.calibration import Config

    seen = {}
    real = job.reject_inconsistent_frames

    def recording(*args, **kwargs):
        first = real(*args[:10], False, *args[11:], **kwargs).consistency  # before any removal
        seen["first"] = first
        out = real(*args, **kwargs)
        seen["rejected"] = [name for name, _ in out.rejected]
        seen["after"] = out.consistency
        return out

    with tempfile.TemporaryDirectory() as tmp:
        _render(Path(tmp) / "cams", seed, shift)
        job.reject_inconsistent_frames = recording
        try:
            result = job.calibrate_cameras_project(Path(tmp) / "cams", Config(pattern=(9, 6), square=20.0))
        finally:
            job.reject_inconsistent_frames = real
    first = seen["first"]
    return {"seed": seed, "shift_mm": shift, "flagged": not first.consistent, "p_value": first.p_value,
            "ratio": first.ratio, "rejected": seen["rejected"], "consistent_after": seen["after"].consistent,
            "old_rule_would_remove": [first.frames[f] for f in _old_rule(first)], "frames": len(result.frames)}


def main(seeds: int = 20) -> None:
    rows = []
    for shift in SHIFTS:
        for seed in range(seeds):
            t0 = time.perf_counter()
            r = one(seed, shift)
            rows.append(r)
            print(f"shift {shift} seed {seed}: flagged {r['flagged']} (T/c {r['ratio']:.2f}, p {r['p_value']:.2g}), "
                  f"removed {r['rejected']}, consistent after {r['consistent_after']}, old rule "
                  f"{r['old_rule_would_remove']} ({time.perf_counter() - t0:.0f} s)", flush=True)
    for shift in SHIFTS:
        group = [r for r in rows if r["shift_mm"] == shift]
        print(f"shift {shift} mm: flagged {sum(r['flagged'] for r in group)}/{len(group)}, frames removed on "
              f"{sum(bool(r['rejected']) for r in group)}/{len(group)} seeds, old rule on "
              f"{sum(bool(r['old_rule_would_remove']) for r in group)}/{len(group)}")
    out = Path(__file__).parent / "results" / "rig_frame_rejection_rendered.json"
    out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20)
