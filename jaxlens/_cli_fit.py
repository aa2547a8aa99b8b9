"""`jaxlens fit`: the camera distance and field of view from an image of an Einstein ring."""

import json
import math
import sys


def _positive(name):
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{name} {text!r} is not a number") from None
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} {text!r} must be a finite number > 0")
        return value

    return parse


def register(sub):
    p = sub.add_parser(
        "fit",
        help="fit distance and field of view to an image of an Einstein ring",
        description="Fit the camera distance (units of R_S) and horizontal field of view to "
        "an image of a star exactly behind the hole (linear pixel values; integer formats "
        "read as stored, normalised to [0, 1]; channels averaged).",
    )
    p.add_argument("image", help="the image (PNG, EXR, TIFF, ...)")
    p.add_argument(
        "--star-sigma-deg",
        type=str,
        default=None,
        help="the star's Gaussian width in degrees, when known (fitted otherwise)",
    )
    scale = p.add_mutually_exclusive_group()
    scale.add_argument(
        "--mass", type=str, default=None, help="mass of the hole in solar masses: D in metres"
    )
    scale.add_argument(
        "--distance-m", type=str, default=None, help="camera distance in metres: the mass"
    )
    p.add_argument("--json", action="store_true", help="end with one line of JSON")
    p.set_defaults(run=run)


def run(args):
    sigma = None
    if args.star_sigma_deg is not None:
        sigma_deg = _positive("--star-sigma-deg")(args.star_sigma_deg)
        if not sigma_deg < 180.0:
            raise ValueError(f"--star-sigma-deg {args.star_sigma_deg} must be below 180")
        sigma = math.radians(sigma_deg)
    mass = _positive("--mass")(args.mass) if args.mass is not None else None
    dist_m = _positive("--distance-m")(args.distance_m) if args.distance_m is not None else None

    from ._fit import fit_ring

    if sys.stderr.isatty():  # a fit is silent for ~20 s, most of it compiling
        print(f"jaxlens fit: fitting {args.image} (compiling on first use) ...", file=sys.stderr)
    fit = fit_ring(args.image, star_sigma=sigma)
    out = fit.to_dict()
    lines = [f"fit of {args.image}", fit.summary()]
    if mass is not None:
        d_m, d_m_err = fit.distance_m(mass)
        out.update(mass_msun=mass, distance_m=d_m, distance_m_err=d_m_err)
        lines.append(f"distance      = {d_m:.6g} +- {d_m_err:.2g} m (mass {mass:g} M_sun)")
    if dist_m is not None:
        m, m_err = fit.mass_msun(dist_m)
        out.update(distance_m=dist_m, mass_msun=m, mass_msun_err=m_err)
        lines.append(f"mass          = {m:.6g} +- {m_err:.2g} M_sun (distance {dist_m:g} m)")
    if args.json:
        print(json.dumps(_finite(out)))
    else:
        print("\n".join(lines))
    return 0


def _finite(d):
    """JSON has no NaN or infinity: such values become null."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}
