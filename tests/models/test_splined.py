"""The splined lens (models/splined.py): its Jacobian against central differences, its unprojection's round trip,
the B-spline's exact reproduction of linear surfaces (which the curvature prior must leave free), its names."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.errors import DstereoError
from dstereo.models import splined
from dstereo.models.distortion import coeff_slots, lens_model, parse_model

NX, NY = 7, 6
K = jnp.array([400.0, 410.0, 320.0, 240.0])
# compiled once (eager JAX runs op by op: several times slower on these small arrays)
project = jax.jit(splined.project, static_argnums=(3, 4))


def _case(seed=0, n=24):
    rng = np.random.default_rng(seed)
    coeffs = jnp.asarray(rng.normal(0.0, 3.0, 2 * NX * NY))
    # points up to ~50 degrees off axis: their argument a stays inside the grid's square
    p = np.stack([rng.uniform(-0.8, 0.8, n), rng.uniform(-0.6, 0.6, n), rng.uniform(0.8, 2.0, n)])
    return coeffs, jnp.asarray(p)


def test_hand_jacobian_matches_central_differences():
    coeffs, p = _case()
    q, dk, dc, dp = jax.jit(splined.project_jacobian, static_argnums=(3, 4))(K, coeffs, p, NX, NY)
    # the same formula in two programs (jitted with its Jacobian, eager alone): O(1000) px from a few dozen roundings;
    # FMA contraction or another ISA moves each by ~1e-16 relative, so 1e-12 holds on any processor
    np.testing.assert_allclose(np.asarray(q), np.asarray(project(K, coeffs, p, NX, NY)), rtol=1e-12)

    def central(fn, x, h):
        """(out..., m) central differences of fn along each of x's m coordinates, in one compiled batch."""
        diff = jax.jit(jax.vmap(lambda e: (fn(x + e) - fn(x - e)) / (2 * h)))(h * jnp.eye(len(x)))
        return jnp.moveaxis(diff, 0, -1)

    # Central differences err by h^2 |q'''| / 6 plus rounding eps |q| / h: with |q| ~ 1e3 px, h = 1e-4 (p, in
    # units of ~1) leaves ~1e-8 truncation and ~1e-9 rounding; the comparisons allow 1e-5 of the scale.
    num_k = jnp.moveaxis(central(lambda k: splined.project(k, coeffs, p, NX, NY), K, 1e-3), -1, 1)
    num_c = jnp.moveaxis(central(lambda c: splined.project(K, c, p, NX, NY), coeffs, 1e-3), -1, 1)  # linear in c
    # d q_j / d p_j for each point j: perturb all points' coordinate i at once (points are independent)
    num_p = jnp.moveaxis(jnp.stack([
        (project(K, coeffs, p.at[i].add(1e-4), NX, NY) - project(K, coeffs, p.at[i].add(-1e-4), NX, NY))
        / 2e-4 for i in range(3)]), 0, 1)
    np.testing.assert_allclose(np.asarray(dk), np.asarray(num_k), atol=1e-5 * 400)
    np.testing.assert_allclose(np.asarray(dc), np.asarray(num_c), atol=1e-8)
    np.testing.assert_allclose(np.asarray(dp), np.asarray(num_p), atol=1e-5 * 400)


def test_unprojection_round_trip_and_refusal_outside_the_grid():
    coeffs, p = _case(1)
    q = project(K, coeffs, p, NX, NY)
    rays, ok = jax.jit(jax.vmap(lambda qq: splined.unproject(K, coeffs, qq, NX, NY)))(q.T)
    assert bool(jnp.all(ok))
    truth = p / jnp.linalg.norm(p, axis=0)
    # Newton stops at a round trip within 1e-6 px (ROUND_TRIP_PX) of a ~400 px focal: rays within ~1e-8
    np.testing.assert_allclose(np.asarray(rays), np.asarray(truth.T), atol=1e-8)
    # far outside the grid's square (a = 3 half-images) no ray is claimed
    ray, ok = jax.jit(splined.unproject, static_argnums=(3, 4))(K, coeffs, jnp.array([320.0 * 4, 240.0]), NX, NY)
    assert not bool(ok) and bool(jnp.all(jnp.isnan(ray)))


def test_linear_knots_give_a_linear_surface_which_the_curvature_prior_leaves_free():
    """Uniform cubic B-splines reproduce linear functions: knots P[r, k] = alpha k + beta r + gamma give
    S = alpha (t_x + 1) + beta (t_y + 1) + gamma at grid position t (sum_m m B_m(s) = s + 1)."""
    alpha, beta, gamma = 2.0, -3.0, 5.0
    rr, kk = np.mgrid[0:NY, 0:NX]
    grid = alpha * kk + beta * rr + gamma
    coeffs = jnp.asarray(np.concatenate([grid.ravel(), -grid.ravel()]))
    a = jnp.asarray(np.random.default_rng(2).uniform(-1.2, 1.2, (2, 30)))
    s, _, _ = jax.jit(splined._surfaces, static_argnums=(2, 3))(coeffs, a, NX, NY)
    t = (np.asarray(a) + splined.DOMAIN) / (2 * splined.DOMAIN) * (np.array([NX, NY]) - 3)[:, None]
    expected = alpha * (t[0] + 1) + beta * (t[1] + 1) + gamma
    # a 16-term sum of O(10) knots times basis weights against the closed form: rounding ~1e-14, any processor
    np.testing.assert_allclose(np.asarray(s[0]), expected, atol=1e-12)
    np.testing.assert_allclose(np.asarray(s[1]), -expected, atol=1e-12)
    rows = splined.prior_rows(NX, NY)
    curvature = rows[:-2 * NX * NY]
    # second differences of O(10) knots on a plane: a few exact-ish float64 sums, zero up to ~1e-14 anywhere
    np.testing.assert_allclose(curvature @ np.asarray(coeffs), 0.0, atol=1e-12)
    bumpy = np.asarray(coeffs).copy()
    bumpy[NX * 2 + 3] += 1.0
    assert np.abs(curvature @ bumpy).max() >= splined.CURVATURE_WEIGHT


def test_names_grid_and_spec():
    free = parse_model("splined:6x5")
    assert free == splined.knot_names(6, 5) and len(free) == 60
    assert lens_model(free) == "splined" and coeff_slots(free) == free
    assert splined.grid_of(free) == (6, 5)
    assert parse_model(list(free)) == free
    assert lens_model(parse_model("splined")) == "splined"
    with pytest.raises(DstereoError, match="splined:NXxNY"):
        parse_model("splined:3x9")
    with pytest.raises(DstereoError, match="every knot"):
        parse_model(list(free[:-1]))


def test_valid_spans_cover_where_corners_are():
    corners = np.random.default_rng(3).uniform([0, 0], [320, 480], (400, 2))  # the left half of a 640 x 480 image
    valid = splined.valid_spans(np.asarray(K), corners, NX, NY)
    assert valid.shape == (NY - 3, NX - 3)
    assert splined.in_valid_region(np.asarray(K), np.array([[100.0, 240.0]]), valid)[0]
    assert not splined.in_valid_region(np.asarray(K), np.array([[600.0, 240.0]]), valid)[0]
