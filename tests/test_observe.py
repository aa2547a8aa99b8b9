"""`jaxlens.observe` on the files users have: what values it reads and what it says of them.

Every file here is written by `tests/user_images.py` (a PNG writer of its own, OpenImageIO's
TIFF and JPEG writers called directly, astropy's FITS), so the tag, or its absence, is
exactly what each test says; only the library-written cases use `jaxlens.write_image`.
No fit runs here.

Tolerances. OpenImageIO hands integer samples over as float32, exact to 2^-24 relative
(6e-8), and the sRGB decode's slope is at most 2.4 / 1.055 = 2.28: so values agree with
the exact decoding of the stored integers within 1e-6 (both well inside). Against the
linear values before storing, a linear file is right within half a step (0.5 / 255 or
0.5 / 65535), plus that 1e-6.
"""

import math

import numpy as np
import pytest
import user_images as ui

import jaxlens as jl

ATOL = 1e-6  # float32 samples (6e-8) times the decode's slope (<= 2.28), with margin
SRGB_SLOPE = 2.4 / 1.055  # the largest slope of the sRGB decode (at 1)


def _values(h=24, w=32, seed=0):
    """Linear values in [0, 1]: random, with 0, 1 and values on the sRGB curve's linear
    segment (below 0.0031308) among them."""
    v = np.random.default_rng(seed).random((h, w))
    v[0, :4] = (0.0, 1.0, 0.001, 0.003)
    return v


def _close(a, b, atol=ATOL):
    np.testing.assert_allclose(np.asarray(a, np.float64), b, rtol=0, atol=atol)


def _untagged(tmp_path, kind, stored):
    if kind == "png":
        path = ui.write_png(tmp_path / "u.png", stored)
        assert ui.png_chunks(path) == [b"IHDR", b"IDAT", b"IEND"]  # no colour chunk
    else:
        path = ui.write_tiff(tmp_path / "u.tif", stored)
        assert ui.file_attributes(path)["colorspace"] == ""  # OpenImageIO sees no tag
    return path


# --- untagged 8/16-bit files: the caller's choice, and "auto" saying it is untagged ------


@pytest.mark.parametrize("kind", ["png", "tif"])
@pytest.mark.parametrize("bits", [8, 16])
def test_untagged_file_read_as_the_caller_says(tmp_path, kind, bits):
    v = _values()
    stored = ui.quantise(v, bits)
    path = _untagged(tmp_path, kind, stored)
    lin = jl.observe(path, transfer="linear")
    assert lin.transfer == "linear" and lin.transfer_tagged is True  # the caller chose
    _close(lin.data, ui.stored_fraction(stored))
    _close(lin.data, v, atol=0.5 / (2**bits - 1) + ATOL)  # the values numpy stored
    assert np.all(np.asarray(lin.valid)) and lin.fov is None and lin.path == str(path)
    srgb = jl.observe(path, transfer="srgb")
    assert srgb.transfer == "srgb" and srgb.transfer_tagged is True
    _close(srgb.data, ui.srgb_decode(ui.stored_fraction(stored)))
    # the two decodings differ by up to ~0.2 here: the test above can tell them apart
    assert np.max(np.abs(np.asarray(srgb.data) - np.asarray(lin.data))) > 0.1


@pytest.mark.parametrize("kind", ["png", "tif"])
@pytest.mark.parametrize("bits", [8, 16])
def test_untagged_file_under_auto_is_marked_untagged(tmp_path, kind, bits):
    # "auto" cannot know how an untagged integer file was meant: the observation says
    # so (transfer_tagged False) and, if it names a decoding, holds that decoding's values.
    stored = ui.quantise(_values(), bits)
    obs = jl.observe(_untagged(tmp_path, kind, stored))
    assert obs.transfer_tagged is False
    assert obs.transfer in ("srgb", "linear", None)
    if obs.transfer is not None:
        decoded = {"linear": ui.stored_fraction, "srgb": lambda s: ui.srgb_decode(
            ui.stored_fraction(s))}[obs.transfer](stored)  # fmt: skip
        _close(obs.data, decoded)


