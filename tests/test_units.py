"""astropy Quantities as arguments: angles converted to radians, dimensionless lengths
read as R_S, physical lengths converted where the hole's mass is known and refused with
the fix elsewhere, masses converted to solar masses; a Quantity of another dimension,
or one given where jaxlens reads no unit, refused. Never a unit dropped silently.

Tolerances: a conversion by astropy is one multiplication by a power of ten or by
pi/180 (float64: within 1e-15 relative, asserted at 1e-12); float32 results (the
default without x64 is float64 here: conftest enables x64) are compared in their dtype.
"""

import math
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxlens as jl

u = pytest.importorskip("astropy.units")

RS_SUN_M = jl.RS_SUN_M  # m, the Schwarzschild radius of one (nominal) solar mass: 2953.25
REL = 1e-12  # a unit conversion's rounding, float64
ANGLES = [(2.0 * u.deg, math.radians(2.0)), (90.0 * u.arcsec, math.radians(90.0 / 3600.0)),
          (0.3 * u.rad, 0.3)]  # fmt: skip
ANGLE_IDS = ["deg", "arcsec", "rad"]


def close(got, want):
    np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=REL, atol=0.0)


# ------------------------------------------------------------------ angles


@pytest.mark.parametrize("q, rad", ANGLES, ids=ANGLE_IDS)
def test_camera_angles_converted(q, rad):
    """The issue's case: Camera(20, 2 deg) has a 2-degree field of view, not 2 radians;
    every angle field of the camera likewise."""
    c = jl.Camera(20.0, q, 32, 24, yaw=q, pitch=q, roll=q, azimuth=q, elevation=q)
    for name in ("fov", "yaw", "pitch", "roll", "azimuth", "elevation"):
        close(getattr(c, name), rad)
    close(jl.zoom(c, [q.value, 2 * q.value] * q.unit).fov, [rad, 2 * rad])
    close(jl.pan(c, [q, q]).yaw, [rad, rad])
    close(jl.orbit(c, [q]).azimuth, [rad])


@pytest.mark.parametrize("q, rad", ANGLES, ids=ANGLE_IDS)
def test_sky_angles_converted(q, rad):
    """Star widths and positions, sky orientations and a plane image's width."""
    star = jl.GaussianStar(q, lon=q, lat=-q)
    close(star.sigma, rad)
    close(star.direction, np.asarray(jl.direction_from_angles(rad, -rad)))
    close(jl.direction_from_angles(q, q), np.asarray(jl.direction_from_angles(rad, rad)))
    close(jl.StarField(np.eye(3), q).sigma, [rad] * 3)
    both = np.array([rad, rad]), np.array([rad, -rad])
    close(jl.StarField.from_angles([q, q], [q, -q], 0.01).directions,
          np.asarray(jl.direction_from_angles(*both)))  # fmt: skip
    close(jl.BlackbodyStars.from_angles([q, q], [q, -q], 0.01).directions,
          np.asarray(jl.direction_from_angles(*both)))  # fmt: skip
    close(jl.BlackbodyStars(np.eye(3), q).sigma, [rad] * 3)
    image = np.ones((4, 8, 3))
    for sky in (jl.Checker(yaw=q, pitch=q, roll=q), jl.Panorama(image, yaw=q, pitch=q, roll=q),
                jl.PlaneImage(image, q, yaw=q, pitch=q, roll=q),
                jl.Rotated(jl.Uniform(1.0), yaw=q, pitch=q, roll=q)):  # fmt: skip
        for name in ("yaw", "pitch", "roll"):
            close(getattr(sky, name), rad)
    close(jl.PlaneImage(image, q).width, rad)
    close(jl.rotation_matrix(q, q, q), np.asarray(jl.rotation_matrix(rad, rad, rad)))


@pytest.mark.parametrize("q, rad", ANGLES, ids=ANGLE_IDS)
def test_disk_and_motion_angles_converted(q, rad):
    disk = jl.Disk(3.0, 12.0, q, position_angle=q)
    close(disk.inclination, rad)
    close(disk.position_angle, rad)
    close(jl.CircularOrbit(q).angle, rad)


