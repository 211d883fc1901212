"""`dstereo reconstruct` for a list of pairs: read the calibration and the images, reconstruct each pair
(`dstereo.stereo.reconstruct`), write the results folder atomically (one sub-folder per pair if several)."""

from __future__ import annotations

import json
from pathlib import Path

from dstereo.config.reconstruction_config import ReconstructionConfig
from dstereo.errors import DstereoError
from dstereo.io.images import read_image
from dstereo.io.results import check_output
from dstereo.stereo.pair_result import PairResult, check_pair, check_rig
from dstereo.stereo.reconstruct import reconstruct_calibrated, reconstruct_uncalibrated


def run_reconstruction(
    pairs: list[tuple[str | Path, str | Path]],
    out: str | Path,
    calib_path: str | Path | None = None,
    config: ReconstructionConfig = ReconstructionConfig(),
    force: bool = False,
) -> list[PairResult]:
    """Reconstruct every (left, right) pair and write the results folder (one sub-folder per pair if several)."""
    from dstereo.io.calib_files import read_stereo_calibration
    from dstereo.io.json_files import json_default
    from dstereo.io.reconstruction_files import write_atomically, write_pair
    from dstereo.io.reconstruction_report import write_index

    check_output(out, force)
    if not pairs:
        raise DstereoError("no image pair given; pass --left and --right")
    calib = read_stereo_calibration(calib_path) if calib_path is not None else None
    if calib is not None:
        check_rig(calib)
    results = []
    for left_path, right_path in pairs:
        left, right = read_image(left_path), read_image(right_path)
        check_pair(left, right, calib, names=(str(left_path), str(right_path)))
        name = Path(left_path).stem
        if calib is None:
            results.append(reconstruct_uncalibrated(left, right, config, name))
        else:
            results.append(reconstruct_calibrated(calib, left, right, config, name))
    names = [r.name for r in results]
    if len(set(names)) != len(names):
        for i, r in enumerate(results):
            r.name = f"{i:02d}_{r.name}"

    def fill(tmp: Path):
        if len(results) == 1:
            write_pair(tmp, results[0], config)
            return
        for r in results:
            (tmp / r.name).mkdir()
            write_pair(tmp / r.name, r, config)
        index = {"pairs": [r.summary for r in results], "config": config.as_dict()}
        (tmp / "summary.json").write_text(json.dumps(index, indent=2, default=json_default))
        write_index(tmp, [r.summary for r in results], [r.name for r in results])

    write_atomically(out, force, fill)
    return results

