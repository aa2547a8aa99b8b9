"""What a fit compares against: an observed image as linear intensity, which of its
pixels count, how its values were decoded, its point-spread function and noise model."""

import math
from pathlib import Path

import equinox as eqx
import numpy as np

from .._io import read_pixels, srgb_decode, transfer_of
from .._psf import AbstractPSF, GaussianPSF, ImagePSF
from .._util import host_driver
from .noise import AbstractNoise, as_noise
from .pixels import real_image

TRANSFERS = ("auto", "srgb", "linear")
PIXELS = ("auto", "area", "point")
# A pixel's area, sampled at its centre rather than averaged, is a blur less: the box's
# variance, 1/12 px^2 along each axis.
BOX_VARIANCE = 1.0 / 12.0
_AREA = "pixels average the light over their area (the default)"
_FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz")


class Observation(eqx.Module):
    """An observed image as a fit reads it (host-side NumPy arrays; `observe` builds it).

    **Fields:**
    - `data`: float64 `(H, W)`, linear intensity (the colour channels averaged, alpha
      left out); NaN where a pixel is not `valid`.
    - `valid`: bool `(H, W)`: finite, not masked, not flagged bad by a FITS file.
    - `transfer`: how the stored values were decoded: `"srgb"` (the sRGB curve undone)
      or `"linear"` (taken as stored, integer formats scaled to [0, 1]); `None` for an
      array, taken as linear.
    - `transfer_reason`: why: the file's tag, the caller's choice, a float format, or
      an untagged 8/16-bit file read by its format's default (sRGB).
    - `transfer_tagged`: whether the file or the caller said how to decode it; False
      for an untagged 8/16-bit file read with `transfer="auto"`, which `fit` then
      fits under both decodings (`other`).
    - `other`: for such a file, the same pixels under the other decoding (linear);
      else `None`.
    - `fov`: the horizontal field of view (radians) that a FITS file's celestial WCS
      fixes, else `None`.
    - `psf`: `None` or the PSF (`jaxlens.GaussianPSF`, `jaxlens.ImagePSF`).
    - `noise`: the noise model (`jaxlens.Gaussian`, `jaxlens.Poisson`), its level
      estimated by the fit where not given.
    - `path`: the file read, or `None`.
    - `pixels`: how the pixels sampled the light: `"area"` (averaged over each pixel,
      as a camera's do) or `"point"` (sampled at each pixel's centre, as a render with
      one ray a pixel); `pixels_reason`: why (given, or the file's record).
    """

    data: np.ndarray
    valid: np.ndarray
    transfer: str | None
    transfer_reason: str
    transfer_tagged: bool
    other: np.ndarray | None
    fov: float | None
    psf: object
    noise: AbstractNoise
    path: str | None
    pixels: str = "area"
    pixels_reason: str = _AREA

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape

    def decoded(self, transfer: str) -> "Observation":
        """This observation under the other decoding of an untagged file (`other`),
        or itself when it is already decoded so."""
        if transfer == self.transfer:
            return self
        if self.other is None or transfer not in ("srgb", "linear"):
            raise ValueError(f"this observation cannot be decoded as {transfer!r}: read the "
                             f"file again with transfer={transfer!r}")  # fmt: skip
        reason = f"untagged file, decoded as {_NAMES[transfer]}"
        return Observation(self.other, self.valid, transfer, reason, False, self.data,
                           self.fov, self.psf, self.noise, self.path, self.pixels,
                           self.pixels_reason)  # fmt: skip


_NAMES = {"srgb": "sRGB", "linear": "linear"}


def _check_transfer(transfer) -> None:
    if not isinstance(transfer, str) or transfer not in TRANSFERS:
        raise ValueError(f"transfer={transfer!r} is not valid: expected one of "
                         f"{', '.join(map(repr, TRANSFERS))} (how an 8/16-bit file's values "
                         "are decoded)")  # fmt: skip


def _pixels(pixels, recorded: str, psf) -> tuple[str, str]:
    """`(pixels, reason)`: how the image's pixels sampled the light, from `observe`'s
    `pixels`, the file's record (`recorded`, "" for none) and the default (area);
    a `ValueError` for a value not in `PIXELS`, and for point samples with a PSF image
    or a Gaussian PSF narrower than a pixel's box."""
    if not isinstance(pixels, str) or pixels not in PIXELS:
        raise ValueError(f"pixels={pixels!r} is not valid: expected one of "
                         f"{', '.join(map(repr, PIXELS))} (how the pixels sampled the "
                         "light)")  # fmt: skip
    if pixels != "auto":
        out = pixels, f"pixels={pixels!r} given"
    elif recorded in ("area", "point"):
        out = recorded, f"the file records jaxlens's {recorded} sampling"
    else:
        out = "area", _AREA
    if out[0] == "point" and psf is not None:
        # The model renders area averages and narrows a Gaussian PSF by the box.
        if not isinstance(psf, GaussianPSF):
            raise ValueError("an image of point samples (pixels='point') is fitted with a "
                             "Gaussian PSF or none, not a PSF image")  # fmt: skip
        if not float(psf.sigma_px) ** 2 > BOX_VARIANCE:
            raise ValueError(f"a Gaussian PSF of {float(psf.sigma_px):.3g} px is narrower "
                             "than a pixel's own blur (0.289 px): with point samples "
                             "(pixels='point') give a wider one or none")  # fmt: skip
    return out


