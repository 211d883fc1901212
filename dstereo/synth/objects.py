"""Analytic surfaces for object renders: a rectangular plane, a sphere, and the cork Plasmatron sample.

Each surface lives in its own object frame and answers, for one ray `o + t d` (object frame; `d` need not be
unit length), `hit(o, d) -> (t, part)`: the parameter of the first hit (`inf` on a miss) and which part of the
surface was hit (-1 on a miss). `implicit(p, part)` is zero on that part of the surface (a length in mm, the
truth the depth-map tests check against), `normal(p, part)` its outward unit normal, and
`texture_point(p, part)` the point at which the speckle texture is evaluated, fixed to the surface.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dstereo.errors import DstereoError

MISS = -1


def _unit(v: Float[Array, "3"]) -> Float[Array, "3"]:
    return v / jnp.linalg.norm(v)


class Plane(eqx.Module):
    """Rectangle z = 0, |x| <= half_width, |y| <= half_height (mm), object frame."""

    half_width: float = 40.0
    half_height: float = 30.0

    def hit(self, o: Float[Array, "3"], d: Float[Array, "3"]) -> tuple[Float[Array, ""], Array]:
        dz = jnp.where(jnp.abs(d[2]) > 1e-15, d[2], 1e-15)
        t = -o[2] / dz
        p = o + t * d
        ok = (t > 0) & (jnp.abs(p[0]) <= self.half_width) & (jnp.abs(p[1]) <= self.half_height)
        return jnp.where(ok, t, jnp.inf), jnp.where(ok, 0, MISS)

    def implicit(self, p: Float[Array, "3"], part: Array) -> Float[Array, ""]:
        return p[2]

    def normal(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        return jnp.array([0.0, 0.0, 1.0])

    def texture_point(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        return jnp.array([p[0], p[1], 0.0])

    def truth(self) -> dict:
        return {"type": "plane", "half_width": float(self.half_width), "half_height": float(self.half_height),
                "equation": "z = 0 in the object frame"}


class Sphere(eqx.Module):
    """Sphere of `radius` (mm) centred on the object-frame origin."""

    radius: float = 25.0

    def hit(self, o: Float[Array, "3"], d: Float[Array, "3"]) -> tuple[Float[Array, ""], Array]:
        a = d @ d
        b = 2.0 * (o @ d)
        c = o @ o - self.radius**2
        disc = b * b - 4.0 * a * c
        sq = jnp.sqrt(jnp.maximum(disc, 0.0))
        q = -0.5 * (b + jnp.where(b >= 0, sq, -sq))
        t1, t2 = q / a, c / jnp.where(q == 0, 1e-300, q)
        near, far = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
        t = jnp.where(near > 0, near, far)
        ok = (disc >= 0) & (t > 0)
        return jnp.where(ok, t, jnp.inf), jnp.where(ok, 0, MISS)

    def implicit(self, p: Float[Array, "3"], part: Array) -> Float[Array, ""]:
        return jnp.linalg.norm(p) - self.radius

    def normal(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        return _unit(p)

    def texture_point(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        return p

    def truth(self) -> dict:
        return {"type": "sphere", "radius": float(self.radius), "centre": [0.0, 0.0, 0.0],
                "equation": "|p| = radius in the object frame"}


FRONT, SIDE = 0, 1
BISECTIONS, NEWTON_STEPS = 12, 4


class Sample(eqx.Module):
    """The cork Plasmatron sample (thesis 5.3.1): a body of revolution about the object-frame z axis.

    The side is a frustum from radius `base_radius` at z = 0 to `head_radius` at z = `length` (thesis: 50 mm
    long, 41.6 mm base and 49 mm head diameter; equal radii give a cylinder). The front face, facing +z, is the
    height field z = F(rho) over the head, rho = sqrt(x^2 + y^2):

        F(rho) = length + cap(rho) - recession_uniform - recession_peak * exp(-rho^2 / (2 recession_sigma^2))

    with cap the spherical cap of height `dome_height` whose rim is the head circle (sphere radius
    (head_radius^2 + dome_height^2) / (2 dome_height)); `dome_height = 0` is a flat front (`Sample.flat()`).
    The solid is {0 <= z <= F(rho), rho <= r_side(z)}; its base (z = 0, on the holder) is not rendered. The
    front-face hit is found by bisection then Newton along the ray, which assumes the ray crosses the face once
    (true for views within ~50 deg of the axis, the stereo geometry of the thesis).
    """

    length: float = 50.0
    base_radius: float = 20.8
    head_radius: float = 24.5
    dome_height: float = 4.0
    recession_uniform: float = 0.0
    recession_peak: float = 0.0
    recession_sigma: float = 8.0

    def __check_init__(self):
        sizes = {"length": self.length, "base_radius": self.base_radius, "head_radius": self.head_radius,
                 "recession_sigma": self.recession_sigma}
        bad = {k: v for k, v in sizes.items() if isinstance(v, (int, float)) and not v > 0}
        if bad:
            raise DstereoError(f"Sample {bad}: lengths must be positive (mm)")

    @classmethod
    def flat(cls, **kwargs) -> "Sample":
        """The sample with a flat front face."""
        return cls(dome_height=0.0, **kwargs)

    @property
    def front(self) -> str:
        return "dome" if float(self.dome_height) > 0 else "flat"

    # --- profile -----------------------------------------------------------------------------------------
    def cap(self, rho2: Float[Array, ""]) -> Float[Array, ""]:
        """Height of the dome above the head circle at rho^2 (zero for a flat front). Flat and domed samples
        share one compiled renderer: the flat case is selected by value, not by structure."""
        h = jnp.maximum(self.dome_height, 0.0)
        h_safe = jnp.where(h > 0, h, 1.0)
        rs = (self.head_radius**2 + h_safe * h_safe) / (2.0 * h_safe)
        dome = jnp.sqrt(jnp.maximum(rs * rs - rho2, 0.0)) - (rs - h_safe)
        return jnp.where(h > 0, dome, 0.0)

    def front_height(self, rho2: Float[Array, ""]) -> Float[Array, ""]:
        """F as a function of rho^2 (smooth on the axis); beyond the head radius the cap is held at its rim."""
        rho2c = jnp.minimum(rho2, self.head_radius**2)
        bump = self.recession_peak * jnp.exp(-rho2 / (2.0 * self.recession_sigma**2))
        return self.length + self.cap(rho2c) - self.recession_uniform - bump

    def side_radius(self, z: Float[Array, ""]) -> Float[Array, ""]:
        return self.base_radius + (self.head_radius - self.base_radius) * z / self.length

    def stagnation_point(self) -> Float[Array, "3"]:
        """Front-face point on the axis (where the plasma jet stagnates)."""
        return jnp.array([0.0, 0.0, self.front_height(jnp.asarray(0.0))])

    # --- ray intersection --------------------------------------------------------------------------------
    def _hit_front(self, o, d):
        top = self.length + jnp.maximum(self.dome_height, 0.0) + 1.0
        bottom = self.length - self.recession_uniform - jnp.abs(self.recession_peak) - 1.0
        dz = jnp.where(d[2] < -1e-12, d[2], -1e-12)
        lo = jnp.maximum((top - o[2]) / dz, 0.0)
        hi = (bottom - o[2]) / dz
        g = lambda t: o[2] + t * d[2] - self.front_height((o[0] + t * d[0]) ** 2 + (o[1] + t * d[1]) ** 2)  # noqa: E731

        def bisect(_, bracket):
            a, b = bracket
            m = 0.5 * (a + b)
            above = g(m) > 0
            return jnp.where(above, m, a), jnp.where(above, b, m)

        def newton(_, state):
            t, a, b = state
            value, slope = jax.jvp(g, (t,), (jnp.ones_like(t),))
            a, b = jnp.where(value > 0, t, a), jnp.where(value > 0, b, t)
            step = t - value / jnp.where(slope == 0, -1.0, slope)
            return jnp.where((step >= a) & (step <= b), step, 0.5 * (a + b)), a, b

        # Bisection narrows the bracket to 1/4096 of its length; safeguarded Newton polishes to rounding.
        a, b = jax.lax.fori_loop(0, BISECTIONS, bisect, (lo, hi))
        t, _, _ = jax.lax.fori_loop(0, NEWTON_STEPS, newton, (0.5 * (a + b), a, b))
        p = o + t * d
        ok = (d[2] < -1e-12) & (g(lo) > 0) & (hi > lo) & (p[0] ** 2 + p[1] ** 2 <= self.side_radius(p[2]) ** 2)
        return jnp.where(ok, t, jnp.inf)

    def _side_valid(self, o, d, t):
        p = o + t * d
        r = self.side_radius(p[2])
        return (t > 0) & (p[2] >= 0) & (p[2] <= self.front_height(r**2)) & (r > 0)

    def _hit_side(self, o, d):
        kk = (self.head_radius - self.base_radius) / self.length
        r0 = self.base_radius + kk * o[2]
        a = d[0] ** 2 + d[1] ** 2 - kk**2 * d[2] ** 2
        b = 2.0 * (o[0] * d[0] + o[1] * d[1] - kk * d[2] * r0)
        c = o[0] ** 2 + o[1] ** 2 - r0**2
        disc = b * b - 4.0 * a * c
        sq = jnp.sqrt(jnp.maximum(disc, 0.0))
        q = -0.5 * (b + jnp.where(b >= 0, sq, -sq))
        t1 = jnp.where(jnp.abs(a) > 1e-300, q / jnp.where(a == 0, 1.0, a), jnp.inf)
        t2 = jnp.where(jnp.abs(q) > 1e-300, c / jnp.where(q == 0, 1.0, q), jnp.inf)
        t1 = jnp.where((disc >= 0) & self._side_valid(o, d, t1), t1, jnp.inf)
        t2 = jnp.where((disc >= 0) & self._side_valid(o, d, t2), t2, jnp.inf)
        return jnp.minimum(t1, t2)

    def hit(self, o: Float[Array, "3"], d: Float[Array, "3"]) -> tuple[Float[Array, ""], Array]:
        tf, ts = self._hit_front(o, d), self._hit_side(o, d)
        t = jnp.minimum(tf, ts)
        part = jnp.where(jnp.isfinite(t), jnp.where(tf <= ts, FRONT, SIDE), MISS)
        return t, part

    # --- surface ------------------------------------------------------------------------------------------
    def _implicit_front(self, p):
        return p[2] - self.front_height(p[0] ** 2 + p[1] ** 2)

    def _implicit_side(self, p):
        return jnp.sqrt(p[0] ** 2 + p[1] ** 2 + 1e-300) - self.side_radius(p[2])

    def implicit(self, p: Float[Array, "3"], part: Array) -> Float[Array, ""]:
        return jnp.where(part == SIDE, self._implicit_side(p), self._implicit_front(p))

    def normal(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        """Gradient of the hit part's implicit function, normalised: front (-2x F', -2y F', 1) with
        F' = dF/d(rho^2), side (x/rho, y/rho, -dr/dz)."""
        slope = jax.grad(self.front_height)(p[0] ** 2 + p[1] ** 2)
        n_front = jnp.array([-2.0 * p[0] * slope, -2.0 * p[1] * slope, 1.0])
        rho = jnp.sqrt(p[0] ** 2 + p[1] ** 2 + 1e-300)
        n_side = jnp.array([p[0] / rho, p[1] / rho, -(self.head_radius - self.base_radius) / self.length])
        return _unit(jnp.where(part == SIDE, n_side, n_front))

    def texture_point(self, p: Float[Array, "3"], part: Array) -> Float[Array, "3"]:
        # The front face carries its speckle in (x, y), so the pattern stays put as the face recedes.
        return jnp.where(part == SIDE, p, jnp.array([p[0], p[1], 0.0]))

    def truth(self) -> dict:
        return {
            "type": "sample", "front": self.front, "length": float(self.length),
            "base_radius": float(self.base_radius), "head_radius": float(self.head_radius),
            "dome_height": max(float(self.dome_height), 0.0),
            "recession_uniform": float(self.recession_uniform), "recession_peak": float(self.recession_peak),
            "recession_sigma": float(self.recession_sigma),
            "stagnation_point": [float(v) for v in self.stagnation_point()],
            "equation": "front z = length + cap(rho) - recession_uniform - recession_peak*exp(-rho^2/(2 sigma^2)); "
                        "side rho = base_radius + (head_radius - base_radius) z / length; object frame, axis +z",
        }
