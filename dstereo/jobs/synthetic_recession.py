"""A rendered recession sequence with known truth, written as `dstereo recession` reads it (for users and tests).

`write_synthetic_sequence(folder)` renders the cork sample in the reduced Plasmatron rig (`synth.rig`) while
its front face recedes by a known profile (`synth.recession`: uniform + centre-peaked, linear in time) and
writes the sequence (`synth.writers.write_recession_sequence`), the rig's true calibration as `stereo.yml`,
and `truth.json`: times, stagnation-point recession, the profile, the true axis and stagnation point in the
left camera frame.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from dstereo.errors import DstereoError


def true_calibration_files(folder: Path, rig) -> Path:
    """stereo.yml of a synthetic rig's true calibration (what a perfect calibration would write)."""
    from dstereo.io.stereo_files import write_stereo_yml

    r, t = rig.rotation_translation()
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    e = tx @ r
    k1, k2 = np.asarray(rig.left.matrix()), np.asarray(rig.right.matrix())
    f = np.linalg.inv(k2).T @ e @ np.linalg.inv(k1)
    return write_stereo_yml(folder / "stereo.yml", k1, rig.left.coeffs(), k2, rig.right.coeffs(), r, t, e, f / f[2, 2],
                            tuple(rig.left.image_size), unit="mm")  # the synthetic scenes are in mm


def sample_truth(rig, sample, T_world_sample) -> dict:
    """The sample's axis (away from the cameras) and stagnation point (t = 0) in the left camera frame."""
    from dstereo.synth.poses import compose, pose_matrix

    m = pose_matrix(compose(rig.T_left_world, T_world_sample))
    p = m[:3, :3] @ np.asarray(sample.stagnation_point(), float) + m[:3, 3]
    return {"axis": (-m[:3, 2]).tolist(), "stagnation_point_mm": p.tolist()}


def converging_rig(image_size: tuple[int, int], focal_px: tuple[float, float], baseline_mm: float = 100.0,
                   distance_mm: float = 600.0):
    """The reduced Plasmatron rig (`synth.rig.plasmatron_rig`: cameras aimed at (0, 0, distance), its lenses and
    principal points) with different focal lengths left and right (fx; fy 0.05 % more), as in issue 14's case
    (fx 4700 / 4900 px at 640 x 480): rectification then rescales one image, and the zero-disparity plane
    sits near the aim distance, so the far side of a face has negative disparities."""
    from dstereo.models.camera import Camera
    from dstereo.synth import plasmatron_rig
    from dstereo.synth.rig import StereoRig

    base = plasmatron_rig(tuple(image_size), float(focal_px[0]), baseline_mm, distance_mm)
    (w, h), (fl, fr) = image_size, focal_px
    left = Camera.create(fl, fl * 1.0005, (w - 1) / 2 + 2.5, (h - 1) / 2 - 1.5, base.left.coeffs(),
                         image_size=tuple(image_size))
    right = Camera.create(fr, fr * 1.0005, (w - 1) / 2 - 3.0, (h - 1) / 2 + 2.0, base.right.coeffs(),
                          image_size=tuple(image_size))
    return StereoRig(left, right, base.rig, base.T_left_world)