def _grey(data, alpha: int = -1, decode: bool = False) -> np.ndarray:
    """The colour channels' mean of `(H, W, C)` (alpha left out), or `(H, W)` as it is;
    with `decode`, each channel decoded from sRGB first (the mean of encoded values is
    not the encoding of the mean)."""
    if data.ndim == 3:
        colour = [i for i in range(data.shape[-1]) if i != alpha] or [0]
        data = data[..., colour]
    if decode:
        data = srgb_decode(data, np.float64)
    return data.mean(axis=-1) if data.ndim == 3 else data


def _read_file(path, transfer: str):
    """`(linear, other, transfer, reason, tagged)` of an image file (not FITS), and
    the pixels' sampling it records ("" for none)."""
    data, info = read_pixels(path)
    return _decoded(data, info, transfer) + (info.get("sampling", ""),)


def _decoded(data, info, transfer: str):
    """`(linear, other, transfer, reason, tagged)` of a file's pixels."""
    data = np.asarray(data, np.float64)

    def grey(decode):
        return _grey(data, info["alpha"], decode)

    integer = info["format"].startswith(("uint", "int"))
    bits = {"uint8": "8-bit", "uint16": "16-bit"}.get(info["format"], info["format"])
    if transfer != "auto":
        return grey(transfer == "srgb"), None, transfer, f"transfer={transfer!r} given", True
    if not integer:
        return grey(False), None, "linear", f"a {info['format']} file: linear", True
    kind = transfer_of(info)
    if info["tagged"]:
        return grey(kind == "srgb"), None, kind, f"the {bits} file is tagged {_NAMES[kind]}", True
    # An untagged 8/16-bit file: sRGB by its format's default, but as often linear
    # values written by a camera pipeline or numpy; the fit tries both.
    reason = f"untagged {bits} file, read as sRGB (its format's default)"
    return grey(True), grey(False), "srgb", reason, False


def read_observation(path, *, transfer: str = "auto") -> np.ndarray:
    """Read an image file as the fit reads it: linear intensity, the colour channels
    averaged (an alpha channel, as OpenImageIO identifies it, left out).

    `transfer` as in `observe`: `"auto"` decodes 8/16-bit files tagged sRGB, or
    untagged (the default of PNG and JPEG), from sRGB to linear and takes float files
    and files tagged linear (a PNG with gAMA 1.0) as stored; `"srgb"` and `"linear"`
    say how. Integer formats are normalised to [0, 1] first.

    **Returns:** float64 `(H, W)`; raises `ValueError` naming the file when it is
    missing, empty, not an image or unreadable.
    """
    _check_transfer(transfer)
    return _read_file(path, transfer)[0]


def _read_mask(mask, shape) -> np.ndarray:
    """A mask (True = bad pixel) from an array or an image file (> 0.5 = bad)."""
    if mask is None:
        return np.zeros(shape, bool)
    if isinstance(mask, (str, Path)):
        data, info = read_pixels(mask)
        mask = _grey(np.asarray(data, np.float64), info["alpha"]) > 0.5
    mask = np.asarray(mask)
    if mask.dtype != bool:
        mask = real_image(mask, "mask") != 0
    if mask.shape != shape:
        raise ValueError(f"mask of shape {mask.shape} does not match the image {shape}")
    return mask


def _checked_psf(psf):
    """`psf` as a PSF model: `None`, an `AbstractPSF` as it is, a number (a Gaussian
    PSF's width in pixels, > 0 and finite: `GaussianPSF`) or a 2-D image (`ImagePSF`)."""
    if psf is None or isinstance(psf, AbstractPSF):
        return psf
    if np.ndim(psf) != 2:
        try:
            width = float(psf)
        except (TypeError, ValueError):
            width = math.nan
        if not 0 < width < math.inf:
            raise ValueError(f"psf={psf!r} must be a Gaussian PSF's width in pixels (> 0, "
                             "finite) or a PSF image (2-D)")  # fmt: skip
        return GaussianPSF(width)
    return ImagePSF(real_image(psf, "psf"))