def test_untagged_rgb_png_decoded_before_the_channels_are_averaged(tmp_path):
    # Three different channels: under "srgb" the mean of the decoded channels (linear
    # light adds), which differs from decoding the mean by up to ~0.1 here.
    v = _values()
    rgb = np.stack([v, v[::-1], v[:, ::-1] ** 2], axis=-1)
    stored = ui.quantise(rgb, 16)
    path = ui.write_png(tmp_path / "rgb.png", stored)
    frac = ui.stored_fraction(stored)
    _close(jl.observe(path, transfer="srgb").data, ui.srgb_decode(frac).mean(axis=-1))
    _close(jl.observe(path, transfer="linear").data, frac.mean(axis=-1))
    assert np.max(np.abs(ui.srgb_decode(frac).mean(-1) - ui.srgb_decode(frac.mean(-1)))) > 0.01


# --- tagged files: "auto" follows the tag; a caller's choice overrides it ---------------


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize(
    ("tag", "transfer"), [("srgb", "srgb"), ("gamma22", "srgb"), ("gamma1", "linear")]
)
def test_tagged_png_follows_its_tag(tmp_path, bits, tag, transfer):
    v = _values()
    stored = ui.quantise(ui.srgb_encode(v) if transfer == "srgb" else v, bits)
    path = ui.write_png(tmp_path / "t.png", stored, tag=tag)
    obs = jl.observe(path)
    assert obs.transfer == transfer and obs.transfer_tagged is True
    frac = ui.stored_fraction(stored)
    _close(obs.data, ui.srgb_decode(frac) if transfer == "srgb" else frac)
    if transfer == "linear":
        _close(obs.data, v, atol=0.5 / (2**bits - 1) + ATOL)
    # the caller's choice wins over the file's tag
    other = "linear" if transfer == "srgb" else "srgb"
    forced = jl.observe(path, transfer=other)
    assert forced.transfer == other and forced.transfer_tagged is True
    _close(forced.data, frac if other == "linear" else ui.srgb_decode(frac))


@pytest.mark.parametrize("channels", [1, 3])
def test_srgb_jpeg(tmp_path, channels):
    # JPEG is lossy: the reference is the decoder's own samples (OpenImageIO, undecoded),
    # sRGB-decoded here and the channels averaged.
    v = _values()
    enc = ui.srgb_encode(v if channels == 1 else np.stack([v, v**0.5, v**2], axis=-1))
    path = ui.write_jpeg(tmp_path / "s.jpg", ui.quantise(enc, 8))
    assert "srgb" in ui.file_attributes(path)["colorspace"].lower()
    obs = jl.observe(path)
    assert obs.transfer == "srgb" and obs.transfer_tagged is True
    _close(obs.data, ui.srgb_decode(ui.read_stored(path)).mean(axis=-1))


# --- the library's own files -------------------------------------------------------------


def test_own_png_and_exr(tmp_path):
    v = _values()
    png = jl.write_image(tmp_path / "own.png", v)  # sRGB chunk, 8 bits
    obs = jl.observe(png)
    assert obs.transfer == "srgb" and obs.transfer_tagged is True
    # 8-bit sRGB: half a step of the encoded value, times the decode's slope
    _close(obs.data, v, atol=SRGB_SLOPE * 0.5 / 255 + ATOL)
    exr = jl.write_image(tmp_path / "own.exr", v)  # float32, linear
    obs = jl.observe(exr)
    assert obs.transfer == "linear" and obs.transfer_tagged is True
    np.testing.assert_array_equal(np.asarray(obs.data), v.astype(np.float32).astype(np.float64))


# --- FITS ----------------------------------------------------------------------------------


