"""Vectorisable arctan2, sin, cos (float32) and log (float32 and float64) for hot paths.

XLA's CPU backend evaluates float32 `atan2`, `sin` and `cos` one element at a time
(about 45, 14 and 10 ns each on the 2-core benchmark machine, against 0.5 ns for a
multiply-add), which made them most of a 1080p render, and `log` likewise in float64,
which made it most of a table look-up. These are plain multiply-adds, bit operations
and selects that XLA vectorises on CPU and fuses on GPU. The float32 trigonometric
functions are the Cephes single-precision polynomials (S. L. Moshier) after an exact
Cody-Waite range reduction, with errors of a few float32 ulps (tests/test_render.py
checks them against float64 NumPy); inputs of any other dtype (float64) go to
`jax.numpy`, which is correctly rounded there. `log` splits off the binary exponent and
sums the series of $2\\operatorname{artanh}$ on the mantissa, within 4 ulps (float64)
and 3 (float32) of the correctly rounded value (tests/test_fastmath.py).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np

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


# ln 2 in two parts; the first has a short mantissa, so e * part is exact for any
# binary exponent e of the dtype.
_LN2 = {
    np.dtype(np.float64): (6.93147180369123816490e-01, 1.90821492927058770002e-10),
    np.dtype(np.float32): (0.693359375, -2.12194440e-4),
}
# Terms of the artanh series a dtype needs: |s| <= 3 - 2 sqrt(2) = 0.1716 after the
# reduction, so the first term left out, 2 s^(2n+1) / (2n+1), is below a tenth of an
# ulp of the result (ln sqrt(2) = 0.35 there).
_LOG_TERMS = {np.dtype(np.float64): 11, np.dtype(np.float32): 5}


def _reciprocal(y, steps):
    """$1/y$ for $y$ in $[2 - \\sqrt{1/2}, 2 + \\sqrt{2} - 1]$ by multiplications alone:
    XLA fuses no division into a consumer that reads it twice, so a division would cost
    the log a pass over memory of its own. The linear start is within 3.1 % (relative),
    and each Newton step squares the error: 4 steps reach 5e-25, 3 reach 7e-13."""
    a, b = 2.0 - math.sqrt(0.5), 1.0 + math.sqrt(2.0)
    r = (a + b - y) * (1.0 / (a * b))
    for _ in range(steps):
        r = r * (2.0 - y * r)
    return r


@jax.custom_jvp
def log(x):
    """Natural logarithm, elementwise, for float32 and float64 arrays: `jnp.log`
    within 4 ulps (float64) and 3 (float32), 0 giving -inf, negatives NaN, subnormals
    handled; vectorised by XLA on CPU, where `jnp.log` is not
    (`benchmarks/results/floor.md`). The derivative is $1/x$, in both modes."""
    x = jnp.asarray(x)
    dtype = np.dtype(x.dtype)
    if dtype not in _LN2:
        return jnp.log(x)
    f64 = dtype == np.float64
    ints, bits_m, bias = (jnp.int64, 52, 1023) if f64 else (jnp.int32, 23, 127)
    info = jnp.finfo(dtype)
    small = x < info.tiny  # subnormal (or zero, negative): scaled into the normals
    xn = jnp.where(small, x * (2.0**bits_m), x)
    bits = jax.lax.bitcast_convert_type(xn, ints)
    e = (bits >> bits_m) - jnp.where(small, bias + bits_m, bias)
    one = np.asarray(1.0, dtype).view(np.int64 if f64 else np.int32)
    m = jax.lax.bitcast_convert_type((bits & ((1 << bits_m) - 1)) | one, dtype)  # [1, 2)
    big = m > math.sqrt(2.0)  # the mantissa into [sqrt(1/2), sqrt(2))
    m = jnp.where(big, 0.5 * m, m)
    e = (e + big).astype(dtype)
    f = m - 1.0  # exact
    s = f * _reciprocal(2.0 + f, 4 if f64 else 3)
    z = s * s
    n = _LOG_TERMS[dtype]
    p = jnp.full_like(z, 2.0 / (2 * n - 1))
    for k in range(n - 2, 0, -1):
        p = 2.0 / (2 * k + 1) + z * p
    hi, lo = _LN2[dtype]
    r = e * hi + ((2.0 * s + s * z * p) + e * lo)
    r = jnp.where(x < jnp.inf, r, x)  # inf, NaN
    return jnp.where(x > 0, r, jnp.where(x == 0, -jnp.inf, jnp.nan))


@log.defjvp
def _log_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return log(x), dx / x