@pytest.mark.parametrize("q, rad", ANGLES, ids=ANGLE_IDS)
def test_ray_angles_converted(q, rad):
    """The local angle of `trace`, the ray map, the closed forms and the weak field."""
    close(jl.trace(q, 20.0).phi, float(jl.trace(rad, 20.0).phi))
    m = jl.RayMap.build(20.0)
    close(m(q).phi, float(m(rad).phi))
    close(m.escape_angle(q), float(m.escape_angle(rad)))
    close(jl.impact_parameter(q, 20.0), float(jl.impact_parameter(rad, 20.0)))
    close(jl.radius_crossings(q, 20.0, 40.0).first,
          float(jl.radius_crossings(rad, 20.0, 40.0).first))  # fmt: skip
    close(jl.weak_field_escape_angle(q, 1e4)[0], float(jl.weak_field_escape_angle(rad, 1e4)[0]))
    close(jl.can_reach(q, 20.0, 12.0), bool(jl.can_reach(rad, 20.0, 12.0)))


def test_fit_model_angles_converted():
    """`ring_image`'s field of view and star width."""
    plain = jl.ring_image(20.0, math.radians(60.0), 16, 12, sigma=math.radians(1.5))
    got = jl.ring_image(20.0, 60.0 * u.deg, 16, 12, sigma=90.0 * u.arcmin)
    np.testing.assert_allclose(got, plain, rtol=1e-12, atol=1e-15)


def test_dimensionless_angle_is_radians():
    """A dimensionless Quantity is radians (astropy's `dimensionless_angles`), its
    scale applied: 50 % is 0.5 rad."""
    close(jl.Camera(20.0, 0.5 * u.dimensionless_unscaled, 32, 24).fov, 0.5)
    close(jl.Camera(20.0, 50.0 * u.percent, 32, 24).fov, 0.5)


# ------------------------------------------------------------------ lengths


def test_dimensionless_length_is_rs():
    """A dimensionless Quantity is a number in R_S, as a plain number is (its scale
    applied: 2000 % is 20)."""
    one = u.dimensionless_unscaled
    close(jl.Camera(2000.0 * u.percent, 1.0, 32, 24).distance, 20.0)
    close(jl.Camera(20.0 * one, 1.0, 32, 24).distance, 20.0)
    close(jl.Disk(3.0 * one, 12.0 * one).r_out, 12.0)
    close(jl.Scene(jl.Camera(20.0, 1.0, 32, 24), jl.Uniform(1.0), source_distance=40.0 * one)
          .source_distance, 40.0)  # fmt: skip
    close(jl.shadow_angle(20.0 * one), float(jl.shadow_angle(20.0)))
    close(jl.trace(0.3, 20.0 * one).phi, float(jl.trace(0.3, 20.0).phi))


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda q: jl.Camera(q, 1.0, 32, 24), "distance"),
        (lambda q: jl.approach(jl.Camera(20.0, 1.0, 32, 24), [q.value] * q.unit), "distance"),
        (lambda q: jl.Disk(q, 12.0), "r_in"),
        (lambda q: jl.Disk(3.0, q), "r_out"),
        (lambda q: jl.Scene(jl.Camera(20.0, 1.0, 8, 8), jl.Uniform(1.0), source_distance=q),
         "source_distance"),
        (lambda q: jl.Scene(jl.Camera(20.0, 1.0, 8, 8), jl.Uniform(1.0), source_plane=q),
         "source_plane"),
        (lambda q: jl.trace(0.3, q), "distance"),
        (lambda q: jl.RayMap.build(q), "distance"),
        (lambda q: jl.shadow_angle(q), "distance"),
        (lambda q: jl.radius_crossings(0.3, 20.0, q), "radius"),
        (lambda q: jl.plane_crossings(0.3, 20.0, q), "plane_distance"),
        (lambda q: jl.periapsis(q), "b"),
        (lambda q: jl.point_source_images_at(np.array([0.0, 0.0, 1.0]), q), "distance"),
        (lambda q: jl.static_blueshift(q), "distance"),
        (lambda q: jl.einstein_ring_angle(q), "distance"),
        (lambda q: jl.ring_image(q, 1.0, 8, 8, sigma=0.01), "distance"),
    ],
)  # fmt: skip
def test_length_without_mass_refused(call, name):
    """20 km is not 20 R_S: refused, naming the argument and the two ways to give it."""
    with pytest.raises(ValueError, match=rf"{name}=\[?20\.0?\]? km is a length in km") as e:
        call(20.0 * u.km)
    assert "as a plain number" in str(e.value)
    assert f"jaxlens.schwarzschild_radii({name}, mass)" in str(e.value)