def test_fits_with_and_without_wcs(tmp_path):
    pytest.importorskip("astropy.io.fits")
    v = 100.0 * _values() - 3.0  # physical values: any range, negatives included
    expect = v.astype(np.float32).astype(np.float64)
    scale = 0.05  # degrees a pixel
    obs = jl.observe(ui.write_fits(tmp_path / "w.fits", v, pixel_scale_deg=scale))
    assert obs.transfer == "linear" and obs.transfer_tagged is True
    np.testing.assert_array_equal(np.asarray(obs.data), expect)  # row 0 at the top, exact
    # the TAN projection's field of view, 2 atan(W s / 2): rtol 1e-12 (float rounding);
    # W s alone differs from it by (FOV/2)^2 / 3 ~ 6e-5, which this tolerance tells apart
    assert obs.fov == pytest.approx(ui.fov_of_scale(v.shape[1], scale), rel=1e-12, abs=0)
    assert abs(obs.fov / (v.shape[1] * math.radians(scale)) - 1) > 1e-5
    bare = jl.observe(ui.write_fits(tmp_path / "n.fits", v))
    assert bare.fov is None and bare.transfer == "linear"
    np.testing.assert_array_equal(np.asarray(bare.data), expect)


def test_fits_nan_pixels_are_not_valid(tmp_path):
    pytest.importorskip("astropy.io.fits")
    img, bad = ui.with_nan(_values(), 0.05)
    assert bad.any() and not bad.all()
    obs = jl.observe(ui.write_fits(tmp_path / "nan.fits", img, pixel_scale_deg=0.01))
    valid, data = np.asarray(obs.valid), np.asarray(obs.data)
    np.testing.assert_array_equal(valid, ~bad)
    assert np.all(np.isnan(data[bad]))
    np.testing.assert_array_equal(data[~bad], img[~bad].astype(np.float32))


# --- arrays, masks, bad arguments -------------------------------------------------------


def test_array_with_nan_and_a_mask(tmp_path):
    img, bad = ui.with_nan(_values(), 0.05, seed=3)
    mask = np.zeros(img.shape, bool)
    mask[5:9, 10:20] = True  # True: a bad pixel (fit's convention)
    obs = jl.observe(img, mask=mask)
    assert obs.transfer is None and obs.path is None and obs.fov is None
    np.testing.assert_array_equal(np.asarray(obs.valid), ~(bad | mask))
    data = np.asarray(obs.data)
    assert np.all(np.isnan(data[bad | mask]))
    np.testing.assert_array_equal(data[~(bad | mask)], img[~(bad | mask)])
    # a mask image (> 0.5: bad), 0 and 255 whatever its decoding
    mpath = ui.write_png(tmp_path / "mask.png", ui.quantise(mask.astype(float), 8))
    stored = ui.quantise(_values(), 16)
    path = ui.write_png(tmp_path / "i.png", stored)
    obs = jl.observe(path, transfer="linear", mask=mpath)
    np.testing.assert_array_equal(np.asarray(obs.valid), ~mask)
    with pytest.raises(ValueError, match="mask"):
        jl.observe(img, mask=np.zeros((3, 4), bool))


@pytest.mark.parametrize("bad", ["gamma", "lin", "", 2.2])
def test_bad_transfer_names_the_choices(tmp_path, bad):
    path = ui.write_png(tmp_path / "b.png", ui.quantise(_values(), 8))
    with pytest.raises(ValueError) as e:
        jl.observe(path, transfer=bad)
    msg = str(e.value)
    assert "transfer" in msg and all(c in msg for c in ("auto", "srgb", "linear"))


def test_psf_and_noise_are_kept():
    img = _values()
    obs = jl.observe(img, psf=2.0, noise=jl.Poisson(gain=100.0))
    # a Gaussian PSF of 2 px, held as its width (pixels) or as a jl.GaussianPSF
    psf = obs.psf
    width = float(psf) if np.ndim(psf) == 0 and not hasattr(psf, "sigma_px") else psf.sigma_px
    assert float(width) == 2.0
    assert isinstance(obs.noise, jl.Poisson) and float(obs.noise.gain) == 100.0
    plain = jl.observe(img)
    assert plain.psf is None and isinstance(plain.noise, jl.Gaussian)
    with pytest.raises(ValueError, match="psf"):
        jl.observe(img, psf=-1.0)
