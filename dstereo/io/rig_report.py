"""report.md sections shared by every rig's results folder (`--left/--right` and `--cameras`)."""

from __future__ import annotations


def consistency_markdown(rc: dict | None) -> list[str]:
    """report.md's section on the rig-consistency test (`calib/rig_consistency.py`, its `as_dict`)."""
    if rc is None:
        return []
    lines = ["", "## Rig consistency", "",
             f"Each camera alone (a board pose per view) against the rig (one pose per frame): T/c = "
             f"{rc['statistic']:.1f}/{rc['dof']} = {rc['ratio']:.2f} (1 expected), p = {rc['p_value']:.2g}: "
             + ("consistent." if rc["consistent"] else "**the rig does not explain its frames** (see Warnings)."),
             "", "| camera | RMS alone (px) | RMS rig (px) |", "|---|---|---|"]
    return lines + [f"| {c['camera']} | {c['rms_alone_px']:.4f} | {c['rms_rig_px']:.4f} |" for c in rc["cameras"]]


def cross_validation_markdown(cv: dict | None) -> list[str]:
    """report.md's section on the rig's cross-validation (`calib/rig_cross_validation.py`, its `as_dict`)."""
    if cv is None:
        return []
    lo, hi = cv["rig_band_if_right"]
    ilo, ihi = cv["intrinsics_band_if_right"]
    return ["", "## Rig cross-validation", "",
            f"{cv['splits']} random halvings of the frames, each half solved jointly: the halves' difference against "
            f"their +- (chi^2 / dof, 1 when the +- is right): placements {cv['rig_ratio']:.2f} (a right +- reads "
            f"{lo:.2f}-{hi:.2f}), intrinsics {cv['intrinsics_ratio']:.2f} ({ilo:.2f}-{ihi:.2f}): "
            + ("the rig's +- holds." if cv["trusted"] else "**the rig's +- is optimistic** (see Warnings)."),
            "", f"Band: {cv['band_note']}."]


def subsets_markdown(rs: dict | None) -> list[str]:
    """report.md's section on the rig's frame subsets and stereo steps (`calib/rig_subsets.py`, its `as_dict`)."""
    if rs is None:
        return []
    lines = ["", "## Rig subsets and stereo steps", "",
             f"{rs['subsets']} subsets of m = {rs['per_set']} frames ({'every one' if rs['exhaustive'] else 'a sample'}"
             f"), {rs['usable']} converged, {rs['surviving']} survive the steps; each stereo step filters every "
             "adjacent pair's column at once (`NAME@a-b`).", ""]
    lines += [f"- {m}" for m in rs["steps"]]
    left = rs["left_out_frames"]
    lines += ["", (f"Frames in no surviving subset, left out of the rig solve: {', '.join(left)}." if left else
                   "Every frame is in a surviving subset: the rig solve is on every frame."), "",
              "| column | mean | std over the surviving subsets |", "|---|---|---|"]
    lines += [f"| {name} | {v['mean']:.6g} | {v['std']:.3g} |" for name, v in rs["statistics"].items()]
    return lines
