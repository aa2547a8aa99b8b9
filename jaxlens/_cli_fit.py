"""`jaxlens fit`: the camera distance, field of view and source position from an image of
a lensed star (a ring, or arcs from a star off the axis)."""

import argparse
import json
import math
import sys

from . import _multi, _schema, cli
from ._messages import cut
from ._schema import MAGNITUDE_MAX

# The modules of the fit, the scene and the skies (and with them JAX) are imported in
# the functions that run the command: at module level they would load JAX for
# `jaxlens --help`, which builds this parser.

# Numbers of the command line that are not scene keys (a noise sigma, a gain, a mass, a
# distance in metres) lie in [1e-30, 1e30]: their squares and inverses stay within
# float64 (1e-300 as a noise sigma made every weight infinite), and no image or black
# hole needs more (the observable universe is 9e26 m across, its mass 1e23 M_sun).
SMALLEST, LARGEST = 1e-30, MAGNITUDE_MAX
# A Gaussian PSF of 1000 pixels or more: the model is rendered with a margin of
# 4 sigma on each side (8000 pixels more each way), and a ring blurred over thousands
# of pixels is not there to fit.
PSF_SIGMA_MAX = 1000.0


def _noise(text):
    if text in ("gaussian", "poisson"):
        return text
    try:
        return _number_in("--noise", text, SMALLEST, LARGEST, "a noise sigma in pixel values")
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{cut(repr(text))} is not gaussian, poisson or a noise sigma from "
            f"{SMALLEST:g} to {LARGEST:g} (pixel values)"
        ) from None


def _number(name, text):
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{name} {cut(repr(text))} is not a number") from None


def _number_in(name, text, lo, hi, unit, *, open_=False):
    """The number of an option, checked to be finite and in [lo, hi] (`open_`: in
    (lo, hi))."""
    value = _number(name, text)
    if not (math.isfinite(value) and (lo < value < hi if open_ else lo <= value <= hi)):
        valid = f"in ({lo:g}, {hi:g})" if open_ else f"from {lo:g} to {hi:g}"
        raise ValueError(f"{name} {cut(repr(text))} is not valid: expected a number "
                         f"{valid} ({unit})")  # fmt: skip
    return value


def _positive(name, unit):
    """A number option in [SMALLEST, LARGEST]."""
    return lambda text: _number_in(name, text, SMALLEST, LARGEST, unit)


def _held(item: str) -> tuple[str, float]:
    """`--fix NAME=VALUE`: the parameter's name (without `_deg`) and value (radians for
    `_deg`), checked against the range the fit keeps the parameter in (distance > 1,
    FOV in (0, 180) degrees, ...) and at most `MAGNITUDE_MAX` in magnitude."""
    from ._fit.params import is_angle, parameter

    shown = cut(repr(item))
    name, sep, text = item.partition("=")
    name, text = name.strip(), text.strip()
    if not sep:
        raise ValueError(f"--fix {shown} is not NAME=VALUE")
    value = _number(f"--fix {name}", text)
    deg = name.endswith("_deg")
    base = name[:-4] if deg else name
    try:
        p = parameter(base)
        if deg and not is_angle(base):
            raise ValueError(f"{base} is not an angle: give it without _deg ({p.unit})")
    except ValueError as e:
        raise ValueError(f"--fix {shown}: {e}") from None
    t = p.transform
    lo = -math.inf if t.kind == "free" else t.lo
    hi = t.hi if t.kind == "between" else math.inf
    if base == "psf_sigma":
        hi = PSF_SIGMA_MAX
    if deg:
        lo, hi = math.degrees(lo), math.degrees(hi)
    inside = lo < value < hi
    if not (math.isfinite(value) and inside and abs(value) <= MAGNITUDE_MAX):
        if math.isfinite(lo) and math.isfinite(hi):
            valid = f"a number in ({lo:.12g}, {hi:.12g})"
        else:
            valid = f"a number > {lo:.12g}" if math.isfinite(lo) else "a finite number"
        unit = "degrees" if deg else p.unit
        big = f", at most {MAGNITUDE_MAX:g} in magnitude" if inside else ""
        raise ValueError(f"--fix {name}={cut(text)} is not valid: expected {valid}"
                         f"{f' ({unit})' if unit else ''}{big}")  # fmt: skip
    return base, math.radians(value) if deg else value


