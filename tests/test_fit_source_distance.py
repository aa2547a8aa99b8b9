"""The fit with the source at a finite distance behind the hole (`SourceDistance`): its
three ways (the radius in R_S; the distance behind the hole with the observer's
distance, which measures the mass; with the mass, which measures the observer's
distance), the model's ray map against the exact images, a ring rendered by the
renderer's sphere recovered, the units read from text and astropy Quantities in and out,
and `jaxlens fit --source-distance`."""

import argparse
import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl

W, H = 64, 48
D, R, FOV_DEG, SIGMA_DEG, FLOOR, NOISE = 20.0, 40.0, 60.0, 1.5, 0.1, 0.02
MASS = 4.3e6  # solar masses
KPC = 3.0856775814913673e19  # m


@pytest.fixture(scope="module")
def ring():
    """A ring of a star on the sphere R = 40 behind a hole seen from D = 20, rendered by
    the renderer's crossings of the sphere (8 x 8 samples a pixel), with noise."""
    cam = jl.Camera(D, math.radians(FOV_DEG), W, H, supersample=8)
    sky = jl.GaussianStar(math.radians(SIGMA_DEG), 0.8) + jl.Uniform(FLOOR)
    img = np.asarray(jax.jit(jl.render_array)(jl.Scene(cam, sky, source_distance=R)))[..., 0]
    return img + NOISE * np.random.default_rng(20).standard_normal(img.shape)


@pytest.fixture(scope="module")
def fitted(ring):
    """The ring fitted with the observer's distance and the source's distance behind the
    hole known (R = D x D_LS / D_OL follows the fitted D; the mass is measured)."""
    d_ol = D * float(jl.schwarzschild_radius_m(MASS))
    sd = jl.SourceDistance(behind=2.0 * d_ol, observer=d_ol)
    return jl.fit_ring(ring, supersample=3, source_distance=sd)


