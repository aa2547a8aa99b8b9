"""The ray-level API takes any value and either answers with finite numbers or refuses it
by name: `trace`, `RayMap.build`, `Camera` and `weak_field_escape_angle` given arbitrary
values (NaN, inf, huge, tiny, negative, integer, bool, complex, text, None, lists).

Eagerly, a refusal is a `ValueError` or `TypeError` whose message names the argument;
under `jax.jit` (one program a function, compiled once outside the examples, the value
its traced argument) an error at run time whose message names it. A `Camera` checks
known values when it is built and traced ones where they are used (here: `trace` of its
distance), as the renderer does.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings, strategies as st

import jaxlens as jl

SETTINGS = settings(max_examples=40, deadline=None)

# Real numbers of every kind, including those the library refuses.
reals = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1.0, 1.5, math.pi, 1e30, 1e31, 5e-324, -1e300, 1e300]),
    st.floats(1.0, 1e30),  # the valid distances
    st.floats(0.0, math.pi),  # the valid angles
)
anything = st.one_of(
    reals,
    st.integers(-(10**40), 10**40),
    st.booleans(),
    st.complex_numbers(max_magnitude=1e6),
    st.text(max_size=4),
    st.sampled_from([None, [1.0, 2.0], "20", b"20", object()]),
    reals.map(lambda v: _float32(v)),
)


def _float32(v):
    with np.errstate(over="ignore"):  # 1e300 is inf in float32: refused as such
        return np.float32(v)


def _refused_by_name(error: Exception, *names: str) -> bool:
    return isinstance(error, ValueError | TypeError) and any(n in str(error) for n in names)


def _finite(*arrays) -> bool:
    return all(np.all(np.isfinite(np.asarray(a, float))) for a in arrays)


@SETTINGS
@given(anything, anything)
def test_trace_answers_finite_or_names_the_argument(alpha, distance):
    try:
        r = jl.trace(alpha, distance)
    except Exception as e:  # noqa: BLE001 - the assertion says which
        assert _refused_by_name(e, "alpha", "distance"), repr(e)
        return
    # and resolved: a ray runs out of its 10 windings only within ~e^-63 of the critical
    # angle (NaN alpha and D = 1e300 gave every ray "unresolved")
    assert _finite(r.phi, r.r_min) and not np.any(np.asarray(r.unresolved)), (alpha, distance)


@SETTINGS
@given(anything)
def test_ray_map_answers_finite_or_names_the_distance(distance):
    try:
        m = jl.RayMap.build(distance, knots=64)
    except Exception as e:  # noqa: BLE001
        assert _refused_by_name(e, "distance"), repr(e)
        return
    assert _finite(m.alpha_sh, m.phi, m.slope), (distance, m)


@SETTINGS
@given(anything, anything)
def test_weak_field_answers_finite_or_names_the_argument(alpha, distance):
    try:
        phi, bound = jl.weak_field_escape_angle(alpha, distance)
    except Exception as e:  # noqa: BLE001
        assert _refused_by_name(e, "alpha", "distance"), repr(e)
        return
    assert _finite(phi) and not np.any(np.isnan(np.asarray(bound))), (alpha, distance)


@SETTINGS
@given(anything, anything, st.sampled_from(["distance", "fov", "roll"]), anything)
def test_camera_answers_finite_or_names_the_argument(distance, fov, name, angle):
    try:
        cam = jl.Camera(distance, fov, 16, 12, **{name: angle} if name == "roll" else {})
    except Exception as e:  # noqa: BLE001
        assert _refused_by_name(e, "distance", "fov", "roll", "dtype"), repr(e)
        return
    assert _finite(cam.distance, cam.fov, cam.roll)


@SETTINGS
@given(anything, st.one_of(st.integers(-(10**40), 10**40), st.floats(), anything))
def test_camera_sides_are_whole_numbers_in_range(width, supersample):
    try:
        cam = jl.Camera(20.0, 1.0, width, 12, supersample=supersample)
    except Exception as e:  # noqa: BLE001
        assert _refused_by_name(e, "width", "supersample"), repr(e)
        return
    assert 1 <= cam.width <= jl._camera.MAX_SIDE and 1 <= cam.supersample <= 64


# ------------------------------------------------------------------------- under jit

ALPHAS = jnp.asarray([0.0, 0.3, 1.5, math.pi])
_trace = jax.jit(lambda a, d: jl.trace(ALPHAS.at[1].set(a), d))
_build = jax.jit(lambda d: jl.RayMap.build(d, knots=64))
_camera = jax.jit(lambda d, f: jl.trace(ALPHAS, jl.Camera(d, f, 16, 12).distance).phi)
_trace32 = jax.jit(lambda a, d: jl.trace(ALPHAS.astype(jnp.float32).at[1].set(a), d).phi)


def _run(f, *args):
    """`f(*args)` with its values checked at run time: the result, or the error."""
    try:
        return jax.block_until_ready(f(*args)), None
    except Exception as e:  # noqa: BLE001 - returned for the assertion
        return None, e


@SETTINGS
@given(reals, reals)
def test_trace_under_jit_answers_finite_or_names_the_argument(alpha, distance):
    r, error = _run(_trace, jnp.float64(alpha), jnp.float64(distance))
    if error is not None:
        assert "alpha must be" in str(error) or "distance must be" in str(error), repr(error)
    else:
        assert _finite(r.phi, r.r_min) and not np.any(np.asarray(r.unresolved)), (alpha, distance)


@SETTINGS
@given(reals, reals)
def test_float32_trace_under_jit_answers_finite_or_names_the_argument(alpha, distance):
    phi, error = _run(_trace32, _float32(alpha), _float32(distance))
    if error is not None:
        assert "alpha must be" in str(error) or "distance must be" in str(error), repr(error)
    else:
        assert _finite(phi), (alpha, distance)


@SETTINGS
@given(reals)
def test_ray_map_under_jit_answers_finite_or_names_the_distance(distance):
    m, error = _run(_build, jnp.float64(distance))
    if error is not None:
        assert "distance must be" in str(error), repr(error)
    else:
        assert _finite(m.alpha_sh, m.phi, m.slope), distance


@SETTINGS
@given(reals)
def test_camera_under_jit_is_checked_where_used(distance):
    phi, error = _run(_camera, jnp.float64(distance), jnp.float64(1.0))
    if error is not None:
        assert "distance must be" in str(error), repr(error)
    else:
        assert _finite(phi), distance