def write_synthetic_sequence(folder, n_frames: int = 11, duration_s: float = 40.0, total_mm: float = 2.0,
                             peak_share: float = 0.6, sigma_mm: float = 8.0, image_size: tuple[int, int] = (640, 480),
                             seed: int = 0, flat: bool = False, options=None, force: bool = False,
                             yaw_deg: float = 0.0, pitch_deg: float = 0.0,
                             focal_px: tuple[float, float] | None = None) -> dict:
    """Render and write a sequence (module docstring); returns the truth. `image_size` scales the reduced rig
    (the focal length with it, so the field of view is kept); `flat` renders a flat front face instead of the
    domed one; `options` are the RenderOptions (default `synth.scenes.OBJECT_OPTIONS`); `yaw_deg`/`pitch_deg` tilt the
    sample's axis off the rig's (`synth.rig.sample_pose`): its side wall comes into view. `focal_px` (left, right):
    the focal lengths of `converging_rig` instead (at this `image_size`, not scaled)."""
    from dstereo.synth import Sample, plasmatron_rig, recession_sequence, sample_pose
    from dstereo.synth.recession import profile_for_total
    from dstereo.synth.scenes import OBJECT_OPTIONS
    from dstereo.synth.writers import write_recession_sequence

    if n_frames < 2:
        raise DstereoError(f"n_frames={n_frames}: a sequence needs at least 2 frames")
    folder = Path(folder)
    if focal_px is None:
        rig = plasmatron_rig(tuple(image_size), 4800.0 * image_size[0] / 640.0)
    else:
        rig = converging_rig(tuple(image_size), focal_px)
    sample = Sample.flat() if flat else Sample()
    profile = profile_for_total(total_mm, duration_s, peak_share, sigma_mm)
    pose = sample_pose(sample.length, yaw_deg=yaw_deg, pitch_deg=pitch_deg)
    renders = recession_sequence(rig, sample, profile, n_frames, duration_s, pose, seed=seed,
                                 options=options or OBJECT_OPTIONS)
    write_recession_sequence(folder, renders, force=force)
    true_calibration_files(folder, rig)
    truth = {"time_s": [r.truth_left["time_s"] for r in renders],
             "recession_stagnation_mm": [r.truth_left["recession_stagnation_mm"] for r in renders],
             "profile": profile.to_truth(), "rate_stagnation_mm_s": profile.uniform_rate + profile.peak_rate,
             "sample": sample.truth(), "image_size": list(image_size), "seed": seed,
             "yaw_deg": yaw_deg, "pitch_deg": pitch_deg,
             "focal_px": [float(np.asarray(rig.left.matrix())[0, 0]), float(np.asarray(rig.right.matrix())[0, 0])],
             **sample_truth(rig, sample, pose)}
    (folder / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


# A tilted sample with its side wall in view, as issue 32 measured the rate's interval on: the tilt, its direction
# and the sensor noise vary with the seed (as the texture does), so that seeds differ in more than the speckle.
TILT_DEG = (10.0, 18.0)  # off the rig axis, mostly as yaw (the side wall beside the face, across the baseline)
PITCH_DEG = 5.0  # at most, either way
SENSOR_NOISE = (10000.0, 1.0)  # full well (electrons at full scale) and read noise (DN): a machine-vision sensor


def tilted_pose(seed: int) -> tuple[float, float]:
    """(yaw, pitch) in degrees for `seed`: yaw of TILT_DEG either way, pitch within PITCH_DEG."""
    rng = np.random.default_rng([32, seed])
    yaw = rng.uniform(*TILT_DEG) * rng.choice([-1.0, 1.0])
    return float(yaw), float(rng.uniform(-PITCH_DEG, PITCH_DEG))


def write_tilted_sequence(folder, seed: int, n_frames: int = 11, image_size: tuple[int, int] = (640, 480),
                          noise: tuple[float, float] = SENSOR_NOISE, force: bool = False, **kwargs) -> dict:
    """`write_synthetic_sequence` of the domed sample tilted by `tilted_pose(seed)` (its side wall in view), with
    shot noise and read noise on every image (`noise`: full well in electrons at full scale, read noise in DN;
    the objects' default blur and supersampling); `kwargs` go on to it."""
    from dstereo.synth.scenes import OBJECT_OPTIONS

    yaw, pitch = tilted_pose(seed)
    options = replace(OBJECT_OPTIONS, full_well=float(noise[0]), read_noise_dn=float(noise[1]))
    return write_synthetic_sequence(folder, n_frames=n_frames, image_size=image_size, seed=seed, yaw_deg=yaw,
                                    pitch_deg=pitch, options=options, force=force, **kwargs)