def test_the_models_ray_map_puts_the_rings_where_the_exact_images_are():
    # The fit's map of the crossing azimuth (escape_table's knots, finite_crossings'
    # values) solved for the primary ring (pi) and the first relativistic one (3 pi),
    # against point_source_images_at's images of a point exactly behind the hole: the
    # map's interpolation error at 4096 knots (1e-11 rad at infinity) and the solve's.
    from jaxlens._fit.table import source_table

    @jax.jit
    def rings(r):  # orders 0 and 1, and d alpha_E / dR by forward mode (the fit's)
        def primary(r):
            return source_table(D, r).solve(jnp.pi)

        a0, slope = jax.jvp(primary, (r,), (jnp.ones_like(r),))
        return a0, source_table(D, r).solve(3 * jnp.pi), slope

    @jax.jit
    def exact(r):
        axis = jnp.asarray([0.0, 1e-9, 1.0])
        return tuple(jl.point_source_images_at(axis, D, r, order=m).alpha for m in (0, 1))

    # Spheres inside the camera's radius (R = 10, 5: the crossing after the periapsis),
    # through it, beyond it.
    radii = jnp.asarray([10.0, 5.0, 20.0, 40.0, 1e4, R - 1e-3, R + 1e-3, jnp.inf])
    a0, a1, slope = (np.asarray(v) for v in jax.vmap(rings)(radii))
    # (The two images of each order of a source on the axis: the ring, twice.)
    e0, e1 = (np.asarray(v) for v in jax.vmap(exact)(radii[:5]))
    np.testing.assert_allclose(a0[:5, None] + 0 * e0, e0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(a1[:5, None] + 0 * e1, e1, rtol=0, atol=1e-9)
    # At infinity: the primary ring of the escape angle's own map.
    assert a0[7] == pytest.approx(float(jl.einstein_ring_angle(D)), abs=1e-12)
    # The primary ring at R = 40 is 16 % inside the one at infinity (0.296 against 0.353
    # rad): what a fit that ignores the distance puts down to D.
    assert a0[3] == pytest.approx(0.29605, abs=1e-5)
    # d alpha_E / dR against a central difference (step 1e-3: error ~1e-9 relative).
    assert slope[3] == pytest.approx((a0[6] - a0[5]) / 2e-3, rel=1e-6)


def test_a_ring_at_a_finite_distance_is_recovered_and_measures_the_mass(ring, fitted):
    f = fitted
    d_ol = D * float(jl.schwarzschild_radius_m(MASS))
    assert f.valid, f.summary()
    # D within 3 of its standard errors (measured: 20.07 +- 0.22, 0.29 of them; at
    # 96 x 72 with R fixed, 0.67).
    assert abs(f.distance - D) < 3 * f.distance_err
    assert abs(f.fov_deg - FOV_DEG) < 3 * f.fov_deg_err
    assert f.source_radius == pytest.approx(2.0 * f.distance, rel=1e-12)
    assert f.source_radius_err == pytest.approx(2.0 * f.distance_err, rel=1e-12)
    # The mass: D_OL / (D R_S_sun), its relative error D's.
    assert abs(f.mass - MASS) < 3 * f.mass_err
    assert f.mass_err / f.mass == pytest.approx(f.distance_err / f.distance, rel=1e-12)
    out = f.to_dict()
    assert out["mass_msun"] == f.mass and out["mass_msun_err"] == f.mass_err
    assert out["source_radius"] == pytest.approx(2.0 * out["distance"], rel=1e-12)
    assert "M_sun" in f.summary() and "source R" in f.summary()
    assert (f.observer_distance, f.observer_distance_err) == (d_ol, 0.0)  # as given
    held = dataclasses.replace(f, source_distance=jl.SourceDistance(radius=R))
    with pytest.raises(ValueError, match="does not measure the mass without the obs"):
        held.mass  # noqa: B018
    with pytest.raises(ValueError, match="does not measure the observer distance"):
        held.observer_distance  # noqa: B018

    # The other two ways at this fit's R: the radius in R_S, and the distance behind
    # the hole with the mass, hold the same sphere (so the same model), and the mass
    # way's observer distance is D x R_S(M).
    by_mass = jl.SourceDistance(behind=2.0 * d_ol, mass=MASS)
    assert by_mass.linear() == pytest.approx((0.0, 2.0 * D), rel=1e-12)
    g = dataclasses.replace(f, source_distance=by_mass)
    rs = float(jl.schwarzschild_radius_m(MASS))
    assert g.observer_distance == pytest.approx(f.distance * rs, rel=1e-12)
    assert abs(g.observer_distance - d_ol) < 3 * g.observer_distance_err
    # ... consistent with the mass way's own mass: D_OL / (D R_S_sun) = M.
    assert g.observer_distance / (f.distance * jl.RS_SUN_M) == pytest.approx(MASS, rel=1e-12)


def test_a_ring_at_a_finite_distance_fitted_as_if_at_infinity_is_far_off(ring, fitted):
    # The same image fitted with the source at infinity: its primary ring is wider at
    # a given D, so the fit settles nearer (measured: D = 12.00 +- 0.15, 52 standard
    # errors off; 91 at 96 x 72), with residuals at the noise (chi2/dof 0.998 both):
    # only the distance given tells them apart.
    f = jl.fit_ring(ring, supersample=3)
    assert f.converged
    assert abs(f.distance - D) > 20 * f.distance_err
    assert abs(f.distance - D) > 20 * fitted.distance_err
    assert f.distance < 0.75 * D


def test_a_ring_of_a_source_inside_the_cameras_radius_is_recovered():
    # D_LS = D_OL / 2 (R = 10 at D = 20): the star on the sphere, rendered with both of
    # each ray's crossings, and a uniform background far beyond it (at infinity); the
    # model reads the crossing after the periapsis. Measured: D = 20.50 +- 0.94 (0.53 of
    # its standard errors), chi2/dof 1.05.
    cam = jl.Camera(D, math.radians(FOV_DEG), W, H, supersample=8)
    render = jax.jit(jl.render_array)
    star = jl.GaussianStar(math.radians(SIGMA_DEG), 0.8)
    img = np.asarray(render(jl.Scene(cam, star, source_distance=10.0)))[..., 0]
    img = img + np.asarray(render(jl.Scene(cam, jl.Uniform(FLOOR))))[..., 0]
    img = img + NOISE * np.random.default_rng(20).standard_normal(img.shape)
    f = jl.fit_ring(img, supersample=3, source_distance=jl.SourceDistance(radius=10.0))
    assert f.valid, f.summary()
    assert abs(f.distance - D) < 3 * f.distance_err
    assert f.distance_err < 0.1 * D


def test_a_sphere_on_the_photon_sphere_is_refused_by_name(ring):
    # R = 1.5 R_S: light from behind the hole on it reaches the camera only inside the
    # shadow, so no ring relation at any distance; the refusal names the sphere and the
    # range the start searches.
    said = r"ring of a source on the sphere R = 0 D \+ 1.5 R_S \(the model holds R > 1.5, and "
    with pytest.raises(ValueError, match=said + "searches D from 1.9"):
        jl.fit_ring(ring, supersample=3, source_distance=jl.SourceDistance(radius=1.5))


def test_parse_length_accepts_units_and_refuses_others():
    kpc = jl.parse_length("8.5kpc")
    assert (kpc.value, kpc.unit, kpc.in_rs) == (8.5, "kpc", False)
    assert kpc.metres == pytest.approx(8.5 * KPC, rel=1e-15)
    for text, metres in (("3e20 m", 3e20), ("1 km", 1e3), ("1au", 149_597_870_700.0),
                         ("2 pc", 2 * KPC / 1e3), ("1Mpc", 1e3 * KPC),
                         ("1 ly", 9_460_730_472_580_800.0)):  # fmt: skip
        assert jl.parse_length(text).metres == pytest.approx(metres, rel=1e-15)
    rs = jl.parse_length("4e4Rs")
    assert rs.in_rs and rs.value == 4e4
    with pytest.raises(ValueError, match="needs the mass"):
        rs.metres  # noqa: B018
    for bad in ("8.5", "kpc", "8.5 parsec", "8.5KPC", "", "8.5 kpc kpc", "nan m", "inf m"):
        with pytest.raises(ValueError, match=r"--source-distance .* not a length.*m, km, au"):
            jl.parse_length(bad, name="--source-distance")
    for bad in ("0 m", "-1kpc", "1e400 m"):
        with pytest.raises(ValueError, match="positive, finite number"):
            jl.parse_length(bad)


def test_source_distance_takes_three_ways_and_refuses_the_rest():
    assert jl.SourceDistance(radius=100.0).linear() == (0.0, 100.0)
    sd = jl.SourceDistance(behind=8.5 * KPC, observer=8.5 * KPC)
    assert sd.follows_distance and sd.linear() == (1.0, 0.0)
    # The real lens of the README: R = D_LS / R_S(M), for M = 2.8e6 and D_LS = 8.5 kpc.
    sd = jl.SourceDistance(behind=8.5 * KPC, mass=2.8e6)
    r = 8.5 * KPC / (2.8e6 * jl.RS_SUN_M)
    assert sd.linear() == pytest.approx((0.0, r), rel=1e-15)
    for kw in ({}, {"radius": 10.0, "mass": 1.0}, {"behind": 1.0}, {"observer": 1.0, "mass": 1.0},
               {"behind": 1.0, "observer": 1.0, "mass": 1.0}):  # fmt: skip
        with pytest.raises(ValueError, match="not one of the three ways"):
            jl.SourceDistance(**kw)
    for kw, match in (
        ({"radius": 1.0}, "radius=1.0 must be finite and > 1"),
        ({"radius": math.inf}, "must be finite"),
        ({"behind": -1.0, "observer": 1.0}, "behind=-1.0 must be positive and finite"),
        ({"behind": 1.0, "observer": "far"}, "observer='far' is not a number"),
        ({"behind": 1e3, "mass": 1.0}, "0.338.* R_S for mass=1.0: .* outside the horizon"),
    ):
        with pytest.raises(ValueError, match=match):
            jl.SourceDistance(**kw)
    scene = jl.Scene(jl.Camera(D, 1.0, 8, 8), jl.GaussianStar(0.01) + jl.Uniform(0.0))
    with pytest.raises(ValueError, match="must be a SourceDistance"):
        jl.fit(scene, np.zeros((H, W)), source_distance=40.0)


def test_a_model_scenes_own_source_distance_is_a_fixed_radius():
    from jaxlens._fit.general import _checked_source

    sky = jl.GaussianStar(0.01) + jl.Uniform(0.0)
    scene = jl.Scene(jl.Camera(D, 1.0, 8, 8), sky, source_distance=R)
    assert _checked_source(scene, None) == jl.SourceDistance(radius=R)
    given = jl.SourceDistance(radius=2 * R)
    assert _checked_source(scene, given) is given  # the argument wins
    assert _checked_source(jl.Scene(jl.Camera(D, 1.0, 8, 8), sky), None) is None


def test_astropy_quantities_in_and_out(fitted):
    u = pytest.importorskip("astropy.units")
    d_ol = D * float(jl.schwarzschild_radius_m(MASS)) * u.m
    sd = jl.SourceDistance(behind=(2.0 * d_ol).to(u.kpc), observer=d_ol.to(u.pc))
    assert sd.quantities and sd.linear() == pytest.approx((2.0, 0.0), rel=1e-12)
    f = dataclasses.replace(fitted, source_distance=sd)
    assert f.mass.unit == u.M_sun and f.mass_err.unit == u.M_sun
    assert f.mass.value == pytest.approx(fitted.mass, rel=1e-12)
    by_mass = jl.SourceDistance(behind=(2.0 * d_ol).to(u.au), mass=MASS * u.M_sun.to(u.kg) * u.kg)
    g = dataclasses.replace(fitted, source_distance=by_mass)
    assert g.observer_distance.unit == u.m
    assert g.observer_distance.to_value(u.m) == pytest.approx(
        fitted.distance * float(jl.schwarzschild_radius_m(MASS)), rel=1e-9
    )
    with pytest.raises(ValueError, match="is not a length"):
        jl.SourceDistance(behind=1.0 * u.s, observer=1.0)
    with pytest.raises(ValueError, match="is not a mass"):
        jl.SourceDistance(behind=1.0 * u.kpc, mass=1.0 * u.m)
    with pytest.raises(ValueError, match="is in units of R_S"):
        jl.SourceDistance(radius=40.0 * u.m)


def test_cli_source_distance(tmp_path, capsys, fitted):
    from jaxlens import _cli_fit, cli

    # Refused before any image is read: the flag, the value and what is valid.
    path = str(tmp_path / "ring.png")
    for argv, said in (
        (["--source-distance", "8.5parsec"], "--source-distance '8.5parsec' is not a length: "
         "expected a positive number and a unit, one of m, km, au, pc, kpc, Mpc, ly, Rs"),
        (["--source-distance", "8.5kpc"], "'8.5kpc' is a distance behind the hole: give the "
         "observer's distance (--distance-m)"),
        (["--source-distance", "1e-30kpc", "--mass", "1e6"], "outside the horizon"),
    ):  # fmt: skip
        assert cli.main(["fit", path, *argv]) == 2
        assert said in capsys.readouterr().err, argv
    # Each way the flag combines with the mass and distance flags.
    d_ol = D * float(jl.schwarzschild_radius_m(MASS))
    assert _cli_fit._source("40Rs", None, None) == jl.SourceDistance(radius=40.0)
    assert _cli_fit._source("40Rs", MASS, None) == jl.SourceDistance(radius=40.0)
    got = _cli_fit._source(f"{2 * d_ol / KPC!r}kpc", None, d_ol)
    assert got.linear() == pytest.approx((2.0, 0.0), rel=1e-12)
    got = _cli_fit._source(f"{2 * d_ol!r} m", MASS, None)
    assert got.linear() == pytest.approx((0.0, 2 * D), rel=1e-12)
    # The report: the mass with its error and unit (text), the same numbers (JSON).
    args = argparse.Namespace(json=False, images=[path])
    text = _cli_fit._report(args, path, fitted, None, d_ol)
    assert f"mass         = {fitted.mass:.6g} +- {fitted.mass_err:.2g} M_sun" in text
    assert text.count("mass ") == 1  # not again from --distance-m
    out = json.loads(_cli_fit._report(argparse.Namespace(json=True, images=[path]), path,
                                      fitted, None, d_ol))  # fmt: skip
    assert out["mass_msun"] == fitted.mass and out["distance_m"] == d_ol


@pytest.mark.benchmark  # one more fit (~45 s on 2 cores): run by `make test-slow`
def test_cli_fit_with_a_source_distance_measures_the_mass(tmp_path, capsys, ring, monkeypatch):
    from jaxlens import cli

    monkeypatch.setenv("JAXLENS_CACHE_DIR", "")  # no persistent cache from a test
    path = jl.write_image(tmp_path / "ring.exr", ring, sampling="area")
    d_ol = D * float(jl.schwarzschild_radius_m(MASS))
    argv = ["fit", str(path), "--source-distance", f"{2.0 * d_ol / KPC!r}kpc",
            "--distance-m", repr(d_ol), "--star-sigma-deg", str(SIGMA_DEG)]  # fmt: skip
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "mass " in text and "M_sun" in text and "source R" in text
    assert cli.main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["valid"] is True, out["message"]
    assert abs(out["distance"] - D) < 3 * out["distance_err"]
    assert abs(out["mass_msun"] - MASS) < 3 * out["mass_msun_err"]
    assert out["distance_m"] == pytest.approx(d_ol, rel=1e-12)
    assert out["source_radius"] == pytest.approx(2.0 * out["distance"], rel=1e-12)
    assert out["source_behind_m"] == pytest.approx(2.0 * d_ol, rel=1e-12)
