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
