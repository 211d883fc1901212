"""Moved to `dstereo.stereo.subpixel` (the reconstruction refines when `ReconstructionConfig.refine` is set);
re-exported here for code that imported it from the recession package."""

from dstereo.stereo.subpixel import exact_pair, rectify_exact, refine_disparity, refine_right_disparity

__all__ = ["exact_pair", "rectify_exact", "refine_disparity", "refine_right_disparity"]