def register(sub):
    p = sub.add_parser(
        "fit",
        help="fit distance, field of view and source position to an image of a lensed star",
        description="Fit the camera distance (units of R_S), horizontal field of view and the "
        "star's position to an image of a lensed Gaussian star: a ring, or arcs from a star "
        "off the axis (pixel values as linear intensity: 8/16-bit files decoded as "
        "--transfer says; float files as stored; channels averaged; FITS through astropy, "
        "its WCS fixing the field of view).",
    )
    p.add_argument("images", nargs="+", metavar="image",
                   help="the image (PNG, EXR, TIFF, FITS, ...); several are fitted in turn "
                   "with the same options, one report (or JSON line) each, the compiled "
                   "programs reused for images of one size")  # fmt: skip
    blur = p.add_mutually_exclusive_group()
    blur.add_argument(
        "--psf-sigma-px",
        type=str,
        default=None,
        help="a Gaussian point-spread function of this width (pixels, in (0, 1000))",
    )
    blur.add_argument("--psf", default=None, help="a point-spread function image (file)")
    blur.add_argument(
        "--fit-psf", action="store_true", help="fit the width of a Gaussian point-spread function"
    )
    p.add_argument(
        "--noise",
        type=_noise,
        default="gaussian",
        help="noise model: gaussian (sigma estimated from the image, the default), poisson, "
        "or the Gaussian sigma itself in pixel values (e.g. 0.01; from 1e-30 to 1e30)",
    )
    p.add_argument(
        "--gain",
        type=str,
        default=None,
        help="Poisson: counts per unit of pixel value, from 1e-30 to 1e30 (estimated if not given)",
    )
    p.add_argument(
        "--transfer",
        choices=("auto", "srgb", "linear"),
        default="auto",
        help="how an 8/16-bit file's values are decoded: srgb (from sRGB to linear), linear "
        "(as stored), auto (the default: the file's tag, and for an untagged file both "
        "decodings tried, the one whose residuals pass the noise test kept)",
    )
    p.add_argument(
        "--pixels",
        choices=("auto", "area", "point"),
        default="auto",
        help="how the pixels sampled the light: area (averaged over each pixel, as a "
        "camera's), point (the light at each pixel's centre, as jaxlens render with one "
        "ray a pixel), auto (the default: what a file jaxlens wrote records, else area)",
    )
    p.add_argument("--mask", default=None, help="mask image: pixels > 0.5 are left out")
    p.add_argument(
        "--fix",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="hold a parameter (distance, fov_deg, source_lon_deg, source_lat_deg, "
        "sigma_deg, brightness, floor, ...) at a value; repeatable",
    )
    p.add_argument(
        "--star-sigma-deg",
        type=str,
        default=None,
        help="the star's Gaussian width in degrees, in (0, 180), when known (fitted otherwise)",
    )
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--mass-msun", "--mass", dest="mass", metavar="MSUN", type=str,
                       help="mass of the hole in solar masses (1e-30 to 1e30): D in "
                       "metres")  # fmt: skip
    scale.add_argument(
        "--distance-m",
        type=str,
        default=None,
        help="camera distance in metres (1e-30 to 1e30): the mass",
    )
    p.add_argument(
        "--source-distance",
        metavar="LENGTH",
        default=None,
        help="the star's distance behind the hole, a number with a unit (m, km, au, pc, "
        "kpc, Mpc, ly; e.g. 8.5kpc): with --distance-m (the observer's distance) the "
        "source sphere's radius follows the fitted D and the mass is measured; with "
        "--mass-msun it is fixed and the observer's distance is measured. In units of "
        "R_S (e.g. 4e4Rs): the radius itself, fixed. Default: at infinity",
    )
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    _multi.add_options(p)
    p.set_defaults(run=run)


