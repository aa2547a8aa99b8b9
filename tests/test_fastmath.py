"""The vectorisable elementary functions of `jaxlens._fastmath` against NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlens import _fastmath


def _ulps(got, want, dtype):
    """|got - want| in units of the last place of `want` in `dtype` (at least 1e-3's)."""
    spacing = np.spacing(np.maximum(np.abs(want), 1e-3).astype(dtype)).astype(np.float64)
    return np.abs(got.astype(np.float64) - want) / spacing


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_log_within_a_few_ulps_over_the_whole_range(dtype):
    info = np.finfo(dtype)
    rng = np.random.default_rng(7)
    x = np.concatenate([
        np.exp(rng.uniform(np.log(info.tiny), np.log(info.max), 40_000)),
        rng.uniform(0.5, 2.0, 40_000),  # around 1, where the result is small
        np.sqrt(2.0) * (1.0 + rng.uniform(-1e-3, 1e-3, 10_000)),  # the reduction's seam
        [info.tiny, info.max, 1.0, 2.0, 0.5, np.e],
    ]).astype(dtype)  # fmt: skip
    want = np.log(x.astype(np.float64))
    got = np.asarray(jax.jit(_fastmath.log)(x))
    assert got.dtype == dtype
    assert _ulps(got, want, dtype).max() <= 4.0
    # Op by op (no fused multiply-adds): as close.
    assert _ulps(np.asarray(_fastmath.log(x[:100])), want[:100], dtype).max() <= 4.0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_log_special_values(dtype):
    x = np.array([0.0, -0.0, -1.0, np.inf, -np.inf, np.nan], dtype)
    got = np.asarray(jax.jit(_fastmath.log)(x))
    np.testing.assert_array_equal(got[:2], [-np.inf, -np.inf])
    assert np.isnan(got[2]) and np.isnan(got[4]) and np.isnan(got[5])
    assert got[3] == np.inf


def test_log_derivatives_are_one_over_x():
    x = jnp.array([1e-12, 0.3, 1.0, 7.5, 1e30])
    np.testing.assert_allclose(jax.vmap(jax.grad(_fastmath.log))(x), 1.0 / x, rtol=1e-15)
    _, tangent = jax.jvp(_fastmath.log, (x,), (2.0 * jnp.ones_like(x),))
    np.testing.assert_allclose(tangent, 2.0 / x, rtol=1e-15)


def test_log_other_dtypes_use_jnp():
    x = jnp.array([1.0, 2.0], jnp.bfloat16)
    np.testing.assert_array_equal(_fastmath.log(x), jnp.log(x))
