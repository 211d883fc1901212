"""Splined lens: a stereographic base projection plus a smooth correction surface over the image, for lenses no
parametric model fits (the idea of mrcal's LENSMODEL_SPLINED_STEREOGRAPHIC; written here from its description,
and not the same model: see `io/cameramodel.py`, which writes no twin).

    u = 2 (X, Y) / (|p| + Z)                      the stereographic plane (|u| = 2 tan(theta / 2))
    q0 = (fx u_x + cx, fy u_y + cy)               the base pixel
    a = (fx u_x / cx, fy u_y / cy)                its offset from the principal point in half-images (~ -1..1
                                                  over the image for a centred principal point)
    q = q0 + (Sx(a), Sy(a))                       Sx, Sy: uniform cubic B-spline surfaces, in pixels

Each surface has NY x NX control values over a in [-DOMAIN, DOMAIN]^2 (NX - 3 spans across); outside that square
the argument is clamped (the surface is held at its rim value). The coefficient vector is all Sx values then all
Sy values, row-major (row = y): names `sx_<row>_<col>`, `sy_<row>_<col>` (`knot_names`), so a free set names
the grid and the model is known from its names alone, like the other lens models.

The surface and (fx, fy, cx, cy) share directions (a constant surface is a principal-point shift, a linear one a
focal change or a roll the board poses absorb), and knots no corner reaches are not seen at all: the calibration
adds `prior_rows` (curvature and a weak ridge) to its cost, so those are decided by the prior and their
projection uncertainty is large.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

DOMAIN = 1.25  # half-width of the control grid in half-images: covers the image with room for a principal point
# off the centre and for base pixels beyond the rim (stereographic maps a wide lens's edge further out)
DEFAULT_GRID = (10, 8)  # (NX, NY) of the `splined` preset: 7 x 5 spans over the square
# The prior (`prior_rows`), in the cost's own unit (px^2, like a corner residual): each second difference of a
# surface between neighbouring knots (along x, along y, and the mixed one with thin-plate energy's weight sqrt 2)
# is a residual row of weight CURVATURE_WEIGHT, each knot value one of weight RIDGE_WEIGHT. A knot that C corner
# residuals reach holds ~C / 10 of data information (cubic B-spline weights are <= 2/3, ~0.3 on average) against
# ~20 CURVATURE_WEIGHT^2 of the prior: 0.2 % for one corner, so the prior bends the fit only where no corner is.
# There a second difference has a standard deviation of sigma / CURVATURE_WEIGHT = 100 sigma per knot, compounding
# with the distance from the corners: the projection uncertainty grows there, large, as it should. Measured on the
# rendered odd lens (the since-removed experiments/splined_odd_lens.py): weight 0.1 left the 10 x 8 fit at 0.22 px RMS on 0.1 px
# noise (the prior bent a fisheye's ~100 px correction), 0.01 at 0.136 px (the noise).
CURVATURE_WEIGHT = 0.01
# The ridge pins what the corners cannot see (the surface's shift, scale and roll, which fx fy cx cy and the board
# poses also hold). Measured on the odd lens: 1e-2 converges in 38 iterations at 0.132 px RMS; 1e-3 leaves those
# directions so flat that LM crawls along them (200 iterations, unconverged) for no better fit.
RIDGE_WEIGHT = 1e-2
VALID_MIN_CORNERS = 4  # a span of the grid is in the valid region when at least this many corners fell in it
NEWTON_ITERATIONS = 30
ROUND_TRIP_PX = 1e-6  # an unprojected pixel's ray must project back within this (Newton converges to ~1e-12)

_NAME = re.compile(r"^s([xy])_(\d+)_(\d+)$")


def knot_names(nx: int, ny: int) -> tuple[str, ...]:
    """Coefficient names of an NX x NY grid: all sx (row-major), then all sy."""
    return tuple(f"s{c}_{r}_{k}" for c in "xy" for r in range(ny) for k in range(nx))


def is_splined(free: tuple[str, ...]) -> bool:
    return bool(free) and _NAME.match(free[0]) is not None


def grid_of(free: tuple[str, ...]) -> tuple[int, int]:
    """(NX, NY) named by a free set of knot names; raises ValueError unless they are exactly one full grid."""
    last = _NAME.match(free[-1]) if free else None
    if last is None:
        raise ValueError(f"not a splined model: {free[:3]}...")
    ny, nx = int(last.group(2)) + 1, int(last.group(3)) + 1
    if nx < 4 or ny < 4 or tuple(free) != knot_names(nx, ny):
        raise ValueError("a splined model names every knot of an NX x NY grid (NX, NY >= 4) in order: "
                         f"sx_0_0 .. sx_{ny - 1}_{nx - 1}, then sy_..")
    return nx, ny


def stereographic(p: Float[Array, "3 ..."]):
    """u (2, ...) on the stereographic plane and du/dp (2, 3, ...)."""
    rho = jnp.sqrt(p[0] ** 2 + p[1] ** 2 + p[2] ** 2)
    d = rho + p[2]
    u = 2.0 * p[:2] / d
    dd = jnp.stack([p[0] / rho, p[1] / rho, p[2] / rho + 1.0])  # d(rho + z) / dp
    eye = jnp.eye(3)[:2].reshape((2, 3) + (1,) * (p.ndim - 1))
    du = 2.0 * eye / d - (2.0 * p[:2] / d ** 2)[:, None] * dd[None, :]
    return u, du


def ray_of(u: Float[Array, "2"]) -> Float[Array, "3"]:
    """Unit ray whose stereographic image is u (the inverse of `stereographic`; valid to 180 degrees)."""
    s2 = 0.25 * jnp.sum(u * u)
    return jnp.concatenate([u, (1.0 - s2)[None]]) / (1.0 + s2)


def _basis(t, n: int):
    """Cubic B-spline weights of control points 0..n-1 at grid positions t (any shape) and their derivatives
    d / dt: (n, ...) each. t in [0, n - 3] spans the grid; outside it is clamped (weights fixed, derivative 0)."""
    inside = (t >= 0.0) & (t <= n - 3.0)
    tc = jnp.clip(t, 0.0, n - 3.0)
    i = jnp.clip(jnp.floor(tc), 0, n - 4)
    s = tc - i
    b = jnp.stack([(1 - s) ** 3, 3 * s ** 3 - 6 * s ** 2 + 4, -3 * s ** 3 + 3 * s ** 2 + 3 * s + 1, s ** 3]) / 6.0
    db = jnp.stack([-3 * (1 - s) ** 2, 9 * s ** 2 - 12 * s, -9 * s ** 2 + 6 * s + 3, 3 * s ** 2]) / 6.0
    db = jnp.where(inside, db, 0.0)
    offset = jnp.arange(n).reshape((n,) + (1,) * t.ndim) - i  # which of the 4 local weights each control gets
    pick = lambda w: sum(jnp.where(offset == m, w[m], 0.0) for m in range(4))  # noqa: E731
    return pick(b), pick(db)


def _surfaces(coeffs, a, nx: int, ny: int):
    """S (2, ...) at a (2, ...), dS/da (2 components, 2 axes, ...) and the basis (wy (ny, ...), wx (nx, ...)) whose
    outer product is dS_c / d(knots of c)."""
    h = 2.0 * DOMAIN
    wx, dwx = _basis((a[0] + DOMAIN) * (nx - 3) / h, nx)
    wy, dwy = _basis((a[1] + DOMAIN) * (ny - 3) / h, ny)
    grids = coeffs.reshape(2, ny, nx)
    sx, sy = (nx - 3) / h, (ny - 3) / h
    val = lambda g, wy_, wx_: jnp.einsum("rk,r...,k...->...", g, wy_, wx_)  # noqa: E731
    s = jnp.stack([val(g, wy, wx) for g in grids])
    ds = jnp.stack([jnp.stack([val(g, wy, dwx) * sx, val(g, dwy, wx) * sy]) for g in grids])
    return s, ds, (wy, wx)


def project(k: Float[Array, "4"], coeffs: Float[Array, " c"], p_cam: Float[Array, "3 ..."], nx: int, ny: int):
    """Camera-frame point(s) (3,) or (3, n) -> pixel(s) (2,) or (2, n)."""
    u, _ = stereographic(p_cam)
    kf, kc = k[:2].reshape((2,) + (1,) * (u.ndim - 1)), k[2:4].reshape((2,) + (1,) * (u.ndim - 1))
    s, _, _ = _surfaces(coeffs, kf * u / kc, nx, ny)
    return kf * u + kc + s


def project_jacobian(k: Float[Array, "4"], coeffs: Float[Array, " c"], p_cam: Float[Array, "3 n"], nx: int, ny: int):
    """`project` on (3, n) columns and d q / d k (2, 4, n), d q / d coeffs (2, 2 NX NY, n), d q / d p (2, 3, n).

    By hand, like the other lens models (the solver is compiled around it; tests compare it with autodiff)."""
    u, du = stereographic(p_cam)
    fx, fy, cx, cy = k[0], k[1], k[2], k[3]
    a = jnp.stack([fx * u[0] / cx, fy * u[1] / cy])
    s, ds, (wy, wx) = _surfaces(coeffs, a, nx, ny)
    q = jnp.stack([fx * u[0] + cx + s[0], fy * u[1] + cy + s[1]])
    # a_x = fx u_x / cx: d a_x / d fx = u_x / cx, d a_x / d cx = -a_x / cx (and a_y likewise)
    da_dk = [(u[0] / cx, 0.0 * u[0], -a[0] / cx, 0.0 * u[0]), (0.0 * u[1], u[1] / cy, 0.0 * u[1], -a[1] / cy)]
    base = [(u[0], 0.0 * u[0], 1.0 + 0.0 * u[0], 0.0 * u[0]), (0.0 * u[1], u[1], 0.0 * u[1], 1.0 + 0.0 * u[1])]
    dk = jnp.stack([jnp.stack([base[c][j] + ds[c, 0] * da_dk[0][j] + ds[c, 1] * da_dk[1][j] for j in range(4)])
                    for c in range(2)])
    n = p_cam.shape[1]
    knots = (wy[:, None, :] * wx[None, :, :]).reshape(ny * nx, n)
    zero = jnp.zeros_like(knots)
    dc = jnp.stack([jnp.concatenate([knots, zero]), jnp.concatenate([zero, knots])])
    # q_c = f_c u_c + dS_c/da_x (fx / cx) u_x + dS_c/da_y (fy / cy) u_y (+ constants): d / du, then d u / d p
    dq_du = jnp.stack([jnp.stack([fx + ds[0, 0] * fx / cx, ds[0, 1] * fy / cy]),
                       jnp.stack([ds[1, 0] * fx / cx, fy + ds[1, 1] * fy / cy])])
    dp = jnp.einsum("cen,ejn->cjn", dq_du, du)
    return q, dk, dc, dp


def unproject(k: Float[Array, "4"], coeffs: Float[Array, " c"], q: Float[Array, "2"], nx: int, ny: int):
    """Pixel -> unit ray (3,) and whether Newton on q = project(u) converged (round trip within ROUND_TRIP_PX)
    with the argument inside the grid and the map's 2 x 2 Jacobian keeping its orientation; NaN where not."""
    f, c = k[:2], k[2:4]

    def residual_jac(u):
        s, ds, _ = _surfaces(coeffs, f * u / c, nx, ny)
        return f * u + c + s - q, jnp.diag(f) + ds * (f / c)[None, :]

    def step(u, _):
        r, j = residual_jac(u)
        det = j[0, 0] * j[1, 1] - j[0, 1] * j[1, 0]
        du = jnp.stack([j[1, 1] * r[0] - j[0, 1] * r[1], j[0, 0] * r[1] - j[1, 0] * r[0]]) / det
        return u - du, None

    u, _ = jax.lax.scan(step, (q - c) / f, None, length=NEWTON_ITERATIONS)
    r, j = residual_jac(u)
    a = f * u / c
    ok = (jnp.all(jnp.isfinite(u)) & (jnp.linalg.norm(r) < ROUND_TRIP_PX) & jnp.all(jnp.abs(a) <= DOMAIN)
          & (j[0, 0] * j[1, 1] - j[0, 1] * j[1, 0] > 0))
    return jnp.where(ok, ray_of(u), jnp.nan), ok


