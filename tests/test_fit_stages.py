"""The fit's stages on their own, without compiling the solver: the noise models and
their goodness-of-fit statistic, the causes a failed test names, the choice between an
untagged file's decodings, what `look` finds in an image."""

import dataclasses
import math

import numpy as np
import pytest
import scipy.ndimage

import jaxlens as jl
from jaxlens._fit import diagnose, general, start
from jaxlens._fit.noise import (
    GOODNESS_SIGMAS,
    as_noise,
    clipping_bounds,
    noise_level,
    noise_level_spread,
)


def _ring(h=96, w=128, radius=30.0, width=2.0, floor=0.05, peak=0.8):
    y, x = np.mgrid[0:h, 0:w]
    rho = np.hypot(x + 0.5 - 0.5 * w, 0.5 * h - (y + 0.5))
    return floor + peak * np.exp(-0.5 * ((rho - radius) / width) ** 2) * (rho > 12.0)


def test_noise_level_is_the_noise_and_its_spread_its_scatter():
    rng = np.random.default_rng(0)
    levels = [noise_level(rng.normal(0.0, 0.02, (120, 160))) for _ in range(60)]
    spread = noise_level_spread(np.zeros((120, 160)))
    assert np.mean(levels) == pytest.approx(0.02, rel=0.01)
    # The stated relative spread is the scatter's to within a third.
    assert np.std(levels) / 0.02 == pytest.approx(spread, rel=0.35)


def test_noise_level_ignores_nan_pixels_and_the_ring():
    rng = np.random.default_rng(1)
    img = _ring() + rng.normal(0.0, 0.01, (96, 128))
    img[10:20, 30:50] = np.nan
    assert noise_level(img) == pytest.approx(0.01, rel=0.1)


@pytest.mark.parametrize("given", [True, False])
def test_excess_of_pure_noise_residuals_is_within_the_limit(given):
    # Residuals of a model that describes the image: chi2 over n values of unit
    # normals, judged with the level given or estimated from an image of this size.
    rng = np.random.default_rng(2)
    img = rng.normal(0.0, 1.0, (200, 240))
    noise = (jl.Gaussian(1.0) if given else jl.Gaussian()).estimated(img, np.isfinite(img))
    assert noise.level_given is given
    zs = []
    for _ in range(50):
        r = rng.normal(0.0, 1.0, 48_000) / float(noise.sigma)
        zs.append(noise.excess(float(r @ r), r.size))
    assert max(abs(z) for z in zs) < GOODNESS_SIGMAS


def test_excess_flags_a_model_off_by_a_quarter_of_the_noise():
    # A systematic misfit of 0.25 noise sigmas on every value: chi2/dof 1.06 over 48,000
    # values, 9 standard deviations of its scatter when the level is given.
    rng = np.random.default_rng(3)
    r = rng.normal(0.0, 1.0, 48_000) + 0.25
    assert jl.Gaussian(1.0).excess(float(r @ r), r.size) > GOODNESS_SIGMAS


def test_an_estimated_level_widens_the_limit():
    # The same chi2 judged against a level estimated from a small image is less
    # surprising: the level's own uncertainty adds to the statistic's scatter.
    small = jl.Gaussian().estimated(np.random.default_rng(4).normal(size=(24, 32)),
                                    np.ones((24, 32), bool))  # fmt: skip
    given = jl.Gaussian(1.0)
    assert small.excess(1.1 * 5000, 5000) < given.excess(1.1 * 5000, 5000)


def test_a_noiseless_image_estimates_a_zero_level():
    # A rendered, quantised image: flat regions with no noise at all. The level is 0 (the
    # fit flags "no pixel noise found"), and the residuals' unit stays positive.
    img = np.round(_ring() * 255) / 255
    noise = jl.Gaussian().estimated(img, np.ones(img.shape, bool))
    assert float(noise.sigma) == 0.0 and float(noise.scale) > 0.0
    assert not noise.level_given


def test_noise_models_from_what_fit_takes():
    assert isinstance(as_noise(None), jl.Gaussian) and not as_noise(None).level_given
    assert as_noise(0.01).level_given and float(as_noise(0.01).sigma) == 0.01
    assert isinstance(as_noise("poisson", 100.0), jl.Poisson)
    assert as_noise("poisson", 100.0).level_given and not as_noise("poisson").level_given
    for bad in ("uniform", -1.0, 0.0, math.inf, True):
        with pytest.raises(ValueError):
            as_noise(bad)
    with pytest.raises(ValueError, match="positive and finite"):
        jl.Gaussian(-0.1)
    with pytest.raises(ValueError, match="positive and finite"):
        jl.Poisson(0.0)


def test_poisson_gain_is_estimated_from_the_counts():
    rng = np.random.default_rng(5)
    gain = 400.0
    img = rng.poisson(_ring() * gain) / gain
    est = jl.Poisson().estimated(img, np.ones(img.shape, bool))
    assert float(est.gain) == pytest.approx(gain, rel=0.15)


