"""The rig solve leaves out a pair whose two images both cameras rejected whole (outlier rejection): kept, it has
no inlier corner and the solve would fit all its bad corners to place it."""

from types import SimpleNamespace

import pytest

from dstereo.jobs.calibrate_stereo import _drop_pairs_rejected_by_both
from dstereo.errors import DstereoError
from dstereo.io.stereo_files import StereoDetection


def _cams(left_gone, right_gone):
    cam = lambda gone: SimpleNamespace(outliers=SimpleNamespace(views=[(v, 1.0) for v in gone]))  # noqa: E731
    return {"left": cam(left_gone), "right": cam(right_gone)}


def _det(n):
    return StereoDetection(None, None, [(f"L{i}", f"R{i}") for i in range(n)])


def test_pair_rejected_by_both_cameras_is_dropped_with_a_warning():
    det, warnings = _det(5), []
    _drop_pairs_rejected_by_both(det, _cams({"L1", "L3"}, {"R1", "R4"}), warnings)
    assert det.pairs == [("L0", "R0"), ("L2", "R2"), ("L3", "R3"), ("L4", "R4")]  # only pair 1 lost both views
    assert [(d.left, d.right) for d in det.dropped] == [("L1", "R1")] and "L1 / R1 dropped" in warnings[0]


def test_too_few_pairs_left_is_refused():
    with pytest.raises(DstereoError, match="only 2 pairs left"):
        _drop_pairs_rejected_by_both(_det(4), _cams({"L0", "L1"}, {"R0", "R1"}), [])
