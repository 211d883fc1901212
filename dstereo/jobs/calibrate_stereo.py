"""A stereo rig's calibration (thesis 4.2.2.2) through the K-camera job (`jobs/calibrate_cameras.calibrate_rig`,
K = 2): both cameras individually, then the rig, its frame subsets and the thesis's stereo steps.

Where the images come from (`stereo_sources`):
- flags `--left L --right R`: a folder each, or a file pattern such as `DATA/left*.jpg`; the same images serve
  the individual calibrations and the stereo pairs;
- the thesis's layout under the project's images folder: `images_left`, `images_right` (individual
  calibrations; `calibrate_left`/`calibrate_right` as in the thesis's template comment are accepted too) and,
  optionally, `images_stereo_left`, `images_stereo_right` (the pairs; without them the individual images are
  the pairs).
Pairs are matched by name (`io.pairing`: left05 with right05 is frame 05; `rig_sources.stereo_pair_sources`). The
job is the one every rig runs (outlier rejection, board sag, the rig's consistency test and frame rejection,
subsets and steps, cross-validation, the survivors' solve): the cameras are labelled `left` and `right`, and the
pair's file is `stereo.yml`. Nothing here prints or writes files.
"""

from __future__ import annotations

from pathlib import Path

from dstereo.calib.calibrations import MultiviewJob, StereoSources
from dstereo.config.calibration import Config
from dstereo.errors import DstereoError
from dstereo.io.corners import list_images
from dstereo.io.pairing import LEFT_FOLDERS, RIGHT_FOLDERS
from dstereo.jobs.rig_sources import stereo_pair_sources

STEREO_FOLDERS = ("images_stereo_left", "images_stereo_right")


def _files(source: Path, image_format: str | None, flag: str) -> tuple[Path, ...]:
    """A folder's images of the given format, or the files matching a pattern such as DIR/left*.jpg."""
    source = Path(source)
    if source.is_dir():
        return tuple(list_images(source, image_format))
    if any(ch in source.name for ch in "*?["):
        if not source.parent.is_dir():
            raise DstereoError(f"{flag}: folder {source.parent} does not exist")
        files = tuple(sorted(p for p in source.parent.glob(source.name) if p.is_file()))
        if not files:
            raise DstereoError(f"{flag}: no file matches {source}; check the pattern")
        return files
    raise DstereoError(f"{flag}: {source} is neither a folder nor a file pattern such as DIR/left*.jpg")


def stereo_sources(images: Path | None, config: Config, left: Path | None = None,
                   right: Path | None = None) -> StereoSources:
    """Resolve the flags or the thesis layout (module docstring) into lists of image files."""
    fmt_l = config.image_format_left or config.image_format
    fmt_r = config.image_format_right or config.image_format
    if left is not None or right is not None:
        if left is None or right is None:
            raise DstereoError("stereo: give both `left` and `right` (a folder or a pattern such as DIR/left*.jpg)")
        files_l, files_r = _files(left, fmt_l, "`left`"), _files(right, fmt_r, "`right`")
        return StereoSources(files_l, files_r, files_l, files_r, f"--left {left} --right {right}")
    if images is None or not Path(images).is_dir():
        raise DstereoError(f"stereo: image folder {images} does not exist; give a PROJECT with images/images_left and "
                           "images/images_right, or `left` DIR `right` DIR")
    images = Path(images)
    found = [next((images / n for n in names if (images / n).is_dir()), None)
             for names in (LEFT_FOLDERS, RIGHT_FOLDERS)]
    if None in found:
        raise DstereoError(f"stereo: {images} needs the folders images_left and images_right (thesis 4.2.2.2); "
                           "or give `left` DIR `right` DIR")
    mono_l, mono_r = _files(found[0], fmt_l, str(found[0])), _files(found[1], fmt_r, str(found[1]))
    pair_dirs = [images / n for n in STEREO_FOLDERS]
    present = [d.is_dir() for d in pair_dirs]
    if any(present) and not all(present):
        raise DstereoError(f"stereo: {images} has only one of {', '.join(STEREO_FOLDERS)}; give both (stereo pairs) "
                           "or neither (the individual images are then the pairs)")
    if all(present):
        pairs_l = _files(pair_dirs[0], fmt_l, str(pair_dirs[0]))
        pairs_r = _files(pair_dirs[1], fmt_r, str(pair_dirs[1]))
        return StereoSources(mono_l, mono_r, pairs_l, pairs_r, f"{images} (individual and stereo folders)")
    return StereoSources(mono_l, mono_r, mono_l, mono_r, f"{images} (the same images for both uses)")


def calibrate_stereo_project(sources: StereoSources, config: Config, progress=None, use_cache: bool = True,
                             scratch: Path | None = None, cross_validate: int = 0,
                             projection_range: float | None = None) -> MultiviewJob:
    """Run the job of the module docstring. Raises DstereoError for bad pairs, sizes, counts or steps, or a
    subset run that cannot fit this machine. `scratch`: folder for huge runs' per-subset tables (as mono).
    `cross_validate`: that many random halvings of the frames (`calib/rig_cross_validation.py`)."""
    from dstereo.jobs.calibrate_cameras import calibrate_rig

    cams, warnings = stereo_pair_sources(sources, config)
    where = Path(cams[0].where)
    job = calibrate_rig(cams, config, where, progress, use_cache, scratch, cross_validate, projection_range,
                        pairs=("left", "right"), warnings=warnings, pair_file="stereo.yml")
    job.sources = sources.description
    return job
