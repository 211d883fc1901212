"""OpenCV's rational lens distortion (k1..k6, p1, p2) on normalised image coordinates.

Coefficients are stored in OpenCV's order (k1, k2, p1, p2, k3, k4, k5, k6) so a vector can be handed to
cv2 unchanged. Which of them a calibration may move is static configuration (`free`); the others are
held at their stored value (zero unless the user fixed them elsewhere).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dstereo.errors import DstereoError
from dstereo.models.fisheye import FISHEYE_NAMES
from dstereo.models.splined import DEFAULT_GRID, grid_of, is_splined, knot_names

COEFF_NAMES: tuple[str, ...] = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
# The fisheye lens (dstereo.models.fisheye) keeps cv2.fisheye's D = (k1..k4) in the first four of the same
# 8 slots, named fk1..fk4 so that a free set says which lens model it belongs to.
FISHEYE_SLOTS: tuple[str, ...] = FISHEYE_NAMES + ("", "", "", "")

# Named presets accepted wherever a model is asked for (CLI --model, configuration files).
PRESETS: dict[str, tuple[str, ...]] = {
    "none": (),
    "k1": ("k1",),
    "k1k2": ("k1", "k2"),
    "k1k2p1p2": ("k1", "k2", "p1", "p2"),
    "k1k2k3p1p2": ("k1", "k2", "p1", "p2", "k3"),
    "default": ("k1", "k2", "p1", "p2", "k3"),
    "rational": COEFF_NAMES,
    "fisheye": FISHEYE_NAMES,
    # the splined lens (dstereo.models.splined): every knot of its grid is free; "splined:NXxNY" picks the grid
    "splined": knot_names(*DEFAULT_GRID),
}


def lens_model(free: tuple[str, ...]) -> str:
    """'fisheye' when the free set names fisheye coefficients (fk1..fk4), 'splined' when it names spline knots
    (sx_0_0, ...), else 'pinhole' (OpenCV's rational)."""
    if is_splined(tuple(free)):
        return "splined"
    return "fisheye" if any(n in FISHEYE_NAMES for n in free) else "pinhole"


def model_label(free: tuple[str, ...]) -> str:
    """A free set as people read it: 'k1,k2,p1,p2,k3', 'none', or a splined lens's 'splined:NXxNY' (not its knots)."""
    if is_splined(tuple(free)):
        nx, ny = grid_of(tuple(free))
        return f"splined:{nx}x{ny}"
    return ",".join(free) or "none"


def coeff_slots(free: tuple[str, ...]) -> tuple[str, ...]:
    """Names of the coefficient slots for the lens model of `free`: 8 (OpenCV order, or fisheye k1..k4 + 4
    unused); a splined lens has one slot per knot, all of them free (its coefficient vector is `free` itself)."""
    if is_splined(tuple(free)):
        return tuple(free)
    return FISHEYE_SLOTS if lens_model(free) == "fisheye" else COEFF_NAMES


def _splined_spec(key: str) -> tuple[str, ...]:
    """'splined:NXxNY' -> its knot names."""
    try:
        nx, ny = (int(v) for v in key.split(":", 1)[1].split("x"))
    except ValueError:
        nx = ny = 0
    if nx < 4 or ny < 4:
        raise DstereoError(f"model: {key!r}: write a splined grid as splined:NXxNY with NX, NY >= 4 knots "
                           f"(e.g. splined:{DEFAULT_GRID[0]}x{DEFAULT_GRID[1]}, the default)")
    return knot_names(nx, ny)


def parse_model(spec: str | tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """'k1,k2,p1,p2,k3' or a preset name or a list -> free coefficient names in OpenCV order."""
    if isinstance(spec, str):
        key = spec.strip().lower()
        if key in PRESETS:
            return PRESETS[key]
        if key.startswith("splined:"):
            return _splined_spec(key)
        names = [s.strip().lower() for s in key.replace(" ", ",").split(",") if s.strip()]
    else:
        names = [s.strip().lower() for s in spec]
    if names and is_splined(tuple(names)):
        try:
            grid_of(tuple(names))
        except ValueError as exc:
            raise DstereoError(f"model: {exc}") from None
        return tuple(names)
    bad = [n for n in names if n not in COEFF_NAMES + FISHEYE_NAMES]
    if bad:
        raise DstereoError(
            f"model: unknown distortion coefficient(s) {bad}; use a subset of {list(COEFF_NAMES)} "
            f"(pinhole), of {list(FISHEYE_NAMES)} (fisheye), or a preset {list(PRESETS)}"
        )
    if any(n in FISHEYE_NAMES for n in names) and any(n in COEFF_NAMES for n in names):
        raise DstereoError(
            f"model: {','.join(names)} mixes pinhole ({list(COEFF_NAMES)}) and fisheye ({list(FISHEYE_NAMES)}) "
            "coefficients; choose one lens model"
        )
    order = FISHEYE_NAMES if any(n in FISHEYE_NAMES for n in names) else COEFF_NAMES
    return tuple(n for n in order if n in names)


def with_free(coeffs: Float[Array, "8"], free: tuple[str, ...], values: Float[Array, " f"]) -> Float[Array, "8"]:
    """`coeffs` with the `free` entries replaced by `values` (in `free` order, which is OpenCV order).

    Built from static slices rather than an indexed update: inside a compiled solver an `.at[].set` becomes
    a scatter loop, which costs compile time for nothing when the positions are known at trace time.
    """
    if is_splined(free):  # every knot is free: the vector is the values
        return values
    parts = []
    for i, name in enumerate(coeff_slots(free)):
        parts.append(values[free.index(name)][None] if name in free else coeffs[i:i + 1])
    return jnp.concatenate(parts) if free else coeffs


class Distortion(eqx.Module):
    """Rational + tangential distortion. `coeffs` (8,) in OpenCV order; `free` names the solvable ones."""

    coeffs: Float[Array, "8"]
    free: tuple[str, ...] = eqx.field(static=True, default=PRESETS["default"])

    @classmethod
    def zeros(cls, free: tuple[str, ...] = PRESETS["default"]) -> "Distortion":
        return cls(jnp.zeros(8), tuple(free))

    @property
    def free_index(self) -> tuple[int, ...]:
        return tuple(coeff_slots(self.free).index(n) for n in self.free)

    def free_values(self) -> Float[Array, " nfree"]:
        return self.coeffs[jnp.array(self.free_index, dtype=int)] if self.free else jnp.zeros(0)

    def with_free_values(self, values: Float[Array, " nfree"]) -> "Distortion":
        return Distortion(with_free(self.coeffs, self.free, values), self.free) if self.free else self


def distort(coeffs: Float[Array, "8"], xy: Float[Array, "2"]) -> Float[Array, "2"]:
    """Normalised undistorted (x, y) -> distorted (x'', y''), OpenCV's equations, one point."""
    k1, k2, p1, p2, k3, k4, k5, k6 = coeffs
    x, y = xy[0], xy[1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd])


def newton_step(coeffs: Float[Array, "8"], xy_d: Float[Array, "2"], xy: Float[Array, "2"]) -> Float[Array, "2"]:
    """One Newton step of distort(coeffs, x) = xy_d from x = xy, one point.

    The 2 x 2 system is solved in closed form: vmapped over many points, jnp.linalg.solve's LAPACK call was seen
    to hang jaxlib 0.10.2's CPU runtime (and it compiles to far more code). From a known root this step returns
    the root, and its derivative there is the implicit-function one (-J_distort^-1 d residual / d coeffs), which
    the uncertainty and refinement code differentiate through.
    """
    f = distort(coeffs, xy) - xy_d
    (a, b), (c, d) = jax.jacfwd(distort, argnums=1)(coeffs, xy)
    det = a * d - b * c
    return xy - jnp.stack([d * f[0] - b * f[1], a * f[1] - c * f[0]]) / det


def undistort(
    coeffs: Float[Array, "8"], xy_d: Float[Array, "2"], iterations: int = 8, start: Float[Array, "2"] | None = None
) -> Float[Array, "2"]:
    """Exact inverse of `distort` for one point: `iterations` Newton steps on distort(x) = xy_d from `start`
    (default xy_d itself). The one undistortion of the pinhole model; every caller uses it.

    Newton converges quadratically where the model is invertible, so a handful of iterations reach machine
    precision (OpenCV's undistortPoints uses a fixed-point scheme that does not).
    """
    x0 = xy_d if start is None else start
    xy, _ = jax.lax.scan(lambda xy, _: (newton_step(coeffs, xy_d, xy), None), x0, None, length=iterations)
    return xy
