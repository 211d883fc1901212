"""`dstereo calibrate`'s request: the flags and the configuration files merged by the one rule (`dstereo.config`),
checked, and which rig they name (one camera, a stereo pair, N cameras), all before any work; `run_request`
(calibrate_runs.py) then runs the one job on it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional


@dataclass(frozen=True)
class CalibrateRequest:
    """A checked calibration request. rig: "camera" (--images, K = 1), "stereo" (--left/--right or the thesis's
    images_left/images_right, K = 2) or "cameras" (--cameras DIR, K = N); out is final for one camera (the stereo
    and N-camera runs check theirs once their sources are listed)."""
    rig: str
    cfg: object
    images: Optional[Path]
    left: Optional[Path]
    right: Optional[Path]
    cameras: Optional[Path]
    pair: Optional[tuple]
    project: Optional[Path]
    out: Optional[Path]
    force: bool
    quiet: bool
    use_cache: bool
    projection_range: Optional[float]
    projection_method: str
    cross_validate: int


def calibrate_request(project, config, images, glob, image_format, pattern, square, unit, model, model_right,
                      per_set, max_subsets, seed, step, min_subsets, final, no_outlier_rejection, board_sag,
                      mrcal_convert, out, force, quiet, no_cache, left, right, cameras, pair, projection_range,
                      projection_method, cross_validate) -> CalibrateRequest:
    """The request the flags make, or a DstereoError naming the flag or file and what to do."""
    from dstereo.commands.calibrate_checks import as_given, check_run_options, pair_of, \
        refuse_splined_where_unsupported, results_folder, stereo_layout
    from dstereo.config.calibration import build_config, file_layer, find_project_config, parse_step_flags, validate
    from dstereo.config.calibration_flags import flag_layer
    from dstereo.config.capabilities import RIGHT_LENS, STEREO_STEPS, refuse
    from dstereo.errors import DstereoError
    from dstereo.runtime import figure_pool

    check_run_options(projection_method, cross_validate, projection_range, pair, cameras)
    config_path = config if config is not None else (find_project_config(project) if project is not None else None)
    flags = flag_layer(dict(  # parameter -> flag value (dstereo.config.options.CALIBRATE)
        pattern=pattern, square=square, unit=unit, images=images, image_format=image_format, glob=glob, model=model,
        model_right=model_right, per_set=per_set, max_subsets=max_subsets, seed=seed, min_subsets=min_subsets,
        final=final, outlier_rejection=no_outlier_rejection, board_sag=board_sag, steps=step,
        mrcal_convert=mrcal_convert))
    cfg = validate(build_config(*([file_layer(config_path)] if config_path is not None else []), flags))
    figure_pool.start_rest()  # JAX is imported: the other workers warm up on the core the full-set solve leaves
    is_rig = cameras is not None or left is not None or right is not None
    refuse_splined_where_unsupported(cfg, is_rig, cross_validate)
    common = dict(cfg=cfg, left=left, right=right, cameras=cameras, pair=pair_of(pair), project=project, force=force,
                  quiet=quiet, use_cache=not no_cache, projection_range=projection_range,
                  projection_method=projection_method, cross_validate=cross_validate)
    if cameras is not None:
        if left is not None or right is not None or images is not None:
            raise DstereoError("--cameras: give the cameras' folder alone, without --images/--left/--right")
        if cfg.model_right is not None:
            refuse(RIGHT_LENS, "--cameras", as_given(cfg, "model_right", "--model-right"))
        return CalibrateRequest("cameras", images=None, out=out, **common)
    stereo_images = images if images is not None else (project / cfg.images if project is not None else None)
    if left is not None or right is not None or (stereo_images is not None and stereo_layout(stereo_images)):
        refuse_splined_where_unsupported(cfg, True, cross_validate)  # a stereo layout found in the images folder
        return CalibrateRequest("stereo", images=stereo_images, out=out, **common)
    if cfg.model_right is not None:
        refuse(RIGHT_LENS, "one camera", as_given(cfg, "model_right", "--model-right"))
    if flags.get("stereo_steps"):
        refuse(STEREO_STEPS, "one camera", f"--step {', '.join(s for s in step if parse_step_flags([s])[1])}")
    if cfg.mode != "individual":
        raise DstereoError(f"{cfg.source or 'configuration'}: a stereo configuration needs the stereo images: put them "
                           "in images/images_left and images/images_right, or give --left DIR --right DIR")
    if images is None:
        base = project if project is not None else (config_path.parent if config_path is not None else None)
        if base is None:
            raise DstereoError("no images: give a PROJECT folder (with images/) or --images DIR")
        images = base / cfg.images
    from dstereo.io.pairing import check_one_camera
    from dstereo.jobs.calibrate_camera import list_camera_images

    check_one_camera(list_camera_images(images, cfg), str(images))
    out = results_folder(out, project, force, cfg, inputs=[images, config_path])
    return CalibrateRequest("camera", images=images, out=out, **common)
