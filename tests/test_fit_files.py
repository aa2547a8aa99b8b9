"""`jaxlens.fit_ring` on the files users have: right where the file can be read right,
flagged where it cannot.

The files come from `tests/user_images.py`, not from the library's writer: a ring drawn by
`jaxlens.ring_image` (D = 20, FOV 60 deg, a star of 1.5 deg given to the fit, 96 x 72
pixels, Gaussian noise 0.01 on a peak of 0.8), stored as linear values in an untagged
16-bit PNG, as numpy and camera pipelines write them. 96 x 72 is tests/test_fit.py's
size, so these fits share its compiled programs (the suite's XLA cache). The blurred
ring is 160 x 120, where an untold blur of 2 px also fails the residuals' test; at
96 x 72 a blur the fitted values take up passes it (D 79.7 +- 0.28, FOV 29.85 deg for
a 2 px blur) and only the blur's own score test flags it.

Tolerances. 1 % in D and FOV is the fit benchmark's goal; here the reported standard
errors are about 0.2 % and 0.1 % (D +- 0.04, FOV +- 0.05 deg), so a right fit meets it
by five of them, while reading the linear file as sRGB puts D off by ~50 % (9.3 instead
of 20).
"Within 3 standard errors" is the pull |fit - truth| / error < 3: the model that drew
the image is the one fitted, so pulls are N(0, 1) and 3 is missed by 0.3 % of seeds
(the seeds are fixed).
"""

import math

import numpy as np
import pytest
import user_images as ui

import jaxlens as jl

D, FOV_DEG, SIGMA_DEG = 20.0, 60.0, 1.5
STAR = math.radians(SIGMA_DEG)
W, H = 96, 72


def _within(fit, rel=0.01):
    """D and FOV both within `rel` of the truth."""
    return abs(fit.distance / D - 1) < rel and abs(fit.fov_deg / FOV_DEG - 1) < rel


def _pulls(fit):
    return ((fit.distance - D) / fit.distance_err, (fit.fov_deg - FOV_DEG) / fit.fov_deg_err)


def _honest(fit):
    """Within 1 % and the truth within 3 reported standard errors."""
    return _within(fit) and max(abs(p) for p in _pulls(fit)) < 3.0


def _said(fit) -> str:
    return (f"D {fit.distance:.4f} +- {fit.distance_err:.3g}, FOV {fit.fov_deg:.4f} +- "
            f"{fit.fov_deg_err:.3g} deg, valid {fit.valid}, transfer {fit.transfer!r} "
            f"({fit.transfer_reason!r}), message {fit.message!r}")  # fmt: skip


def _png16(folder, name, image):
    """`image` (linear) as an untagged 16-bit grey PNG: no sRGB, gAMA or iCCP chunk."""
    path = ui.write_png(folder / name, ui.quantise(image, 16))
    assert ui.png_chunks(path) == [b"IHDR", b"IDAT", b"IEND"]
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("user_files")


@pytest.fixture(scope="module")
def linear_png(folder):
    return _png16(folder, "linear16.png", ui.ring(W, H, noise=0.01, seed=1))


@pytest.fixture(scope="module")
def blurred_png(folder):
    # a Gaussian PSF of 2 px, drawn on a margin and cropped (light from beyond the frame),
    # at 160 x 120 (the module's docstring says why)
    return _png16(folder, "blurred16.png", ui.ring(160, 120, blur_px=2.0, noise=0.01, seed=2))


# --- the transfer of an untagged file -----------------------------------------------------


def test_untagged_linear_png_read_as_linear(linear_png):
    fit = jl.fit_ring(linear_png, star_sigma=STAR, transfer="linear")
    assert fit.transfer == "linear", _said(fit)
    assert fit.valid and _honest(fit), _said(fit)


def test_untagged_linear_png_under_auto_right_or_flagged(linear_png):
    # "auto" may fit both decodings and keep the one whose residuals pass; where it
    # cannot decide it must say so and name the option (transfer=).
    fit = jl.fit_ring(linear_png, star_sigma=STAR, transfer="auto")
    if fit.valid:
        assert _within(fit) and fit.transfer == "linear" and fit.transfer_reason, _said(fit)
    else:
        assert "transfer" in fit.message, _said(fit)


def test_untagged_linear_png_read_as_srgb_is_flagged(linear_png):
    # The caller's wrong choice: decoded as sRGB the ring's profile is distorted (D
    # comes out near 9.3); the residual test must flag it, not report it.
    fit = jl.fit_ring(linear_png, star_sigma=STAR, transfer="srgb")
    assert fit.transfer == "srgb", _said(fit)
    assert not fit.valid or _within(fit), _said(fit)