def observe(image, *, transfer: str = "auto", mask=None, psf=None, noise=None,
            gain: float | None = None, pixels: str = "auto") -> Observation:  # fmt: skip
    """Read an observed image for a fit: an `Observation`.

    **Arguments:**
    - `image`: a path (FITS through astropy, the WCS's pixel scale fixing the field of
      view; any other format OpenImageIO reads), an array `(H, W)` or `(H, W, C)` of
      linear intensity (NaN: not valid), or an `Observation` (returned with what the
      other arguments give replaced).
    - `transfer`: how an 8/16-bit file's values relate to light. `"auto"` (default):
      as the file says (an sRGB or gAMA chunk, an ICC profile, a colour space); a file
      that says nothing is read as sRGB, its format's default, and `fit` fits it under
      both decodings, keeping the one its residuals accept. `"srgb"`: decode the sRGB
      curve. `"linear"`: the stored values as they are (integer formats scaled to
      [0, 1]), as numpy, cameras' raw pipelines and many scientific images write them.
      Float files and FITS are linear; an array is taken as linear unless `"srgb"`.
    - `mask`: bool array (True = bad pixel) or a mask image (> 0.5 = bad).
    - `psf`: `None`, a PSF (`jaxlens.GaussianPSF`, `jaxlens.ImagePSF`), a Gaussian
      PSF's width (pixels) or a PSF image (2-D array).
    - `noise`: `None` or `"gaussian"` (Gaussian, level estimated), a number (Gaussian
      of that standard deviation, data units), `"poisson"`, or a noise model
      (`jaxlens.Gaussian(sigma)`, `jaxlens.Poisson(gain)`).
    - `gain`: counts per data unit, for `noise="poisson"`.
    - `pixels`: how the pixels sampled the light. `"area"`: each averages the light
      over its area, as a camera's pixels do. `"point"`: each is the light at its
      centre, as a render with one ray a pixel (jaxlens' default `supersample=1`):
      its sharper image is not mistaken for a different distance (a default render
      blurred by 1.5 px fitted as area samples: D 1.4 % off, 18 standard errors).
      `"auto"` (default): what a file jaxlens wrote records (PNG, EXR), else area.

    **Returns:** an `Observation`. Raises `ValueError` for an unreadable file, an
    image that is not 2-D (or 2-D with channels), smaller than 8 pixels a side, with
    fewer than 64 valid pixels or blank, and a `TypeError` for an array that does not
    hold real numbers. A host function: not under `jit`.
    """
    host_driver("observe", "read the image outside the traced function", image)
    _check_transfer(transfer)
    psf = _checked_psf(psf)
    if isinstance(image, Observation):
        obs = image if transfer == "auto" else image.decoded(transfer)
        replace = {}
        if pixels != "auto" or psf is not None:
            kept = pixels == "auto"  # the observation's own, checked against a new PSF
            how, why = _pixels(obs.pixels if kept else pixels, "",
                               obs.psf if psf is None else psf)  # fmt: skip
            replace["pixels"], replace["pixels_reason"] = how, obs.pixels_reason if kept else why
        if mask is not None:
            replace["valid"] = obs.valid & ~_read_mask(mask, obs.shape)
            replace["data"] = np.where(replace["valid"], obs.data, np.nan)
        if psf is not None:
            replace["psf"] = psf
        if noise is not None or gain is not None:
            replace["noise"] = as_noise(noise, gain)
        return eqx.tree_at(lambda o: [getattr(o, n) for n in replace], obs,
                           list(replace.values()), is_leaf=lambda x: x is None)  # fmt: skip
    fov, other, path, bad, recorded = None, None, None, None, ""
    if isinstance(image, (str, Path)):
        path = str(image)
        if path.lower().endswith(_FITS_SUFFIXES):
            from .fits import read_fits

            fits = read_fits(image)
            data, fov, bad = fits.data, fits.fov, fits.mask
            tr, reason, tagged = "linear", "a FITS file: linear", True
        else:
            data, other, tr, reason, tagged, recorded = _read_file(image, transfer)
    else:
        data = _grey(real_image(image), decode=transfer == "srgb")
        tr = "srgb" if transfer == "srgb" else None
        reason, tagged = ("transfer='srgb' given" if tr else "an array: linear"), True
    data = np.asarray(data, np.float64)
    if data.ndim != 2:
        raise ValueError(f"image of shape {np.shape(data)} is not (H, W) or (H, W, C)")
    if min(data.shape) < 8:
        raise ValueError(f"image of {data.shape[1]} x {data.shape[0]} pixels is too small to "
                         "fit (8 a side at least)")  # fmt: skip
    valid = np.isfinite(data) & ~_read_mask(mask, data.shape)
    if bad is not None:
        valid &= ~bad
    if valid.sum() < 64:
        raise ValueError(f"only {int(valid.sum())} valid pixels: nothing to fit")
    seen = data[valid]
    if float(seen.max() - seen.min()) <= 1e-12 * max(1.0, abs(float(seen.max()))):
        raise ValueError(f"image is blank (every valid pixel is {float(seen[0]):.6g}): "
                         "no ring to fit")  # fmt: skip
    data = np.where(valid, data, np.nan)
    if other is not None:
        other = np.where(valid, other, np.nan)
    how, why = _pixels(pixels, recorded, psf)
    return Observation(data, valid, tr, reason, tagged, other, fov, psf, as_noise(noise, gain),
                       path, how, why)  # fmt: skip
