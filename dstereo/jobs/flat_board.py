"""A rig asked to solve on a flat board (`--no-board-sag`): that assumption checked on each camera's own views."""

from __future__ import annotations

import numpy as np

SAG_ALARM_Z = 3.0  # a sag this many of its own (reported) sigmas from zero: the flat board the rig assumes is wrong


def flat_board_check(cams: dict, warnings: list[str]) -> list[str]:
    """Solve each camera (label -> `CameraCalibration`) once more with the board's sag (one full-set solve each,
    ~0.1 s) and, where the sag lies beyond SAG_ALARM_Z of its sigma, warn with the figures and how far the camera's
    focal length moves (the synthetic 0.3 mm sag biased a flat solve's fx by 8.6 px; the real boards here sag 3-23
    sigma). Returns the cameras' findings (empty: none measured a sag)."""
    from dstereo.calib.mono import calibrate_full
    from dstereo.uncertainty.view_effects import reported_std

    found = []
    for label, cal in cams.items():
        flat = cal.full
        if flat.camera().lens == "splined":
            continue
        sagged = calibrate_full(cal.detection.object_points, cal.observations, cal.detection.image_size,
                                free=tuple(flat.camera().dist.free), inliers=flat.camera_inliers(), board_warp=True)
        if not sagged.converged:
            continue
        std = reported_std(sagged)
        z = np.abs(sagged.board_sag) / np.maximum(std[-2:], 1e-300)
        if np.max(z) > SAG_ALARM_Z:
            dfx = float(sagged.values[0] - flat.values[0])
            found.append(f"camera {label}: sag x {sagged.board_sag[0]:+.4g}, y {sagged.board_sag[1]:+.4g} "
                         f"{cal.config.unit} ({np.max(z):.1f} sigma), RMS {flat.rms:.4f} -> {sagged.rms:.4f} px, "
                         f"fx moves {dfx:+.3g} px ({abs(dfx) / std[0]:.1f} sigma)")
    if found:
        warnings.append("the board is not flat, but --no-board-sag assumes it is: " + "; ".join(found)
                        + ". The cameras and the rig are biased by it; leave --no-board-sag out to solve the sag")
    return found
