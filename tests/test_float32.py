"""The float32 path: no NaN or inf anywhere, and the documented float32 errors.

float32 inputs keep every computation in float32 (Python constants are weakly
typed), even with x64 enabled for the rest of the suite.

Documented float32 errors (README table), checked here:
- escape angle, moderate rays (D = 20, alpha in [0.05, 3.1]): < 2e-5 rad;
- near the shadow edge the conditioning is eps32 * alpha / |alpha - alpha_sh|;
- the Einstein-ring radius of a float32 render at D = 20 within 0.1 pixel of float64.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

F32 = jnp.float32
EPS32 = float(np.finfo(np.float32).eps)

# One compiled table builder (the distance is an argument): the float32 table of
# D = 20 at 1e-6 is built once, by the same RayMap.build a render calls, and serves
# the table check and the float32 render below.
_build = eqx.filter_jit(jl.RayMap.build)
_render_array = eqx.filter_jit(jl.render_array)


def _one_block_render(camera, sky, accuracy, ray_map):
    # render_array compiled: its plan (mirrored fast path, one block) is decided on the
    # concrete camera here, as render_array does when called eagerly, and the table is
    # the one RayMap.build gives for the camera's distance, as render_array builds it.
    scene = jl.Scene(camera, sky, accuracy=accuracy)
    plan = jl.plan(scene, chunk_samples=1 << 62)
    return np.asarray(_render_array(scene, plan=plan, ray_map=ray_map))


@pytest.mark.parametrize("d", [1.0001, 1.2, 1.5, 3.0, 20.0, 1e4, 1e8, 1e12])
def test_no_nan_or_inf_anywhere(d):
    ash = float(jl.shadow_angle(d))
    alpha = np.concatenate(
        [
            np.linspace(0.0, math.pi, 2001),
            ash * (1 + np.geomspace(1e-7, 1e-1, 200)),
            ash * (1 - np.geomspace(1e-7, 1e-1, 200)),
        ]
    ).astype(np.float32)
    alpha = np.clip(alpha, 0.0, np.float32(np.pi))  # alpha_sh (1 + x) passes pi near D = 1
    r = jl.trace(jnp.asarray(alpha, F32), jnp.asarray(d, F32))
    assert r.phi.dtype == F32
    assert bool(jnp.all(jnp.isfinite(r.phi))) and bool(jnp.all(jnp.isfinite(r.r_min)))
    g = jax.vmap(jax.grad(lambda a: jl.trace(a, F32(d)).phi))(jnp.asarray(alpha, F32))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_a_distance_that_rounds_to_the_horizon_is_refused():
    # float32 rays and a Python float distance: the working dtype is float32, where
    # 1 + 1e-9 is 1.0, the horizon; that is said, not computed at D = 1.
    alpha = np.array([0.5, 2.0], np.float32)
    with pytest.raises(ValueError, match=r"distance=1.000000001 rounds to 1.0 .* float32"):
        jl.trace(alpha, 1 + 1e-9)
    # In float64 it is a camera just outside the horizon: both rays fall in, resolved.
    r = jl.trace(alpha.astype(np.float64), 1 + 1e-9)
    assert np.all(np.asarray(r.captured)) and not np.any(np.asarray(r.unresolved))


def test_float32_error_on_moderate_rays():
    alpha = np.linspace(0.05, 3.1, 500)
    r64 = jl.trace(alpha, 20.0, accuracy=1e-12)
    r32 = jl.trace(jnp.asarray(alpha, F32), F32(20.0))
    esc = np.asarray(r64.escaped)
    ash = float(jl.shadow_angle(20.0))
    # input rounding to float32 moves phi by eps32 * alpha |dphi/dalpha|; bounded by
    # the conditioning eps32 * alpha / |alpha - alpha_sh| plus the arithmetic error.
    cond = EPS32 * alpha / np.abs(alpha - ash)
    err = np.abs(np.asarray(r32.phi, np.float64) - np.asarray(r64.phi))[esc]
    assert np.all(err < 2e-5 + 4 * cond[esc])
    np.testing.assert_array_equal(np.asarray(r32.status)[esc], np.asarray(r64.status)[esc])


def test_float32_table_matches_float64():
    rm32 = _build(F32(20.0), accuracy=1e-6)
    alpha = jnp.linspace(0.2, 3.0, 300)
    e64 = jl.trace(alpha, 20.0, accuracy=1e-12).phi
    e32 = rm32.escape_angle(alpha.astype(F32))
    assert e32.dtype == F32
    assert float(jnp.max(jnp.abs(e32 - e64))) < 3e-5


def test_float32_table_built_eagerly_keeps_its_knots_and_its_error():
    # The eager build's program is compiled without LLVM's optimisations (no fused
    # multiply-add): counted up from tau_lo ~ -31, the knots near the top were off by
    # ~ulp(31) = 2e-6 and the look-up's error there grew 4-fold (median over these rays
    # 7e-7 instead of 1.5e-7, 99th percentile 4.6e-6 instead of 1.2e-6).
    table = jl.RayMap.build(F32(10.0), accuracy=1e-6, captured=True, iterations=6)
    tau = np.asarray(table.tau, np.float64)
    top = tau[tau > -1.0]  # the knots farthest from the shadow edge
    assert np.max(np.abs(np.diff(top) - float(table.dtau))) < 4 * EPS32
    alpha = np.linspace(0.05, 3.0, 60_000)
    r32 = jl.trace(alpha.astype(np.float32), F32(10.0), method="table")
    r64 = jl.trace(alpha.astype(np.float32).astype(np.float64), 10.0, accuracy=1e-12)
    esc = np.asarray(r64.escaped)
    err = np.abs(np.asarray(r32.phi, np.float64) - np.asarray(r64.phi))[esc]
    assert np.median(err) < 3e-7 and np.percentile(err, 99) < 2e-6


def _ring_radius(img):
    # Intensity-weighted mean radius (pixels) of the ring about the image centre.
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w]
    r = np.hypot(x + 0.5 - w / 2, y + 0.5 - h / 2)
    i = img[..., 0].astype(np.float64)
    return float(np.sum(i * r) / np.sum(i))


def test_float32_render_ring_within_a_tenth_of_a_pixel():
    sky64 = jl.GaussianStar(math.radians(1.0))
    cam64 = jl.Camera(20.0, math.radians(60.0), 160, 160, supersample=2)
    sky32 = jl.GaussianStar(F32(math.radians(1.0)))
    cam32 = jl.Camera(F32(20.0), F32(math.radians(60.0)), 160, 160, supersample=2)
    img64 = _one_block_render(cam64, sky64, 1e-8, _build(jnp.asarray(20.0), accuracy=1e-8))
    img32 = _one_block_render(cam32, sky32, 1e-6, _build(F32(20.0), accuracy=1e-6))
    assert img32.dtype == np.float32
    assert abs(_ring_radius(img32) - _ring_radius(img64)) < 0.1
