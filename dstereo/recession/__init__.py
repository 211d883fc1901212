"""Surface recession over time from a sequence of stereo pairs (`dstereo recession`).

`frame` is one pair of the sequence, `surface` the sample axis, grid and per-cell heights, `fits` the
stagnation-point value and rates with confidence intervals, `analysis` measures them over the frames. The files:
`dstereo.io.sequence_files` finds and checks the frames on disk, `dstereo.jobs.recession` reads, reconstructs and
measures them, `dstereo.jobs.synthetic_recession` writes a rendered sequence with known recession.
"""

from dstereo.recession.analysis import FrameResult, RecessionConfig, RecessionResult, measure_recession
from dstereo.recession.fits import LineFit, PointValue, at_stagnation, line_fit, rate_map
from dstereo.recession.frame import Frame
from dstereo.recession.surface import Grid, SampleFrame, estimate_axis, frame_from_axis

__all__ = [
    "Frame", "FrameResult", "Grid", "LineFit", "PointValue", "RecessionConfig", "RecessionResult", "SampleFrame",
    "at_stagnation", "estimate_axis", "frame_from_axis", "line_fit", "measure_recession", "rate_map",
]