def test_untagged_srgb_png_under_auto_right_or_flagged(folder):
    # The other way round: sRGB-encoded values (the noise added to the linear light)
    # in a PNG without a colour chunk. Both decodings fit the noise's level here; the
    # linear one's residuals grow with brightness, so sRGB is the file's.
    img = np.clip(ui.ring(W, H, noise=0.01, seed=21), 0.0, 1.0)
    path = ui.write_png(folder / "srgb16.png", ui.quantise(ui.srgb_encode(img), 16))
    assert ui.png_chunks(path) == [b"IHDR", b"IDAT", b"IEND"]
    fit = jl.fit_ring(path, star_sigma=STAR)
    if fit.valid:
        assert _within(fit) and fit.transfer == "srgb", _said(fit)
    else:
        assert "transfer" in fit.message, _said(fit)


# --- a point-spread function the fit is not told of ---------------------------------------


def test_blur_without_psf_is_flagged_naming_the_psf(blurred_png):
    fit = jl.fit_ring(blurred_png, star_sigma=STAR, transfer="linear")
    assert not fit.valid and "psf" in fit.message.lower(), _said(fit)


@pytest.mark.benchmark  # ~40 s (the slowest here); the fit benchmark's arcs have PSFs of 1-2 px
def test_blur_with_its_psf_is_right(blurred_png):
    fit = jl.fit_ring(blurred_png, star_sigma=STAR, transfer="linear", psf=2.0)
    assert fit.valid and _honest(fit), _said(fit)


# --- clipping and a tiny image ------------------------------------------------------------


def test_ring_clipped_at_one_is_flagged_or_right(folder):
    # three times too bright: the ring's core stored as 1 (8 % of the pixels here)
    img = ui.ring(W, H, brightness=3 * 0.8, noise=0.01, seed=3)
    assert np.mean(img > 1) > 0.05
    fit = jl.fit_ring(_png16(folder, "clipped16.png", img), star_sigma=STAR, transfer="linear")
    if fit.valid:
        assert _honest(fit), _said(fit)
    else:
        assert "clip" in fit.message.lower(), _said(fit)


def test_tiny_ring_is_refused_or_flagged(folder):
    # 16 x 12 pixels: the ring is ~5 px in radius and under a pixel wide
    path = _png16(folder, "tiny16.png", ui.ring(16, 12, noise=0.01, seed=4))
    try:
        fit = jl.fit_ring(path, star_sigma=STAR, transfer="linear")
    except ValueError as e:
        assert str(e), "a refusal must say why"
        return
    assert not fit.valid and fit.message, _said(fit)


def test_a_ring_cut_by_the_frame_is_right(folder):
    # FOV 45 deg on 96 x 72: the ring (20.2 deg from the hole) is beyond the frame's
    # half-height (17.3 deg), seen on the sides only.
    assert ui.half_frame_height_deg(W, H, 45.0) < 20.0 < 22.5
    path = _png16(folder, "cut16.png", ui.ring(W, H, fov_deg=45.0, noise=0.01, seed=5))
    fit = jl.fit_ring(path, star_sigma=STAR, transfer="linear")
    assert fit.valid and abs(fit.distance / D - 1) < 0.01, _said(fit)
    assert abs(fit.fov_deg / 45.0 - 1) < 0.01, _said(fit)
    assert abs(fit.distance - D) < 3.0 * fit.distance_err, _said(fit)


def test_a_ring_outside_the_frame_is_refused_not_fitted(folder):
    # FOV 30 deg: the ring lies beyond the frame's corners; the shadow's edge alone
    # once passed for arcs and was fitted at D = 8.3 +- 0.37, FOV 66 deg, valid.
    path = _png16(folder, "outside16.png", ui.ring(W, H, fov_deg=30.0, noise=0.01, seed=6))
    with pytest.raises(ValueError, match="outside the frame"):
        jl.fit_ring(path, star_sigma=STAR, transfer="linear")


def test_a_blur_the_fit_takes_up_is_flagged_by_its_score(folder):
    # Blurred by 1 px, untold: fitted as a sharp ring at D = 35, FOV 45 deg, whose
    # residuals are the noise's (goodness 0.06); the blur's direction, with the fitted
    # values' share taken out, stands 25 standard errors out.
    path = _png16(folder, "blur1.png", ui.ring(W, H, blur_px=1.0, noise=0.01, seed=3))
    fit = jl.fit_ring(path, star_sigma=STAR, transfer="linear")
    assert not fit.valid and fit.blur_z > 5.0, _said(fit)
    assert "more blurred than the model" in fit.message and "--psf-sigma-px" in fit.message
    # The same image unblurred passes the test.
    sharp = _png16(folder, "sharp1.png", ui.ring(W, H, noise=0.01, seed=3))
    fit = jl.fit_ring(sharp, star_sigma=STAR, transfer="linear")
    assert fit.valid and abs(fit.blur_z) < 5.0, _said(fit)