def test_length_converted_where_mass_known():
    """`schwarzschild_radii`, and the fit's conversions between R_S and metres."""
    close(jl.schwarzschild_radii(20.0 * u.km, 1.0), 20e3 / RS_SUN_M)
    close(jl.schwarzschild_radii(20.0 * u.km, 1.0 * u.M_sun), 20e3 / RS_SUN_M)
    close(jl.schwarzschild_radii(8.0 * u.kpc, 4.3e6), 8.0 * u.kpc.to(u.m) / (4.3e6 * RS_SUN_M))
    kg = (2.0 * u.M_sun).to(u.kg)
    close(jl.schwarzschild_radii([1.0, 2.0] * u.km, kg), np.array([1e3, 2e3]) / (2 * RS_SUN_M))
    close(jl.schwarzschild_radii(5906.5, 1.0), 5906.5 / RS_SUN_M)  # a plain number: metres
    close(jl.schwarzschild_radius_m(1.0 * u.M_sun), RS_SUN_M)
    close(jl.distance_in_metres(20.0, 2.0 * u.M_sun), 40.0 * RS_SUN_M)
    close(jl.mass_from_distance(20.0, 40.0 * RS_SUN_M / 1e3 * u.km), 2.0)
    # The camera's distance in a unit of length is converted by the helper, then taken.
    d = jl.schwarzschild_radii(59.065 * u.km, 1.0 * u.M_sun)
    close(jl.Camera(d, 1.0, 8, 8).distance, 59.065e3 / RS_SUN_M)


def test_delay_in_seconds_takes_a_mass_quantity():
    images = jl.point_source_images_at(np.array([0.1, 0.0, 1.0]), 20.0, 40.0)
    want = np.asarray(images.delay_seconds(4.3e6))
    close(images.delay_seconds(4.3e6 * u.M_sun), want)
    close(images.delay_seconds((4.3e6 * u.M_sun).to(u.kg)), want)


# ------------------------------------------------------------------ wrong dimension


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: jl.Camera(20.0, 2.0 * u.s, 32, 24), r"fov=2.0 s is not an angle \(time\)"),
        (lambda: jl.GaussianStar(1.0 * u.m), r"sigma=1.0 m is not an angle \(length\)"),
        (lambda: jl.trace(1.0 * u.kg, 20.0), r"alpha=1.0 kg is not an angle \(mass\)"),
        (lambda: jl.Disk(3.0 * u.deg, 12.0), r"r_in=3.0 deg is not a length \(angle\)"),
        (lambda: jl.schwarzschild_radii(1.0 * u.km, 1.0 * u.m), r"mass=1.0 m is not a mass"),
        (lambda: jl.schwarzschild_radii(1.0 * u.s, 1.0), r"length=1.0 s is not a length"),
        (lambda: jl.mass_from_distance(20.0, 1.0 * u.s), r"distance_m=1.0 s is not a length"),
    ],
    ids=["fov-time", "sigma-length", "alpha-mass", "r_in-angle", "mass-length",
         "length-time", "metres-time"],
)  # fmt: skip
def test_wrong_dimension_refused(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda q: jl.GaussianStar(0.01, q), "brightness"),
        (lambda q: jl.Uniform(q), "level"),
        (lambda q: jl.Disk(temperature=q), "temperature"),
        (lambda q: jl.blackbody_color(q), "temperature"),
        (lambda q: jl.planck(q, 5800.0), "wavelength"),
        (lambda q: jl.doppler_factor(1.0, q), "v"),
        (lambda q: jl.lorentz_factor(q), "v"),
        (lambda q: jl.GaussianPSF(q), "sigma_px"),
        (lambda q: jl.gaussian_otf((8, 8), q), "sigma_px"),
    ],
)
def test_quantity_without_a_unit_refused(call, name):
    """An argument jaxlens reads no unit of (a radiance, a temperature, a wavelength, a
    speed in units of c, a PSF width in pixels) refuses a Quantity instead of dropping
    its unit."""
    with pytest.raises(ValueError, match=rf"{name}=.* is an astropy Quantity"):
        call(3.0 * u.Jy)


