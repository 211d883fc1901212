"""What `dstereo calibrate` does for each kind of rig: one table, the refusals and the README's feature table.

A cell is True (built, on by the same defaults for every kind), or the one line that says why not and what to do
instead; `check_request` refuses a request with that line, and `markdown_table` is the README's table (a test
keeps the README equal to it). `python -m dstereo.config.capabilities` prints it.
"""

from __future__ import annotations

from dstereo.errors import DstereoError

KINDS = ("one camera", "--left/--right", "--cameras")


class NotApplicable(str):
    """A cell for a feature that has no meaning for the kind (shown "-"): the text is the refusal a request gets."""

SPLINED_RIG = ("stereo rigs and --cameras with splined cameras are not supported: reconstruct's rectification "
               "inverts each lens in closed form and the splined lens has no such inverse; calibrate each camera "
               "alone with --images DIR --model splined, the rig with a parametric model")

# the rows the command checks by name
STEREO_STEPS = "the thesis's stereo steps (`--step stereo_re=..,Tnorm=..`)"
RIGHT_LENS = "a different right lens (`--model-right`)"
SPLINED = "splined lens (full set, no subsets or cross-validation)"

# feature -> one cell per kind in KINDS
CAPABILITIES: dict[str, tuple] = {
    "subsets of views and the thesis's camera steps (`--per-set`, `--step`)": (True, True, True),
    STEREO_STEPS: (
        NotApplicable("stereo steps need a rig; give --left DIR --right DIR (or images/images_left + "
                      "images/images_right), or --cameras DIR"),
        True, True),
    "outlier rejection (corners and views; the rig solved on the corners each camera kept)": (True, True, True),
    "board sag (`--no-board-sag`: flat)": (True, True, True),
    "`--cross-validate N` (views for one camera, frames for a rig)": (True, True, True),
    "`--model auto` (a rig: each camera on its own views, parametric lenses)": (True, True, True),
    "fisheye lens (`--model fisheye`), and mixed lenses in a rig": (True, True, True),
    RIGHT_LENS: (
        NotApplicable("--model-right: only for a stereo rig; give --left DIR --right DIR (or images/images_left + "
                      "images/images_right)"), True,
        "--model-right: only for a stereo rig (--left/--right); --cameras takes one --model for every camera"),
    SPLINED: (True, SPLINED_RIG, SPLINED_RIG),
    "final = the survivors' solve (`--final mean`: the thesis's mean for each camera; a rig's file keeps the "
    "solve, each pair's subset mean beside it)": (True, True, True),
    "mrcal `.cameramodel` (each camera; a rig's in its frame)": (True, True, True),
    "rig consistency test, rig figures": ("-", True, True),
    "a frame the rig cannot explain (the other frames can) leaves the rig": ("-", True, True),
    "stereo files with the calibration covariance (`reconstruct`'s point sigmas)": ("-", True, True),
}


def refusal(feature: str, kind: str) -> str | None:
    """The reason `feature` is refused for `kind` (one of KINDS), or None when it is built."""
    cell = CAPABILITIES[feature][KINDS.index(kind)]
    return None if cell is True or cell == "-" else str(cell)


def refuse(feature: str, kind: str, prefix: str = "") -> None:
    """Raise the table's one line for `feature` and `kind` when it is not built (prefix: how the user asked)."""
    why = refusal(feature, kind)
    if why is not None:
        raise DstereoError(f"{prefix}: {why}" if prefix and not why.startswith(prefix) else why)


def markdown_table() -> str:
    """The README's feature table: Y where built, the reason where not."""
    lines = ["| feature | " + " | ".join(f"`{k}`" if k.startswith("-") else k for k in KINDS) + " |",
             "|---|" + "---|" * len(KINDS)]
    for feature, cells in CAPABILITIES.items():
        shown = ["Y" if c is True else ("-" if c == "-" or isinstance(c, NotApplicable) else f"no: {c}")
                 for c in cells]
        lines.append(f"| {feature} | " + " | ".join(shown) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(markdown_table())
