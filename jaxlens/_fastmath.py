"""Vectorisable float32 arctan2, sin and cos for the per-pixel hot path.

XLA's CPU backend evaluates float32 `atan2`, `sin` and `cos` one element at a time
(about 45, 14 and 10 ns each on the 2-core benchmark machine, against 0.5 ns for a
multiply-add), which made them most of a 1080p render. These are the Cephes
single-precision polynomials (S. L. Moshier) after an exact Cody-Waite range
reduction: plain multiply-adds and selects that XLA vectorises on CPU and fuses on
GPU, with errors of a few float32 ulps (tests/test_render.py checks them against
float64 NumPy). Inputs of any other dtype (float64) go to `jax.numpy`, which is
correctly rounded there: the float64 path stays the accurate reference.
"""

import math

import jax.numpy as jnp

_PIO2_1 = 1.5703125  # pi/2 in three parts; the first two have short mantissas,
_PIO2_2 = 4.837512969970703125e-4  # so k * part is exact for |k| < 2^15
_PIO2_3 = 7.54978995489188216e-8
_TAN_PI_8 = 0.4142135623730950


def _is_f32(x) -> bool:
    return jnp.asarray(x).dtype == jnp.float32


def _atan_unit(a):
    """arctan(a) for a in [0, 1] (Cephes atanf after one reduction step)."""
    big = a > _TAN_PI_8
    x = jnp.where(big, (a - 1.0) / (a + 1.0), a)
    z = x * x
    p = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z
         - 3.33329491539e-1) * z * x + x  # fmt: skip
    return jnp.where(big, p + (0.25 * math.pi), p)


def arctan2(y, x):
    """$\\operatorname{atan2}(y, x)$ in $(-\\pi, \\pi]$, radians; `jnp.arctan2` except
    in float32. `(0, 0)` gives 0."""
    y, x = jnp.broadcast_arrays(y, x)
    if not _is_f32(y):
        return jnp.arctan2(y, x)
    ax, ay = jnp.abs(x), jnp.abs(y)
    mx, mn = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    a = mn / jnp.where(mx > 0, mx, 1.0)
    r = _atan_unit(a)
    r = jnp.where(ay > ax, (0.5 * math.pi) - r, r)
    r = jnp.where(x < 0, math.pi - r, r)
    return jnp.where(jnp.signbit(y), -r, r)


def sin_cos(phi):
    """`(sin(phi), cos(phi))`, radians; `jnp` except in float32, where the error
    stays at a few ulps for $|\\phi| < 10^4$."""
    if not _is_f32(phi):
        return jnp.sin(phi), jnp.cos(phi)
    k = jnp.round(phi * (2.0 / math.pi))
    r = ((phi - k * _PIO2_1) - k * _PIO2_2) - k * _PIO2_3
    z = r * r
    s = ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1) * z * r + r
    c = ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z + 4.166664568298827e-2) * (
        z * z
    ) - 0.5 * z + 1.0  # fmt: skip
    q = k.astype(jnp.int32) & 3
    sin = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    cos = jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))
    return sin, cos
