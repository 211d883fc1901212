"""Surface recession over time from a sequence of stereo pairs (`dstereo recession`).

`sequence` finds and checks the frames on disk, `surface` the sample axis, grid and per-cell heights, `fits`
the stagnation-point value and rates with confidence intervals, `analysis` runs it all, `results` writes the
results folder, `synthetic` writes a rendered sequence with known recession.
"""

from dstereo.recession.analysis import FrameResult, RecessionConfig, RecessionResult, run_recession
from dstereo.recession.fits import LineFit, PointValue, at_stagnation, line_fit, rate_map
from dstereo.recession.sequence import Frame, check_sizes, discover, time_from_name
from dstereo.recession.surface import Grid, SampleFrame, estimate_axis, frame_from_axis

__all__ = [
    "Frame", "FrameResult", "Grid", "LineFit", "PointValue", "RecessionConfig", "RecessionResult", "SampleFrame",
    "at_stagnation", "check_sizes", "discover", "estimate_axis", "frame_from_axis", "line_fit", "rate_map",
    "run_recession", "time_from_name",
]
