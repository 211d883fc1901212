"""`dstereo recession`'s job: every frame's images read and matched with the calibration (`FrameReconstructor`),
then measured over time (`dstereo.recession.analysis.measure_recession`)."""

from __future__ import annotations

from dstereo.errors import DstereoError
from dstereo.recession.analysis import RecessionConfig, RecessionResult, measure_recession
from dstereo.recession.frame import Frame


def run_recession(frames: list[Frame], calib, config: RecessionConfig = RecessionConfig(), recon_config=None,
                  progress=None, reconstruct=None, runner=None, store=None) -> RecessionResult:
    """Reconstruct every frame with `calib` (a StereoCalibration) and `recon_config` and measure the recession.
    `reconstruct(frame)` replaces the image reading and matching; the other arguments are `measure_recession`'s."""
    from dstereo.config.reconstruction_config import ReconstructionConfig

    reconstruct = reconstruct or _reconstructor(calib, recon_config or ReconstructionConfig(), config.refine_subpixel)
    return measure_recession(frames, reconstruct, config, progress=progress, runner=runner, store=store)


MAPS_KEPT = 2  # rectifying maps kept per process (one calibration and image size per sequence; 10 MB at 640x480)
_MAPS: dict = {}  # key of (calibration, configuration, size) -> RectifyingMaps, oldest first


def _reconstructor(calib, recon_config, refine: bool):
    return FrameReconstructor(calib, recon_config, refine)


class FrameReconstructor:
    """frame -> (points, per-point random sigma vectors, noise check): the images read and matched with
    `calib`. An object (not a closure) so that it travels to Dask workers. `log`: frame key -> the search range
    and warnings of every frame that matched here. After the first frame that matched, `config` holds that
    frame's search range, and every later frame is matched over it (the same matcher for the whole sequence,
    and no sparse matching per frame); it is still widened where a frame runs off it."""

    def __init__(self, calib, recon_config, refine: bool):
        from dataclasses import replace

        # The points and their random (disparity-noise) sigmas: the calibration's share is common to all frames
        # and cancels in a recession, so its propagation is skipped. No fill (`dstereo.stereo.fill`): the grids
        # average every point of a cell alike and would take filled points as measured ones.
        self.calib, self.config, self.log = calib, replace(recon_config, refine=refine, uncertainty=False,
                                                           fill=False), {}

    def _maps(self, size: tuple[int, int]):
        """The rectifying maps of this calibration and configuration at `size`, made once per process (a worker
        keeps them for every frame it runs: they travel neither with the tasks nor from the client)."""
        import hashlib
        import pickle
        from dataclasses import replace

        from dstereo.stereo.reconstruct import rectifying_maps

        # the search range is set after the first frame and does not change the maps; every other setting may
        key = hashlib.sha256(pickle.dumps((self.calib, replace(self.config, search_range=None), size))).hexdigest()
        if key not in _MAPS:
            maps = rectifying_maps(self.calib, size, self.config)
            while len(_MAPS) >= MAPS_KEPT:
                _MAPS.pop(next(iter(_MAPS)))
            _MAPS[key] = maps
        return _MAPS[key]

    def __call__(self, frame: Frame):
        from dataclasses import replace

        from dstereo.stereo.disparity_noise import point_sigma_vectors
        from dstereo.stereo.reconstruct import check_pair, disparity_sigma_hook, reconstruct_calibrated
        from dstereo.io.images import read_image

        left, right = read_image(frame.left), read_image(frame.right)
        try:
            check_pair(left, right, self.calib)
            r = reconstruct_calibrated(self.calib, left, right, self.config, name=str(frame.left),
                                       maps=self._maps((left.shape[1], left.shape[0])))
            # the originals' own noise is only reported by `dstereo reconstruct`; a recession does not use it
            sigma_d, _ = disparity_sigma_hook(r, self.config, originals=(left, right), report_image_noise=False)
            vectors = point_sigma_vectors(r.points, r.disparity, r.matrices["Q"], sigma_d, r.matrices)
        except DstereoError:
            raise
        except Exception as exc:  # noqa: BLE001 - an OpenCV failure on one frame skips that frame only
            raise DstereoError(f"{frame.left}: reconstruction failed ({type(exc).__name__}: {exc})") from exc
        search = r.summary["search_range"]
        self.log[frame.key] = {"search_range": search, "warnings": r.warnings}
        if not search["user"] and self.config.search_range is None:
            self.config = replace(self.config, search_range=(search["min_disparity"], search["num_disparities"]))
        return r.points, vectors, r.summary["disparity_noise"]["plane_check"]
