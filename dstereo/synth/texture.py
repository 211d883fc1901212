"""Random speckle texture fixed to a surface, and Lambertian shading.

The speckle is seeded value noise: random values on the nodes of a cubic lattice (an integer hash of the node
and the seed, so the pattern is unbounded and never repeats), blended with quintic weights so the field is
smooth, summed over two octaves on randomly rotated lattices, and pushed through a tanh to give dark and
bright blobs about `size_mm` across. It is a pure function of the texture point, so every camera sees the same
pattern and a render is reproducible from the seed. (A sum of random plane waves looks alike but costs a
cosine per wave per sample, ~15x slower on a CPU.)
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.spatial.transform import Rotation

OCTAVE_WEIGHTS = (1.0, 0.5)  # the default two octaves; octave k of a multi-scale texture weighs 0.5^k
FIELD_STD = 0.45  # standard deviation of the two-octave field, measured; makes `contrast` a gain on a unit field


class Speckle(eqx.Module):
    """Two octaves of value noise: lattice rotations (2, 3, 3), offsets (2, 3), hash seeds (2,), cell size."""

    rotations: Float[Array, "2 3 3"]
    offsets: Float[Array, "2 3"]
    seeds: Array
    size_mm: float = 0.6
    contrast: float = 2.0
    mean: float = 0.5
    amplitude: float = 0.42

    @classmethod
    def create(cls, seed: int, size_mm: float = 0.6, contrast: float = 2.0, octaves: int = 2) -> "Speckle":
        """Speckle whose blobs are about `size_mm` across; deterministic in `seed`. `octaves` > 2: a multi-scale
        (fractal) texture, octave k at size_mm / 2^k with weight 0.5^k (natural ground, foliage, rock)."""
        if octaves < 1:
            raise ValueError(f"octaves {octaves}: at least 1")
        rng = np.random.default_rng(seed)
        rotations = Rotation.random(octaves, random_state=rng).as_matrix()
        offsets = rng.uniform(0.0, 1000.0, (octaves, 3))
        seeds = rng.integers(0, 2**32, octaves, dtype=np.uint64).astype(np.uint32)
        return cls(jnp.asarray(rotations), jnp.asarray(offsets), jnp.asarray(seeds), size_mm, contrast)

    def to_truth(self) -> dict:
        out = {"type": "speckle (value noise)", "size_mm": float(self.size_mm), "contrast": float(self.contrast),
               "mean": float(self.mean), "amplitude": float(self.amplitude)}
        return out if self.seeds.shape[0] == 2 else out | {"octaves": int(self.seeds.shape[0])}


def _lattice_value(i: Array, j: Array, k: Array, seed: Array) -> Float[Array, ""]:
    """Hash of a lattice node to a value in [-1, 1] (32-bit multiply-xorshift mixing)."""
    u32 = lambda v: v.astype(jnp.uint32)  # noqa: E731
    h = (u32(i) * jnp.uint32(0x8DA6B343)) ^ (u32(j) * jnp.uint32(0xD8163841)) ^ (u32(k) * jnp.uint32(0xCB1AB31F)) ^ seed
    h = (h ^ (h >> 16)) * jnp.uint32(0x7FEB352D)
    h = (h ^ (h >> 15)) * jnp.uint32(0x846CA68B)
    h = h ^ (h >> 16)
    return h.astype(jnp.float64) * (2.0 / 4294967295.0) - 1.0


def value_noise(p: Float[Array, "3"], seed: Array) -> Float[Array, ""]:
    """Smooth noise at `p` (lattice units), one point: quintic blend of the 8 surrounding node values."""
    cell = jnp.floor(p)
    f = p - cell
    s = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)
    c = cell.astype(jnp.int64)
    total = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (s[0] if dx else 1 - s[0]) * (s[1] if dy else 1 - s[1]) * (s[2] if dz else 1 - s[2])
                total = total + w * _lattice_value(c[0] + dx, c[1] + dy, c[2] + dz, seed)
    return total


def albedo(tex: Speckle, p: Float[Array, "3"]) -> Float[Array, ""]:
    """Reflectance in (mean - amplitude, mean + amplitude) at texture point `p` (mm), one point."""
    octaves = tex.seeds.shape[0]
    weights = OCTAVE_WEIGHTS if octaves == 2 else tuple(0.5**k for k in range(octaves))
    field = 0.0
    for octave, weight in enumerate(weights):
        q = tex.rotations[octave] @ p / (tex.size_mm / 2**octave) + tex.offsets[octave]
        field = field + weight * value_noise(q, tex.seeds[octave])
    # the octaves are independent, each with the same std: the field's std grows as sqrt(sum of weights^2)
    std = FIELD_STD if octaves == 2 else FIELD_STD * float(np.sqrt(sum(w * w for w in weights) / 1.25))
    return tex.mean + tex.amplitude * jnp.tanh(tex.contrast * field / std)


def lambert(
    reflectance: Float[Array, ""], normal: Float[Array, "3"], view: Float[Array, "3"], light: Float[Array, "3"],
    ambient: float,
) -> Float[Array, ""]:
    """Radiance of a Lambertian point: reflectance * (ambient + (1 - ambient) * max(0, n . l)).

    `normal` is flipped to face the viewer (`view` is the ray direction, towards the surface); `light` is the
    unit direction from the surface towards the light.
    """
    n = jnp.where(normal @ view > 0, -normal, normal)
    return reflectance * (ambient + (1.0 - ambient) * jnp.maximum(n @ light, 0.0))