def _second_differences(nx: int, ny: int) -> np.ndarray:
    """Rows (m, NY NX) of one surface's second differences: along x, along y, and mixed (weight sqrt 2)."""
    idx = np.arange(ny * nx).reshape(ny, nx)
    rows = []
    for r in range(ny):
        for k in range(1, nx - 1):
            rows.append({idx[r, k - 1]: 1.0, idx[r, k]: -2.0, idx[r, k + 1]: 1.0})
    for r in range(1, ny - 1):
        for k in range(nx):
            rows.append({idx[r - 1, k]: 1.0, idx[r, k]: -2.0, idx[r + 1, k]: 1.0})
    w = np.sqrt(2.0)
    for r in range(ny - 1):
        for k in range(nx - 1):
            rows.append({idx[r, k]: w, idx[r, k + 1]: -w, idx[r + 1, k]: -w, idx[r + 1, k + 1]: w})
    out = np.zeros((len(rows), ny * nx))
    for i, row in enumerate(rows):
        for j, v in row.items():
            out[i, j] = v
    return out


def prior_rows(nx: int, ny: int) -> np.ndarray:
    """(m, 2 NX NY) the prior's residual rows on the coefficient vector (their target is 0): CURVATURE_WEIGHT x
    second differences and RIDGE_WEIGHT x values, both surfaces (see the module's weight rule)."""
    d = CURVATURE_WEIGHT * _second_differences(nx, ny)
    z = np.zeros_like(d)
    curvature = np.block([[d, z], [z, d]])
    return np.concatenate([curvature, RIDGE_WEIGHT * np.eye(2 * nx * ny)])


