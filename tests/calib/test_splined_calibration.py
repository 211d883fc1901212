"""The splined lens through the one calibration core: its frame Jacobian, a lens no parametric model has (held-out
error), and projection uncertainty that grows where no corner is. Small synthetic cases, one shape throughout (the
compiled solver is shared)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.calib import model_choice
from dstereo.calib.mono import calibrate_full
from dstereo.calib.problem import Problem, frame_linearize, frame_residual, shared_data
from dstereo.models.distortion import PRESETS, parse_model
from dstereo.synth import odd_lens
from dstereo.uncertainty.projection import mean_board_distance, solution_map

GRID = parse_model("splined:8x6")
LENS = odd_lens.OddLens()
OBJ = odd_lens.board_points(7, 5, 30.0)
N_TRAIN, N_TEST = 12, 6


def test_splined_frame_jacobian_matches_autodiff():
    free = parse_model("splined:5x4")
    problem = Problem.of([free])
    rng = np.random.default_rng(0)
    g = jnp.asarray(np.concatenate([[300.0, 310.0, 320.0, 240.0], rng.normal(0, 2.0, len(free))]))
    pose = jnp.array([0.1, -0.2, 0.05, -100.0, -60.0, 400.0])
    obs = jnp.asarray(rng.uniform(0, 600, (1, len(OBJ), 2)))
    shared = shared_data(OBJ, np.zeros(4), np.zeros(8))
    r, jt = jax.jit(frame_linearize(problem))(g, pose, obs, shared)
    res = frame_residual(problem)
    r_ad = jax.jit(res)(g, pose, obs, shared)
    jg, jp = jax.jit(jax.jacfwd(res, argnums=(0, 1)))(g, pose, obs, shared)
    np.testing.assert_allclose(np.asarray(r), np.asarray(r_ad), atol=1e-10)  # the same sums, reordered
    # the hand chain rule and autodiff differ by rounding of terms of ~1e3 px per unit: 1e-8 relative
    np.testing.assert_allclose(np.asarray(jt), np.asarray(jnp.concatenate([jg, jp], axis=1).T), atol=1e-8 * 1e3)


@pytest.fixture(scope="module")
def odd_views():
    """Train and test views of the odd lens over the whole image, and the test views' true poses' stand-in: the
    test views' poses come from a solve that saw them (as `model_choice` refits held-out views from the full set)."""
    obs = odd_lens.views(LENS, OBJ, N_TRAIN + N_TEST, seed=4, noise_px=0.1)
    start = calibrate_full(OBJ, obs, LENS.image_size, free=PRESETS["fisheye"]).poses[N_TRAIN:]
    return obs[:N_TRAIN], obs[N_TRAIN:], start


def _heldout_rms(free, train, test, start) -> float:
    """Calibrate on `train`; refit each test view's pose for that fixed camera (from `start`, the pose a solve on
    all views found), and return the RMS over the test corners: the error a user meets on views the calibration
    never saw."""
    sol = calibrate_full(OBJ, train, LENS.image_size, free=free)
    n = len(test)
    sse = np.asarray(model_choice._pose_refit(free)(start, np.repeat(sol.values[None, :4], n, 0),
                                                   np.repeat(sol.camera().coeffs()[None], n, 0), test, OBJ))
    return float(np.sqrt(np.mean(sse) / len(OBJ)))


@pytest.mark.slow
def test_splined_predicts_held_out_views_of_an_odd_lens_better_than_every_parametric_model(odd_views):
    errors = {name: _heldout_rms(PRESETS[name], *odd_views) for name in model_choice.PARAMETRIC}
    splined = _heldout_rms(GRID, *odd_views)
    print("held-out RMS px:", errors, "splined", splined)
    # Noise 0.1 px per coordinate: a model that follows the lens leaves ~0.14 px per corner; the wave (2 px) is
    # what the parametric models cannot follow.
    assert all(np.isfinite(v) for v in errors.values())
    assert splined < min(errors.values()), (splined, errors)
    assert splined < 0.25


def test_projection_uncertainty_grows_where_no_corner_is():
    """Corners only in the left 55 % of the image: the right part is decided by the prior, and its projection
    uncertainty must be large against the covered part's (not small: nothing there was measured)."""
    obs = odd_lens.views(LENS, OBJ, N_TRAIN, seed=5, noise_px=0.1, region=(0.0, 0.0, 0.55, 1.0))
    sol = calibrate_full(OBJ, obs, LENS.image_size, free=GRID)
    assert sol.converged
    pmap = solution_map(sol, LENS.image_size, mean_board_distance(sol.poses, OBJ), grid=(12, 6))
    std = pmap.std
    u = pmap.u
    covered = std[:, u < 0.45 * LENS.image_size[0]]
    bare = std[:, u > 0.75 * LENS.image_size[0]]
    assert np.isfinite(covered).all()
    # where corners are the map is about the noise's share of a pixel; where none are it must be tens of times that
    assert np.nanmedian(bare) > 20 * np.median(covered), (np.median(covered), np.nanmedian(bare))


def test_cli_refuses_a_splined_rig_and_subsets_in_one_line(tmp_path):
    from conftest import run_cli

    (tmp_path / "l").mkdir()
    (tmp_path / "r").mkdir()
    code, _, err = run_cli("calibrate", "--left", tmp_path / "l", "--right", tmp_path / "r", "--pattern", "9x6",
                           "--model", "splined", "--out", tmp_path / "out")
    assert code == 1 and "stereo rigs and --cameras with splined cameras are not supported" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    code, _, err = run_cli("calibrate", "--images", tmp_path / "l", "--pattern", "9x6", "--model", "splined:6x5",
                           "--per-set", "5", "--out", tmp_path / "out")
    assert code == 1 and "--cross-validate are not available for the splined lens" in err
    assert not (tmp_path / "out").exists()


def test_auto_gate_opens_for_the_odd_lens(odd_views):
    """`--model auto` solves the splined lens when the best parametric model leaves a residual pattern: the odd
    lens's 2 px wave leaves one under every parametric model."""
    from dstereo.calib.model_choice import Candidate, _spline_not_needed

    train = odd_views[0]
    sol = calibrate_full(OBJ, train, LENS.image_size, free=PRESETS["fisheye"])
    row = Candidate("fisheye", PRESETS["fisheye"], 8, sol.rms, 0.8, np.zeros(len(train)), True, True, 1.0, ("", 0.0),
                    solution=sol)
    assert _spline_not_needed([row], train) is None
