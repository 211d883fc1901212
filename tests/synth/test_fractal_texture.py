"""The multi-scale (fractal) speckle of `Speckle.create(..., octaves=n)` that the outdoor renders use."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dstereo.synth.texture import Speckle, albedo


def _line(tex: Speckle, n: int = 4000, step_mm: float = 0.05) -> np.ndarray:
    points = jnp.stack([jnp.arange(n) * step_mm, jnp.zeros(n), jnp.zeros(n)], axis=1)
    return np.asarray(jax.vmap(lambda p: albedo(tex, p))(points))


def test_two_octaves_are_the_speckle_as_before():
    """octaves=2 (the default) draws the same lattices and gives the same values as every earlier render."""
    a, b = Speckle.create(7, 3.0, 1.0), Speckle.create(7, 3.0, 1.0, octaves=2)
    for x, y in ((a.rotations, b.rotations), (a.offsets, b.offsets), (a.seeds, b.seeds)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(_line(a, 200), _line(b, 200))
    assert "octaves" not in a.to_truth() and Speckle.create(7, 3.0, 1.0, octaves=5).to_truth()["octaves"] == 5
    with pytest.raises(ValueError, match="octaves"):
        Speckle.create(7, octaves=0)


def test_more_octaves_add_fine_detail_within_the_same_range():
    """Five octaves: reflectance still within mean +- amplitude, the same overall spread within 25 % (the field's
    std is normalised for the octaves' weights), and more fine detail: the std of neighbouring differences along a
    line 0.05 mm apart (size 3 mm: octave 4 at 0.19 mm). Octave k has weight 0.5^k and scale size / 2^k, so each
    adds the same gradient variance: five octaves against two, sqrt(5 / 2) = 1.58, less the 3 % of the field's
    normalisation (1.53); the tanh compresses a little (measured 1.48); 1.3 asked."""
    two, five = (_line(Speckle.create(11, 3.0, 0.6, octaves=k)) for k in (2, 5))
    tex = Speckle.create(11, 3.0, 0.6, octaves=5)
    assert np.all(np.abs(five - tex.mean) < tex.amplitude)
    assert 0.75 < five.std() / two.std() < 1.25
    fine = np.diff(five).std() / np.diff(two).std()
    print(f"spread ratio {five.std() / two.std():.2f}, fine detail ratio {fine:.2f}")
    assert fine > 1.3