def test_blur_excess_measures_a_missing_blur():
    model = _ring(width=1.2)
    for s in (1.0, 2.0):
        data = scipy.ndimage.gaussian_filter(model, s, mode="nearest")
        got = diagnose.blur_excess(model, data - model, 1)
        assert got == pytest.approx(s, rel=0.3)
    # Residuals of pure noise follow no Laplacian: no blur named.
    noise = np.random.default_rng(6).normal(0.0, 0.01, model.shape)
    assert math.isnan(diagnose.blur_excess(model, noise, 1))


def _observed(img, **kw):
    return jl.observe(img, **kw)


def test_likely_causes_name_clipping_blur_and_transfer():
    model = _ring(width=1.2, peak=2.0)
    data = np.minimum(scipy.ndimage.gaussian_filter(model, 2.0, mode="nearest"), 1.0)
    obs = _observed(data)
    hi = clipping_bounds(data)[1]
    causes = diagnose.likely_causes(obs, data, model, data - model, 1, False, hi)
    text = "; ".join(causes)
    assert "clipped" in text and "PSF" in text and "psf=" in text
    untagged = dataclasses.replace(obs, transfer="srgb", transfer_tagged=False)
    assert "transfer" in "; ".join(diagnose.likely_causes(untagged, data, model, data - model,
                                                          1, False, hi))  # fmt: skip


def test_goodness_note_only_beyond_the_limit():
    noise = jl.Gaussian(1.0)
    assert diagnose.goodness_note(noise, 1000.0, 1000, []) == ""
    note = diagnose.goodness_note(noise, 1950.0, 1000, ["a cause"])
    assert "exceed the noise" in note and "a cause" in note and "1.95" in note


def test_noise_trend_sees_a_noise_that_grows_with_brightness():
    rng = np.random.default_rng(8)
    model = rng.uniform(0.0, 1.0, 6000)
    flat = rng.standard_normal(6000)
    growing = flat * (0.5 + model)  # twice the scatter at the top as at the bottom
    assert abs(diagnose.noise_trend(flat, model, -np.inf, np.inf, 0.01)) < 5.0
    assert diagnose.noise_trend(growing, model, -np.inf, np.inf, 0.01) > 20.0
    # Bins near a clipping bound are left out (their noise is shrunk by the clipping).
    clipped = np.where(model < 0.05, 0.3 * flat, flat)
    assert abs(diagnose.noise_trend(clipped, model, 0.0, np.inf, 0.02)) < 5.0


def _fit_like(transfer, distance, error, goodness, converged=True, trend=0.0):
    return jl.Fit(
        scene=None, names=("distance",), values={"distance": distance},
        errors={"distance": error}, covariance=np.eye(1), correlation=np.eye(1), start={},
        noise="gaussian", noise_sigma=0.01, gain=math.nan, chi2_dof=1.0 + goodness / 100,
        model=np.zeros((2, 2)), residuals=np.zeros((2, 2)), n_pixels=100, block=1,
        supersample=2, result=None, result_name="successful", num_steps=3,
        variance_inflation=1.0, converged=converged, degenerate=False, message="",
        seconds=1.0, transfer=transfer, transfer_reason="", goodness=goodness, noise_trend=trend,
    )  # fmt: skip


def test_the_decoding_whose_residuals_fit_the_noise_is_kept():
    srgb, linear = _fit_like("srgb", 18.0, 0.01, 80.0), _fit_like("linear", 37.5, 0.02, 0.3)
    chosen = general._decoding_chosen([srgb, linear], 2.0)
    assert chosen.transfer == "linear" and chosen.valid
    assert "linear decoding's residuals fit the noise" in chosen.transfer_reason


def test_two_decodings_that_both_fit_but_disagree_are_flagged():
    srgb, linear = _fit_like("srgb", 18.0, 0.5, 1.0), _fit_like("linear", 37.5, 0.5, 0.5)
    chosen = general._decoding_chosen([srgb, linear], 2.0)
    assert not chosen.valid and "transfer=" in chosen.message


def test_of_two_decodings_that_fit_the_noise_level_the_flat_one_is_kept():
    # Both fit the noise's level to different values, but one decoding's residuals grow
    # with brightness: the other is the file's.
    srgb = _fit_like("srgb", 20.0, 0.5, 0.5, trend=-0.4)
    linear = _fit_like("linear", 25.3, 0.5, -0.3, trend=-39.7)
    chosen = general._decoding_chosen([srgb, linear], 2.0)
    assert chosen.transfer == "srgb" and chosen.valid and "brightness" in chosen.transfer_reason


def test_two_decodings_that_both_fit_and_agree_are_valid():
    srgb, linear = _fit_like("srgb", 20.0, 0.5, 1.0), _fit_like("linear", 20.3, 0.5, 0.5)
    chosen = general._decoding_chosen([srgb, linear], 2.0)
    assert chosen.valid and chosen.transfer == "linear" and "agree" in chosen.transfer_reason


def test_neither_decoding_fitting_is_flagged_naming_transfer():
    srgb, linear = _fit_like("srgb", 18.0, 0.5, 40.0), _fit_like("linear", 37.5, 0.5, 9.0)
    chosen = general._decoding_chosen([srgb, linear], 2.0)
    assert not chosen.valid and "--transfer" in chosen.message


