"""`read_rectification`: a results folder's matrices.npz read back as the `Rectification` it was written from,
its projection included (pinhole and spherical), a folder written before projections and sizes were recorded taken
as pinhole at its disparity map's size, and a file that is not a reconstruction's refused in one line."""

import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.io.reconstruction_files import read_rectification
from dstereo.models.stereo_calibration import StereoCalibration
from dstereo.stereo.rectify_fisheye import rectify_any
from dstereo.synth import fisheye_rig, wide_fisheye_rig


def _calib(rig) -> StereoCalibration:
    R, T = rig.rotation_translation()
    return StereoCalibration(rig.left.matrix(), rig.left.coeffs(), rig.right.matrix(), rig.right.coeffs(), R, T,
                             rig.left.image_size, models=(rig.left.lens, rig.right.lens))


def _written(tmp_path, rect, keep=None):
    """matrices.npz as `dstereo.stereo.reconstruct` fills it and `write_pair` writes it (np.savez of the dict)."""
    matrices = {k: np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2")}
    matrices |= {"projection": np.array(rect.projection), "size": np.array(rect.size)}
    matrices = {k: v for k, v in matrices.items() if keep is None or k in keep}
    np.savez(tmp_path / "matrices.npz", **matrices)
    return tmp_path


@pytest.mark.parametrize("rig, projection", [(wide_fisheye_rig, "spherical"), (fisheye_rig, "pinhole")])
def test_a_rectification_round_trips_with_its_projection(tmp_path, rig, projection):
    rect = rectify_any(_calib(rig()))
    assert rect.projection == projection
    back = read_rectification(_written(tmp_path, rect))
    assert back.projection == projection and back.size == rect.size and back.vertical == rect.vertical
    for k in ("R1", "R2", "P1", "P2", "Q", "roi1", "roi2"):
        assert np.array_equal(np.asarray(getattr(back, k)), np.asarray(getattr(rect, k))), k
    assert read_rectification(tmp_path / "matrices.npz").projection == projection  # the file itself, too


def test_an_older_file_is_pinhole_and_a_foreign_one_is_refused(tmp_path):
    rect = rectify_any(_calib(fisheye_rig()))
    older = _written(tmp_path, rect, keep=("R1", "R2", "P1", "P2", "Q", "roi1", "roi2"))  # neither projection nor size
    np.save(tmp_path / "disparity.npy", np.zeros(rect.size[::-1], np.float32))
    back = read_rectification(older)
    assert back.projection == "pinhole" and back.size == rect.size  # the size of the disparity map beside it
    np.savez(tmp_path / "other.npz", H1=np.eye(3))
    with pytest.raises(DstereoError, match="other.npz: no R1, R2, P1, P2, Q, roi1, roi2: not a calibrated") as err:
        read_rectification(tmp_path / "other.npz")
    assert "\n" not in str(err.value)
    np.savez(tmp_path / "bad.npz", **{k: np.asarray(getattr(rect, k)) for k in ("R1", "R2", "P1", "P2", "Q", "roi1",
                                                                               "roi2")},
             size=np.array(rect.size), projection=np.array("cylinder"))
    with pytest.raises(DstereoError, match="projection 'cylinder' is not one of"):
        read_rectification(tmp_path / "bad.npz")
