"""Image files as users make them, written without jaxlens's own writer.

numpy, Pillow and camera pipelines store linear values in 8- and 16-bit PNGs with no
colour tag at all; astronomers hand over FITS files; TIFFs and JPEGs come from other
software. The fit's tests of reading and fitting such files need files whose every byte
the test controls, so the tag (or its absence) is exactly what the test says:

- `write_png`: a PNG written here byte by byte (zlib + struct): 8 or 16 bits, grey or
  RGB, and no colour chunk, an `sRGB` chunk or a `gAMA` chunk (1.0 or 1/2.2).
- `write_tiff`, `write_jpeg`: OpenImageIO's writers called directly, the TIFF with no
  colour-space attribute, the JPEG with "sRGB"; `file_attributes` says what
  OpenImageIO reports of a file written.
- `write_fits`: a float32 FITS image (astropy), with or without a celestial TAN WCS.

The pixel content: `ring` draws an Einstein ring with `jaxlens.ring_image` (linear
intensity), optionally blurred by a Gaussian point-spread function (rendered on a margin
at the same focal length, blurred, cropped, as light from beyond the frame spreads into
it) and with Gaussian noise; `quantise` stores values as 8- or 16-bit integers (clipped
to the format's range, as every writer does), `srgb_encode` / `srgb_decode` are the sRGB
transfer written out here from IEC 61966-2-1, not the library's.
"""

import math
import pathlib
import struct
import zlib

import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# The tags `write_png` can write: no colour chunk, an sRGB chunk (rendering intent 0,
# perceptual), or a gAMA chunk of the file's encoding exponent (stored x 100000).
PNG_TAGS = (None, "srgb", "gamma1", "gamma22")


# ------------------------------------------------------------------------- transfer


def srgb_encode(linear):
    """The sRGB transfer (IEC 61966-2-1): linear values in [0, 1] -> encoded values."""
    x = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def srgb_decode(encoded):
    """The inverse of `srgb_encode`: encoded values in [0, 1] -> linear values."""
    e = np.asarray(encoded, np.float64)
    return np.where(e <= 0.04045, e / 12.92, ((e + 0.055) / 1.055) ** 2.4)


def quantise(values, bits: int) -> np.ndarray:
    """`values` in [0, 1] stored as `bits`-bit integers (8 or 16): clipped to [0, 1]
    and rounded to the nearest of 2^bits - 1 steps (NaN stored as 0)."""
    top = _top(bits)
    v = np.nan_to_num(np.asarray(values, np.float64), nan=0.0)
    return np.round(np.clip(v, 0.0, 1.0) * top).astype(np.uint8 if bits == 8 else np.uint16)


def stored_fraction(stored) -> np.ndarray:
    """Integers as stored -> float64 in [0, 1] (divided by 255 or 65535)."""
    stored = np.asarray(stored)
    return stored.astype(np.float64) / _top(8 if stored.dtype == np.uint8 else 16)


def _top(bits: int) -> int:
    if bits not in (8, 16):
        raise ValueError(f"bits={bits!r} must be 8 or 16")
    return (1 << bits) - 1


# ------------------------------------------------------------------------------ PNG


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def write_png(path, stored, *, tag: str | None = None) -> pathlib.Path:
    """Write `stored` (uint8 or uint16, `(H, W)` grey or `(H, W, 3)` RGB) as a PNG.

    The bit depth is the dtype's; the samples are written as they are (big-endian for
    16 bits, each row with filter type 0), so a reader that decodes nothing gets them
    back exactly. `tag`: None (no colour chunk: what numpy-based writers produce),
    "srgb" (an sRGB chunk), "gamma1" (gAMA 1.0: linear), "gamma22" (gAMA 1/2.2, 45455).
    """
    stored = np.asarray(stored)
    if stored.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"stored samples of dtype {stored.dtype}: expected uint8 or uint16")
    if stored.ndim == 2:
        colour_type = 0
    elif stored.ndim == 3 and stored.shape[-1] == 3:
        colour_type = 2
    else:
        raise ValueError(f"stored samples of shape {stored.shape}: expected (H, W) or (H, W, 3)")
    if tag not in PNG_TAGS:
        raise ValueError(f"tag={tag!r} must be one of {PNG_TAGS}")
    h, w = stored.shape[:2]
    bits = 8 * stored.dtype.itemsize
    rows = stored.astype(">u2" if bits == 16 else np.uint8).reshape(h, -1).view(np.uint8)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows.reshape(h, -1)], axis=1)
    chunks = [_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, colour_type, 0, 0, 0))]
    if tag == "srgb":
        chunks.append(_chunk(b"sRGB", bytes([0])))
    elif tag in ("gamma1", "gamma22"):
        chunks.append(_chunk(b"gAMA", struct.pack(">I", 100000 if tag == "gamma1" else 45455)))
    chunks += [_chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)), _chunk(b"IEND", b"")]
    path = pathlib.Path(path)
    path.write_bytes(PNG_SIGNATURE + b"".join(chunks))
    return path


