"""Scene values outside their range are refused by name, eagerly and under `jit`.

Each sky, motion and disk declares its fields' ranges (`limits`); `render_array` checks
them (and the camera's angles) once a call: a `ValueError` or `TypeError` naming the
field when the value is known, an error at run time under `jit`, never a NaN, inf or
black image. The property tests give every field arbitrary numbers (NaN, inf, huge,
tiny, negative, integer, complex) and ask for exactly that.

Each group of fields is one program, compiled once (the field values are its traced
arguments) and reused for every example.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import jaxlens as jl

W, H = 8, 6  # tiny images: every case below is a few milliseconds once compiled
PANO = np.linspace(0.1, 1.0, 4 * 8 * 3).reshape(4, 8, 3)
# Every camera is at D = 20: its ray map built once, outside the programs (which then
# compile in a third of the time).
RAY_MAP = jl.RayMap.build(20.0, accuracy=1e-8, iterations=6)


def _camera(v, dtype=None):
    angles = {k: v[k] for k in ("yaw", "pitch", "roll", "azimuth", "elevation") if k in v}
    return jl.Camera(20.0, 1.0, W, H, **angles, dtype=dtype)


def _stars(v, dtype=None):
    cam = _camera(v, dtype)
    star = jl.GaussianStar(v["sigma"], v["brightness"], color=(1.0, v["color"], 1.0),
                           lon=v.get("lon", 0.0), lat=0.0)  # fmt: skip
    return jl.render_array(cam, star + jl.Uniform(v["level"]), ray_map=RAY_MAP)


def _stars32(v):
    # float32 pixels from float64 values: a value float32 rounds to inf, or a width to
    # 0, is refused as well.
    return _stars(v, np.float32)


def _many(v):
    cam = jl.Camera(20.0, 1.0, W, H)
    d = [[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]
    field = jl.StarField(d, v["field_sigma"], v["field_brightness"])
    bb = jl.BlackbodyStars(d, v["bb_sigma"], v["bb_brightness"], v["bb_temperature"])
    scene = jl.Scene(cam, field + bb, redshift=jl.Redshift("spectral"))
    return jl.render_array(scene, ray_map=RAY_MAP)


def _textured(v):
    cam = jl.Camera(20.0, 1.0, W, H)
    sky = (
        jl.Checker(4, 2, brightness=v["checker_brightness"], yaw=v["checker_yaw"])
        + jl.Panorama(PANO, brightness=v["panorama_brightness"], pitch=v["panorama_pitch"])
        + jl.PlaneImage(
            PANO, v["plane_width"], brightness=v["plane_brightness"], roll=v["plane_roll"]
        )  # fmt: skip
        + jl.Rotated(jl.Uniform(0.1), yaw=v["rotated_yaw"])
    )
    return jl.render_array(cam, sky, ray_map=RAY_MAP)


def _disk(v):
    cam = jl.Camera(20.0, 1.0, W, H)
    disk = jl.Disk(3.0, 12.0, v["inclination"], position_angle=v["position_angle"],
                   temperature=v["disk_temperature"], brightness=v["disk_brightness"],
                   crossings=1, steps=4)  # fmt: skip
    scene = jl.Scene(cam, jl.Uniform(0.1), motion=jl.CircularOrbit(v["angle"]), disk=disk)
    return jl.render_array(scene, ray_map=RAY_MAP)


GROUPS = {
    _stars: dict(yaw=0.0, pitch=0.0, roll=0.0, azimuth=0.0, elevation=0.0, sigma=0.05,
                 brightness=1.0, color=1.0, lon=0.0, level=0.1),
    _stars32: dict(pitch=0.0, sigma=0.05, brightness=1.0, color=1.0, level=0.1),
    _many: dict(field_sigma=0.05, field_brightness=1.0, bb_sigma=0.05, bb_brightness=1.0,
                bb_temperature=5800.0),
    _textured: dict(checker_brightness=1.0, checker_yaw=0.0, panorama_brightness=1.0,
                    panorama_pitch=0.0, plane_width=1.0, plane_brightness=1.0,
                    plane_roll=0.0, rotated_yaw=0.0),
    _disk: dict(inclination=1.2, position_angle=0.0, disk_temperature=8000.0,
                disk_brightness=1.0, angle=0.0),
}  # fmt: skip
# The names a field goes by in messages, where the test's key is not one of them: its
# constructor's argument and the field it sets (lon/lat set the direction).
NAMES = {"lon": ("lon", "direction"), "position_angle": ("position_angle",)} | {
    k: (k.split("_", 1)[1],) for g in GROUPS.values() for k in g if "_" in k
}
JITTED = {f: eqx.filter_jit(f) for f in GROUPS}


def _named(field) -> tuple[str, ...]:
    return NAMES.get(field, (field,))


def _traced(value):
    """A value as the jitted programs' argument: an array (a Python number would be a
    static argument of `filter_jit`, and compile anew for each value); integers as
    float64, so that the program compiles once (they are tried as integers eagerly)."""
    a = np.asarray(value)
    return a.astype(np.float64) if a.dtype.kind in "iu" else a


def _outcome(f, values, jitted):
    """The image, or the exception, of group `f` at `values`."""
    try:
        if jitted:
            values = {k: _traced(v) for k, v in values.items()}
        img = (JITTED[f] if jitted else f)(values)
        return np.asarray(jax.block_until_ready(img))
    except Exception as e:  # noqa: BLE001 - each is checked by the caller
        return e


def _check(f, field, value, jitted):
    values = dict(GROUPS[f], **{field: value})
    out = _outcome(f, values, jitted)
    if isinstance(out, np.ndarray):
        assert out.shape == (H, W, 3), (field, value, jitted)
        assert np.all(np.isfinite(out)), (field, value, jitted, out.dtype)
    else:
        # A ValueError or TypeError eagerly; under jit the same, or equinox's run-time
        # error (its message the check's). Either names the field.
        assert isinstance(out, ValueError | TypeError) or "EquinoxRuntimeError" in repr(
            type(out)
        ), (field, value, jitted, out)
        assert any(n in str(out) for n in _named(field)), (field, value, jitted, str(out)[:500])


numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-1e-300, 1e-300),
    st.sampled_from([0.0, -0.0, 1e30, -1e30, 1e31, 1e300, 5e-324, 3.5e38]),
    st.integers(-(2**63), 2**63 - 1),
    st.complex_numbers(max_magnitude=1e3),
)
SETTINGS = settings(max_examples=30, deadline=None)


@pytest.mark.parametrize("jitted", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("group", list(GROUPS), ids=lambda f: f.__name__[1:])
def test_every_field_renders_finite_or_is_refused_by_name(group, jitted):
    fields = sorted(GROUPS[group])

    @SETTINGS
    @given(st.sampled_from(fields), numbers)
    def run(field, value):
        _check(group, field, value, jitted)

    run()


@pytest.mark.parametrize(
    "group,field,value",
    [
        (_stars, "yaw", math.nan),
        (_stars, "sigma", 0.0),
        (_stars, "sigma", -0.05),
        (_stars, "sigma", math.nan),
        (_stars, "brightness", math.nan),
        (_stars, "level", math.inf),
        (_many, "bb_temperature", 0.0),
        (_disk, "inclination", math.nan),
        (_disk, "disk_temperature", 0.0),
        (_disk, "disk_temperature", -5.0),
        (_disk, "disk_brightness", -1.0),
    ],
)
def test_the_values_of_the_report_raise_under_jit(group, field, value):
    # Each gave a NaN, inf, black or negative image under jit, without an error.
    name = _named(field)[-1]
    with pytest.raises(Exception, match=rf"{name} \(\w+\) must be|camera yaw must"):
        values = dict(GROUPS[group], **{field: value})
        jax.block_until_ready(JITTED[group]({k: _traced(v) for k, v in values.items()}))


def test_good_values_give_the_same_image_eagerly_and_under_jit():
    for f, values in GROUPS.items():
        eager = np.asarray(f(values))
        assert np.all(np.isfinite(eager)) and eager.max() > 0, f.__name__
        # The same kernel, with its checks (identities on the values) or without: the
        # two programs may fuse differently, so agreement to rounding (100 ulps).
        jitted = JITTED[f]({k: _traced(v) for k, v in values.items()})
        tol = 100 * np.finfo(eager.dtype).eps
        np.testing.assert_allclose(np.asarray(jitted), eager, rtol=tol, atol=tol * eager.max())


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda: jl.GaussianStar(0.0), r"sigma=0.0 must be finite and in \(0, pi\)"),
        (lambda: jl.GaussianStar(-0.1), r"sigma=-0.1 must be"),
        (lambda: jl.GaussianStar(0.1, math.nan), r"brightness=nan must be finite"),
        (lambda: jl.Uniform(math.inf), r"level=inf must be finite"),
        (lambda: jl.Disk(inclination=math.nan), r"inclination=nan must be finite"),
        (lambda: jl.Disk(temperature=0.5), r"temperature=0.5 must be finite and >= 1 \(K\)"),
        (lambda: jl.Disk(brightness=-1.0), r"brightness=-1.0 must be in \[0, 1e30\]"),
        (lambda: jl.CircularOrbit(math.inf), r"angle=inf must be finite \(radians\)"),
        (lambda: jl.StarField([[0.0, 0.0, 0.0]], 0.1), r"directions: row 0 = \[0.0, 0.0, 0.0\]"),
        (lambda: jl.Checker(brightness=-2.0), r"brightness=-2.0 must be in \[0, 1e30\]"),
        (lambda: jl.DefaultSky(math.nan), r"brightness=nan must be in \[0, 1e30\]"),
        (lambda: jl.Uniform(1.0 + 2.0j), r"level=\(1\+2j\) must be real numbers"),
    ],
)
def test_bad_values_are_refused_when_the_part_is_built(make, match):
    with pytest.raises((ValueError, TypeError), match=match):
        make()


def test_a_value_set_after_building_is_refused_eagerly_with_its_value():
    # eqx.tree_at skips the constructor's checks: render_array's own check names it.
    sky = jl.GaussianStar(0.05) + jl.Uniform(0.1)
    bad = eqx.tree_at(lambda s: s.parts[0].sigma, sky, jnp.asarray(-1.0))
    cam = jl.Camera(20.0, 1.0, W, H)
    msg = r"sky.parts\[0\].sigma \(GaussianStar\) must be finite and in \(0, pi\) .*got -1.0"
    with pytest.raises(ValueError, match=msg):
        jl.render_array(cam, bad)
    with pytest.raises(ValueError, match=msg):
        jl.render(cam, bad)


@pytest.mark.parametrize("dtype", [np.float16, jnp.bfloat16, np.int32, np.complex64])
def test_pixel_dtypes_other_than_float32_and_float64_are_refused(dtype):
    # render(dtype=float16) gave an all-NaN image and a RuntimeWarning.
    cam, sky = jl.Camera(20.0, 1.0, W, H), jl.Uniform(0.1)
    name = np.dtype(dtype).name
    with pytest.raises(ValueError, match=rf"dtype={name} is not supported: .*float32 or float64"):
        jl.render(cam, sky, dtype=dtype)


def test_float32_pixels_refuse_what_float32_cannot_hold():
    # A float64 brightness of 1e300 is finite, but not in a float32 render: refused,
    # where it gave inf pixels.
    cam = jl.Camera(20.0, 1.0, W, H, dtype=np.float32)
    sky = eqx.tree_at(lambda s: s.level, jl.Uniform(0.1), jnp.asarray(1e300))
    with pytest.raises(ValueError, match=r"sky.level \(Uniform\) must be finite"):
        jl.render(cam, sky)
    f = eqx.filter_jit(
        lambda s: jl.render_array(cam, jl.GaussianStar(s) + jl.Uniform(0.1), ray_map=RAY_MAP)
    )
    assert np.all(np.isfinite(np.asarray(f(jnp.asarray(0.05, jnp.float32)))))
    with pytest.raises(Exception, match=r"sigma \(GaussianStar\) must be"):
        jax.block_until_ready(f(jnp.asarray(1e-50, jnp.float64)))  # 0 in float32
