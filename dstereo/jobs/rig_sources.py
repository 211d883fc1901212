"""Where a rig's images come from, for every kind of rig: per camera, the images it is calibrated on alone and its
image of each rig frame (the frames are what the rig is solved on).

- `--cameras DIR` (`folder_sources`): one subfolder per camera; each camera is calibrated on its folder's images, and
  an image is also the frame of its stem (cam0/0001.png and cam1/0001.png are one frame).
- `--left/--right` and the thesis's stereo layout (`stereo_pair_sources`, K = 2): each camera is calibrated on its
  individual images (`StereoSources.mono_*`), and the frames are the stereo pairs (`stereo_*`), matched by name
  (`io.pairing`: left05 with right05 is frame 05). The pairs may be the individual images themselves, or other files.

A frame image that is not among its camera's own images is detected on its own (`rig_frames`); one that is gives the
rig the corners its camera's calibration kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dstereo.errors import DstereoError


@dataclass(frozen=True)
class CameraSource:
    """One camera of a rig (module docstring). `frames`: (frame name, this camera's image of it), by name."""

    label: str
    images: tuple[Path, ...]
    frames: tuple[tuple[str, Path], ...]
    where: str  # where the images are, for messages
    config: object | None = None  # the camera's own configuration (lens model, image format); None: the rig's


def folder_sources(folders: list[Path], list_images) -> list[CameraSource]:
    """`--cameras DIR`'s subfolders as sources: `list_images(folder)` gives a camera's images, each the frame of its
    stem."""
    out = []
    for folder in folders:
        files = tuple(list_images(folder))
        out.append(CameraSource(folder.name, files, tuple((p.stem, p) for p in files), str(folder)))
    return out


def stereo_pair_sources(sources, config) -> tuple[list[CameraSource], list[str]]:
    """([left, right] sources, warnings) of a stereo rig's `calib.calibrations.StereoSources`: the pairs matched by
    name, an image without a partner left out with a warning, too few pairs or one file as both partners refused
    before any detection. The right camera's own lens model (`model_right`) goes in its source."""
    from dstereo.config.calibration import validate
    from dstereo.io.pairing import check_enough_pairs, pair_by_name, pair_key

    left, right = list(sources.stereo_left), list(sources.stereo_right)
    named = pair_by_name(left, right)
    check_enough_pairs(named, str(left[0].parent) if left else "left", str(right[0].parent) if right else "right")
    same = [a for a, b in named.pairs if a.resolve() == b.resolve()]
    if same:
        raise DstereoError(f"stereo images: {same[0]} is given as both the left and the right image"
                           + (f" ({len(same) - 1} more)" if len(same) > 1 else "")
                           + "; give each camera's own images (`left` and `right` point at different files)")
    configs = []
    for side, fmt in (("left", config.image_format_left), ("right", config.image_format_right)):
        own = config.model_right if side == "right" else None  # the right camera's own lens: not chosen
        cfg = config.with_overrides(image_format=fmt, model=own, model_auto=False if own is not None else None)
        configs.append(validate(cfg) if cfg.model != config.model else cfg)
    out = [CameraSource(side, tuple(mono), tuple((pair_key(p[i]), p[i]) for p in named.pairs),
                        str(mono[0].parent) if mono else side, cfg)
           for i, (side, mono, cfg) in enumerate((("left", sources.mono_left, configs[0]),
                                                   ("right", sources.mono_right, configs[1])))]
    return out, [named.warning()] if named.warning() else []