def test_look_finds_the_ring():
    rng = np.random.default_rng(7)
    seen = start.look(jl.observe(_ring() + rng.normal(0.0, 0.01, (96, 128))))
    assert seen.prof.ring_radius == pytest.approx(30.0, abs=1.5)
    assert not seen.arc_like


def test_sub_bins_are_no_wider_than_a_gaussian_psf():
    g = jl.GaussianPSF
    assert start.psf_sub_bins(g(2.0), 3, (480, 640), 2.0) == 2
    assert start.psf_sub_bins(g(1.0), 2, (300, 400), 1.0) == 2
    assert start.psf_sub_bins(g(1.5), 1, (240, 320), 1.5) == 1
    # Within the sub-bins' budget: a 4096 x 4096 image in bins of 16 px.
    n_bins = (4096 // 16) ** 2
    sub = start.psf_sub_bins(g(1.5), 16, (4096, 4096), 1.5)
    assert 1 <= sub < 16 and sub * sub * n_bins <= start.SUB_BINS


def test_a_psf_image_is_applied_on_pixels_and_refused_beyond_their_budget():
    psf = jl.ImagePSF(np.ones((5, 5)))
    assert start.psf_sub_bins(psf, 3, (480, 640), 1.0) == 3
    with pytest.raises(ValueError, match="crop it"):
        start.psf_sub_bins(psf, 16, (4096, 4096), 1.0)


def _model_of_bins(img, psf, block):
    """The fit's model image of `img`'s bins of side `block` at the image's own truth."""
    import jax
    import jax.numpy as jnp

    from jaxlens._fit import objective

    scene = jl.Scene(jl.Camera(20.0, math.radians(60.0), 8, 8),
                     jl.GaussianStar(math.radians(1.0)) + jl.Uniform(0.05))  # fmt: skip
    obs = jl.observe(img, psf=psf, noise=0.01)
    seen = start.look(obs)
    opts = start.Options(("distance", "fov"), {}, block, None, None, 4096, 1e-6, 1e-6, 10)
    values = start.starting_values_given(scene, obs, opts)
    s = start.build(obs, seen, obs.noise.estimated(obs.data, obs.valid), scene, opts, values,
                    start.focal(values["fov"], img.shape[1]), (0.0, 0.0))  # fmt: skip
    p = {n: jnp.asarray(float(v)) for n, v in zip(s.prob.names, s.data.sel.value)}
    with jax.enable_x64(True):
        m = objective.model_image(p, s.data.scene, s.data.grid, s.data.otf, s.prob)
    return np.asarray(m).reshape(img.shape[0] // block, -1), s.prob


def test_bins_under_a_psf_are_the_means_of_their_blurred_pixels():
    # Bins of 2 px under a 1.2 px PSF are rendered as 2 x 2 sub-bins, blurred there:
    # the model is the mean of the pixels' model, not the blur of the bins' means.
    img = 0.01 + _ring(96, 128)
    bins, prob = _model_of_bins(img, jl.GaussianPSF(1.2), 2)
    pixels, _ = _model_of_bins(img, jl.GaussianPSF(1.2), 1)
    assert prob.sub == 2
    means = pixels.reshape(48, 2, 64, 2).mean(axis=(1, 3))
    assert np.max(np.abs(bins - means)) < 1e-4 * np.max(means)
    # A PSF image of the same Gaussian (pixels) gives the same bins.
    y, x = np.mgrid[-7:8, -7:8]
    kernel = np.exp(-0.5 * (x * x + y * y) / 1.2**2)
    as_image, _ = _model_of_bins(img, jl.ImagePSF(kernel), 2)
    assert np.max(np.abs(as_image - bins)) < 1e-3 * np.max(means)


def test_fit_keeps_the_observations_noise_model(monkeypatch):
    # `fit(scene, observation)` once replaced an observation's noise by its own default
    # (Gaussian): `fit_ring(..., noise="poisson")` fitted Gaussian residuals.
    seen = []

    class Seen(Exception):
        pass

    def record(scene, obs, *rest):
        seen.append(obs)
        raise Seen  # the observation the stages get; no solve

    monkeypatch.setattr(general, "_fit_observed", record)
    img = _ring()
    obs = jl.observe(img, noise=jl.Poisson(50.0), transfer="linear")
    scene = jl.Scene(jl.Camera(20.0, 1.0, 8, 8), jl.GaussianStar(0.02) + jl.Uniform(0.0))
    for call in (lambda: jl.fit_ring(img, star_sigma=0.02, noise="poisson", gain=200.0,
                                     transfer="linear"),
                 lambda: jl.fit(scene, obs),
                 lambda: jl.fit(scene, obs, noise=0.01)):  # fmt: skip
        with pytest.raises(Seen):
            call()
    assert [type(o.noise).__name__ for o in seen] == ["Poisson", "Poisson", "Gaussian"]
    assert [float(o.noise.gain) for o in seen[:2]] == [200.0, 50.0]