def span_of(k: np.ndarray, q: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """(…, 2) integer (col, row) of the grid span each pixel's argument a falls in (approximately: the base
    pixel's offset is taken as the pixel's own, which is what the valid region needs), -1 outside."""
    k = np.asarray(k, float)
    a = (np.asarray(q, float) - k[2:4]) / k[2:4]
    t = (a + DOMAIN) / (2.0 * DOMAIN) * (np.array([nx, ny]) - 3)
    cell = np.floor(t).astype(int)
    inside = np.all((t >= 0) & (cell < np.array([nx, ny]) - 3), axis=-1)
    return np.where(inside[..., None], cell, -1)


def valid_spans(k: np.ndarray, corners: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """(NY - 3, NX - 3) bool: the grid spans holding at least VALID_MIN_CORNERS of the corners (…, 2) px: the valid
    region, where corners constrain the surface."""
    cells = span_of(k, np.asarray(corners, float).reshape(-1, 2), nx, ny)
    cells = cells[cells[:, 0] >= 0]
    count = np.zeros((ny - 3, nx - 3), int)
    np.add.at(count, (cells[:, 1], cells[:, 0]), 1)
    return count >= VALID_MIN_CORNERS


def in_valid_region(k: np.ndarray, q: np.ndarray, valid: np.ndarray) -> Bool[np.ndarray, "..."]:
    """Whether each pixel (…, 2) lies in a valid span (`valid_spans`)."""
    ny, nx = np.shape(valid)[0] + 3, np.shape(valid)[1] + 3
    cell = span_of(k, q, nx, ny)
    inside = cell[..., 0] >= 0
    return inside & np.asarray(valid)[np.where(inside, cell[..., 1], 0), np.where(inside, cell[..., 0], 0)]