def png_chunks(path) -> list[bytes]:
    """The chunk types of a PNG file, in order (to check what `write_png` wrote)."""
    data = pathlib.Path(path).read_bytes()
    assert data[:8] == PNG_SIGNATURE, f"{path} is not a PNG"
    kinds, i = [], 8
    while i < len(data):
        (n,) = struct.unpack(">I", data[i : i + 4])
        kinds.append(data[i + 4 : i + 8])
        i += 12 + n
    return kinds


# ------------------------------------------------------------- TIFF, JPEG (OpenImageIO)


def _write_oiio(path, stored, attributes: dict) -> pathlib.Path:
    import OpenImageIO as oiio

    stored = np.asarray(stored)
    data = stored[..., None] if stored.ndim == 2 else stored
    fmt = {np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16}[data.dtype]
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for key, value in attributes.items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    ok = out.open(str(path), spec) and out.write_image(np.ascontiguousarray(data))
    ok = out.close() and ok
    assert ok, out.geterror()
    return pathlib.Path(path)


def write_tiff(path, stored) -> pathlib.Path:
    """`stored` (uint8 or uint16, grey or RGB) as a TIFF with no colour-space attribute
    set (OpenImageIO's TIFF writer then writes no colour tag)."""
    return _write_oiio(path, stored, {})


def write_jpeg(path, stored, *, quality: int = 95) -> pathlib.Path:
    """`stored` (uint8, grey or RGB: sRGB-encoded values) as a JPEG tagged sRGB."""
    if np.asarray(stored).dtype != np.uint8:
        raise ValueError("a JPEG stores 8-bit samples")
    return _write_oiio(path, stored, {"oiio:ColorSpace": "sRGB", "Compression": f"jpeg:{quality}"})


def file_attributes(path) -> dict:
    """What OpenImageIO reports of a file: its pixel format, channel count, colour space
    (`oiio:ColorSpace`, "" if none) and gamma (`oiio:Gamma`, 0 if none)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        spec = inp.spec()
        return {
            "format": str(spec.format),
            "nchannels": spec.nchannels,
            "colorspace": str(spec.get_string_attribute("oiio:ColorSpace", "")),
            "gamma": float(spec.get_float_attribute("oiio:Gamma", 0.0)),
        }
    finally:
        inp.close()


def read_stored(path) -> np.ndarray:
    """A file's samples as OpenImageIO reads them, undecoded, as float64 in [0, 1]
    `(H, W, C)` (for JPEG, whose stored values only the decoder knows)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        data = inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.FLOAT)
    finally:
        inp.close()
    data = np.asarray(data, np.float64)
    return data[..., None] if data.ndim == 2 else data


# ----------------------------------------------------------------------------- FITS


