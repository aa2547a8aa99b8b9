"""`jaxlens fit`: the camera distance, field of view and source position from an image of
a lensed star (a ring, or arcs from a star off the axis)."""

import argparse
import json
import math
import sys

from . import _multi


def _noise(text):
    if text in ("gaussian", "poisson"):
        return text
    try:
        sigma = float(text)
    except ValueError:
        sigma = math.nan
    if not (math.isfinite(sigma) and sigma > 0):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not gaussian, poisson or a noise sigma > 0 (pixel values)"
        )
    return sigma


def _number(name, text):
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{name} {text!r} is not a number") from None


def _positive(name):
    def parse(text):
        value = _number(name, text)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} {text!r} must be a finite number > 0")
        return value

    return parse


def register(sub):
    p = sub.add_parser(
        "fit",
        help="fit distance, field of view and source position to an image of a lensed star",
        description="Fit the camera distance (units of R_S), horizontal field of view and the "
        "star's position to an image of a lensed Gaussian star: a ring, or arcs from a star "
        "off the axis (pixel values as linear intensity: 8/16-bit files tagged sRGB or "
        "untagged, as PNG and JPEG are by default, decoded from sRGB; float files and files "
        "tagged linear as stored; channels averaged; FITS through astropy, its WCS fixing "
        "the field of view).",
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
        help="a Gaussian point-spread function of this width (pixels)",
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
        "or the Gaussian sigma itself in pixel values (e.g. 0.01)",
    )
    p.add_argument(
        "--gain",
        type=str,
        default=None,
        help="Poisson: counts per unit of pixel value (estimated if not given)",
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
        help="the star's Gaussian width in degrees, when known (fitted otherwise)",
    )
    scale = p.add_mutually_exclusive_group()
    scale.add_argument("--mass-msun", "--mass", dest="mass", metavar="MSUN", type=str,
                       help="mass of the hole in solar masses: D in metres")  # fmt: skip
    scale.add_argument(
        "--distance-m", type=str, default=None, help="camera distance in metres: the mass"
    )
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    _multi.add_options(p)
    p.set_defaults(run=run)


def run(args):
    index, count = _multi.join() if args.distributed else (0, 1)
    sigma = None
    if args.star_sigma_deg is not None:
        sigma_deg = _positive("--star-sigma-deg")(args.star_sigma_deg)
        if not sigma_deg < 180.0:
            raise ValueError(f"--star-sigma-deg {args.star_sigma_deg} must be below 180")
        sigma = math.radians(sigma_deg)
    mass = _positive("--mass-msun")(args.mass) if args.mass is not None else None
    dist_m = _positive("--distance-m")(args.distance_m) if args.distance_m is not None else None

    from ._camera import Camera
    from ._fit import DEFAULT_FREE, fit as fit_scene
    from ._fit.params import split_name
    from ._scene import Scene
    from ._sky import GaussianStar, Uniform

    psf, free = None, list(DEFAULT_FREE)
    if args.psf_sigma_px is not None:
        psf = _positive("--psf-sigma-px")(args.psf_sigma_px)
    elif args.fit_psf:
        psf = 1.0
        free.append("psf_sigma")
    elif args.psf is not None:
        from ._fit.pixels import read_observation

        psf = read_observation(args.psf)
    init = {}
    if sigma is not None:
        init["sigma"] = sigma
        free.remove("sigma")
    for item in args.fix:
        name, sep, text = item.partition("=")
        name = name.strip()
        value = _finite_number(f"--fix {item}", text) if sep else None
        if value is None:
            raise ValueError(f"--fix {item!r} is not NAME=VALUE")
        if name.endswith("_deg"):
            name, value = name[:-4], math.radians(value)
        try:
            split_name(name)
        except ValueError as e:
            raise ValueError(f"--fix {item!r}: {e}") from None
        init[name] = value
        if name in free:
            free.remove(name)
    gain = _positive("--gain")(args.gain) if args.gain is not None else None
    from . import cli

    model = Scene(Camera(20.0, 1.0, 8, 8), GaussianStar(0.01) + Uniform(0.0))
    images = args.images
    several = len(images) > 1

    def one(i) -> tuple[str, bool]:
        """Image `i`'s report (or JSON line), and whether it failed."""
        image = images[i]
        which = f" ({i + 1} of {len(images)})" if several else ""
        if count > 1:  # process 0's status line
            which = f" ({i + 1} of {len(images)}, over {count} processes)"
        cli.status(f"fitting {image}{which} (compiling on first use)")  # ~30 s, most compiling
        try:
            fit = fit_scene(model, image, free=free, psf=psf, noise=args.noise, gain=gain,
                            mask=args.mask, init=init or None)  # fmt: skip
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


def _report(args, image, fit, mass, dist_m) -> str:
    """One image's result: the readable report, or one line of JSON."""
    out = {"image": image, **fit.to_dict()}
    lines = [f"fit of {image}", fit.summary()]
    if mass is not None:
        d_m, d_m_err = fit.distance_m(mass)
        out.update(mass_msun=mass, distance_m=d_m, distance_m_err=d_m_err)
        lines.append(f"distance      = {d_m:.6g} +- {d_m_err:.2g} m (mass {mass:g} M_sun)")
    if dist_m is not None:
        m, m_err = fit.mass_msun(dist_m)
        out.update(distance_m=dist_m, mass_msun=m, mass_msun_err=m_err)
        lines.append(f"mass          = {m:.6g} +- {m_err:.2g} M_sun (distance {dist_m:g} m)")
    if args.json:
        return json.dumps(_finite(out))
    return "\n".join(lines) + ("\n" if len(args.images) > 1 else "")


def _finite_number(what, text):
    value = _number(what, text)
    if not math.isfinite(value):
        raise ValueError(f"{what} {text!r} must be finite")
    return value


def _finite(d):
    """JSON has no NaN or infinity: such values become null."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}