# ------------------------------------------------------------------ the fit


@pytest.mark.slow  # ~10 s idle (25 s at load 5): one fit's compile, its only cost
def test_fit_init_converted():
    """`fit`'s `init` values in R_S and radians: the held ones are the fit's values."""
    img = np.asarray(jl.ring_image(20.0, math.radians(60.0), 32, 24, sigma=math.radians(1.5),
                                   floor=0.1, supersample=3))  # fmt: skip
    scene = jl.Scene(jl.Camera(15.0, 1.0, 32, 24), jl.GaussianStar(0.02) + jl.Uniform(0.0))
    init = {"distance": 20.0 * u.dimensionless_unscaled, "fov": 60.0 * u.deg,
            "sigma": 90.0 * u.arcmin}  # fmt: skip
    fit = jl.fit(scene, img, free=("floor",), init=init, max_steps=1)
    close(fit.values["distance"], 20.0)
    close(fit.values["fov"], math.radians(60.0))
    close(fit.values["sigma"], math.radians(1.5))


def test_fit_arguments_refused():
    """A length in km for the fit's distance, a time for the star's width: refused
    before the fit starts, naming the argument."""
    img = np.asarray(jl.ring_image(20.0, math.radians(60.0), 32, 24, sigma=math.radians(1.5),
                                   floor=0.1, supersample=3))  # fmt: skip
    with pytest.raises(ValueError, match=r"init\['distance'\]=20.0 km is a length in km"):
        jl.fit_ring(img, init={"distance": 20.0 * u.km, "fov": 1.0})
    with pytest.raises(ValueError, match=r"init\['fov'\]=1.0 s is not an angle"):
        jl.fit_ring(img, init={"distance": 20.0, "fov": 1.0 * u.s})
    with pytest.raises(ValueError, match=r"init\['floor'\]=1.0 Jy is an astropy Quantity"):
        jl.fit_ring(img, init={"floor": 1.0 * u.Jy})
    with pytest.raises(ValueError, match=r"star_sigma=1.0 s is not an angle"):
        jl.fit_ring(img, star_sigma=1.0 * u.s)


# ------------------------------------------------------------------ under jit


def test_quantities_under_jit():
    """A Quantity the traced function holds (not one of the jitted function's own
    arguments, which JAX turns into plain arrays before jaxlens sees them) is converted
    while tracing, or refused then: the same values and errors as eagerly."""
    want = float(jl.trace(math.radians(10.0), 20.0).phi)
    close(jax.jit(lambda: jl.trace(10.0 * u.deg, 20.0).phi)(), want)
    close(jax.jit(lambda d: jl.trace(10.0 * u.deg, d).phi)(20.0), want)
    m = jl.RayMap.build(20.0)
    close(jax.jit(lambda m: m(10.0 * u.deg).phi)(m), want)
    with pytest.raises(ValueError, match=r"distance=20.0 km is a length in km"):
        jax.jit(lambda a: jl.trace(a, 20.0 * u.km).phi)(0.3)
    with pytest.raises(ValueError, match=r"alpha=1.0 s is not an angle"):
        jax.jit(lambda d: jl.trace(1.0 * u.s, d).phi)(20.0)
    cam = jax.jit(lambda d: jl.Camera(d, 2.0 * u.deg, 8, 8).fov)(20.0)
    close(cam, math.radians(2.0))


# ------------------------------------------------------------------ no astropy import


def test_plain_numbers_do_not_import_astropy():
    """astropy is optional: jaxlens never imports it to read a plain number."""
    code = ("import sys, jaxlens as jl; jl.Camera(20.0, 1.0, 8, 8); jl.trace(0.3, 20.0); "
            "jl.Disk(3.0, 12.0); jl.GaussianStar(0.01, lon=0.1); "
            "assert 'astropy' not in sys.modules, 'astropy imported'")  # fmt: skip
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]