def run(args):
    index, count = _multi.join() if args.distributed else (0, 1)
    from ._camera import Camera
    from ._fit import DEFAULT_FREE, fit as fit_scene
    from ._scene import Scene, scene_table_keys
    from ._sky import GaussianStar, Uniform

    sigma = None
    if args.star_sigma_deg is not None:
        key = scene_table_keys("sky", "star")["sigma_deg"]
        value = _number("--star-sigma-deg", args.star_sigma_deg)
        sigma = math.radians(_schema.coerce("", "--star-sigma-deg", value, key, equals=" "))
    mass = _positive("--mass-msun", "solar masses")(args.mass) if args.mass is not None else None
    dist_m = None
    if args.distance_m is not None:
        dist_m = _positive("--distance-m", "metres")(args.distance_m)
    source = _source(args.source_distance, mass, dist_m)

    psf, free = None, list(DEFAULT_FREE)
    if args.psf_sigma_px is not None:
        psf = _number_in("--psf-sigma-px", args.psf_sigma_px, 0.0, PSF_SIGMA_MAX, "pixels",
                         open_=True)  # fmt: skip
    elif args.fit_psf:
        psf = 1.0
        free.append("psf_sigma")
    elif args.psf is not None:
        from ._fit.observation import read_observation

        psf = read_observation(args.psf)
    init = {}
    if sigma is not None:
        init["sigma"] = sigma
        free.remove("sigma")
    for item in args.fix:
        name, value = _held(item)
        init[name] = value
        if name in free:
            free.remove(name)
    gain = None
    if args.gain is not None:
        gain = _positive("--gain", "counts a unit of pixel value")(args.gain)
    model = Scene(Camera(20.0, 1.0, 8, 8), GaussianStar(0.01) + Uniform(0.0))
    images = args.images
    several = len(images) > 1

    def one(i) -> tuple[str, bool]:
        """Image `i`'s report (or JSON line), and whether it failed."""
        image = images[i]
        which = f" ({i + 1} of {len(images)})" if several else ""
        if count > 1:  # process 0's status line
            which = f" ({i + 1} of {len(images)}, over {count} processes)"
        cli.status(f"fitting {image}{which} (compiling on first use)")
        try:
            fit = fit_scene(model, image, free=free, psf=psf, noise=args.noise, gain=gain,
                            mask=args.mask, init=init or None, transfer=args.transfer,
                            pixels=args.pixels, source_distance=source,
                            progress=lambda text: cli.status(f"fitting {image}{which}: "
                                                             f"{text}"))  # fmt: skip
        except (ValueError, OSError) as e:
            if not several:
                raise
            # One bad image among several: said on its own line, the others go on.
            if args.json:
                return json.dumps({"image": image, "error": cli.one_line(e)}), True
            return f"fit of {image}\nerror: {cli.one_line(e)}\n", True
        return _report(args, image, fit, mass, dist_m), False

    failed = 0
    if args.distributed:
        # Each process fits every `count`-th image and posts each result to the job's
        # key-value store; process 0, its own share done, prints them in order.
        for i in _multi.share(len(images), index, count):
            text, bad = one(i)
            _multi.post(f"fit/{i}", f"{int(bad)}{text}")
        if index != 0:
            return 0
        cli.status("waiting for the other processes' fits")
        for i in range(len(images)):
            text = _multi.collect(f"fit/{i}")
            cli.stop_status()
            print(text[1:], flush=True)
            failed += text[:1] == "1"
    else:
        for i in range(len(images)):
            text, bad = one(i)
            cli.stop_status()
            print(text, flush=True)
            failed += bad
    if failed:
        cli.stop_status()
        print(f"jaxlens fit: error: {failed} of {len(images)} images could not be "
              "fitted (see their lines)", file=sys.stderr)  # fmt: skip
        return 2
    return 0


def _source(text, mass, dist_m):
    """`--source-distance`'s `SourceDistance` (None without it): a length in R_S is the
    radius; a length in metres is the distance behind the hole, which needs the
    observer's distance (`--distance-m`) or the mass (`--mass-msun`)."""
    if text is None:
        return None
    from ._fit import SourceDistance
    from ._fit.units import parse_length

    length = parse_length(text, name="--source-distance")
    try:
        if length.in_rs:
            return SourceDistance(radius=length.value)
        if dist_m is None and mass is None:
            raise ValueError(
                f"--source-distance {cut(repr(text))} is a distance behind the hole: give "
                "the observer's distance (--distance-m) to measure the mass, or the mass "
                "(--mass-msun) to measure the distance, or the source sphere's radius in "
                "units of R_S (e.g. 4e4Rs)"
            )
        if dist_m is not None:
            return SourceDistance(behind=length.metres, observer=dist_m)
        return SourceDistance(behind=length.metres, mass=mass)
    except ValueError as e:
        if str(e).startswith("--source-distance"):
            raise
        raise ValueError(f"--source-distance {cut(repr(text))}: {e}") from None


def _report(args, image, fit, mass, dist_m) -> str:
    """One image's result: the readable report (the file's name, then `Fit.summary`
    with the given mass or distance), or one line of JSON (`Fit.to_dict`, the same)."""
    if args.json:
        out = {"image": image, **fit.to_dict(mass_msun=mass, distance_m=dist_m)}
        return json.dumps(_finite(out))
    text = f"fit of {image}\n{fit.summary(mass_msun=mass, distance_m=dist_m)}"
    return text + ("\n" if len(args.images) > 1 else "")


def _finite(d):
    """JSON has no NaN or infinity: such values become null."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}