def write_fits(path, image, *, pixel_scale_deg: float | None = None, **keys) -> pathlib.Path:
    """`image` (float, `(H, W)`, row 0 at the top as jaxlens has it) as a float32 FITS
    primary HDU. FITS's first stored row is the bottom of the picture, so the rows are
    flipped. `pixel_scale_deg`: a celestial TAN WCS with square pixels of that size
    (degrees), the reference pixel at the image's centre, RA increasing to the left,
    north up; None: no WCS. `keys`: more header cards (e.g. GAIN=2.0)."""
    from astropy.io import fits

    data = np.asarray(image, np.float32)[::-1]
    hdu = fits.PrimaryHDU(np.ascontiguousarray(data))
    h, w = data.shape
    if pixel_scale_deg is not None:
        hdr = hdu.header
        hdr["CTYPE1"], hdr["CTYPE2"] = "RA---TAN", "DEC--TAN"
        hdr["CRPIX1"], hdr["CRPIX2"] = (w + 1) / 2, (h + 1) / 2
        hdr["CRVAL1"], hdr["CRVAL2"] = 150.0, 30.0
        hdr["CDELT1"], hdr["CDELT2"] = -pixel_scale_deg, pixel_scale_deg
        hdr["CUNIT1"], hdr["CUNIT2"] = "deg", "deg"
    for key, value in keys.items():
        hdu.header[key] = value
    hdu.writeto(path, overwrite=True)
    return pathlib.Path(path)


def fov_of_scale(width: int, pixel_scale_deg: float) -> float:
    """The horizontal field of view (radians) of a pinhole camera whose pixels subtend
    `pixel_scale_deg` at the centre: 2 atan(W s / 2) (the TAN projection's)."""
    return 2.0 * math.atan(0.5 * width * math.radians(pixel_scale_deg))


def pixel_scale_of_fov(width: int, fov_deg: float) -> float:
    """The inverse of `fov_of_scale`: the TAN WCS's pixel scale (degrees) of a field of
    view `fov_deg` over `width` pixels."""
    return math.degrees(2.0 * math.tan(0.5 * math.radians(fov_deg)) / width)


# ------------------------------------------------------------------------- content


def ring(
    width: int = 160,
    height: int = 120,
    *,
    distance: float = 20.0,
    fov_deg: float = 60.0,
    sigma_deg: float = 1.5,
    brightness: float = 0.8,
    floor: float = 0.05,
    blur_px: float = 0.0,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """A linear image of an Einstein ring (float64 `(height, width)`, not clipped).

    A Gaussian star of width `sigma_deg` (degrees) and peak `brightness` exactly behind
    the hole over a uniform `floor`, seen from `distance` (R_S) with a horizontal field
    of view `fov_deg` (degrees): `jaxlens.ring_image`, area-averaged pixels. With
    `blur_px` > 0 (a Gaussian point-spread function's sigma, pixels) the frame is drawn
    with a margin of ceil(5 blur_px) pixels on every side at the same focal length,
    blurred by `scipy.ndimage.gaussian_filter` (mode "nearest", truncate 6) and
    cropped. Then Gaussian noise of sigma `noise` (seeded by `seed`).
    """
    import jaxlens as jl

    margin = math.ceil(5.0 * blur_px) if blur_px > 0 else 0
    w, h = width + 2 * margin, height + 2 * margin
    focal = 0.5 * width / math.tan(0.5 * math.radians(fov_deg))
    fov = 2.0 * math.atan(0.5 * w / focal)  # the same focal length on the larger frame
    sigma = math.radians(sigma_deg)
    img = jl.ring_image(distance, fov, w, h, sigma=sigma, brightness=brightness, floor=floor)
    img = np.asarray(img, np.float64)
    if margin:
        from scipy.ndimage import gaussian_filter

        img = gaussian_filter(img, blur_px, mode="nearest", truncate=6.0)
        img = img[margin:-margin, margin:-margin]
    if noise > 0:
        img = img + noise * np.random.default_rng(seed).standard_normal(img.shape)
    return img


def with_nan(image, fraction: float = 0.01, *, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """`(copy of image with NaN pixels, where)`: a `fraction` of the pixels, chosen at
    random (seeded), set to NaN, as bad pixels and cosmic-ray masks leave them."""
    img = np.array(image, np.float64)
    bad = np.random.default_rng(seed).random(img.shape) < fraction
    img[bad] = np.nan
    return img, bad


def half_frame_height_deg(width: int, height: int, fov_deg: float) -> float:
    """The angle from the image centre to the middle of the top edge (degrees)."""
    return math.degrees(math.atan(height / width * math.tan(0.5 * math.radians(fov_deg))))
