"""`jaxlens render`: one image of a scene."""

import math
import time

from . import _io
from ._camera import Camera
from ._render import render
from ._sky import DefaultSky, GaussianStar, Uniform


def _size(text):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size {text!r} is not WxH, e.g. 1280x720") from None
    if w < 1 or h < 1:
        raise ValueError(f"--size {text!r}: width and height must be >= 1")
    return w, h


def register(sub):
    p = sub.add_parser("render", help="render an image of the black hole")
    p.add_argument("-o", "--output", required=True, help="output image (.png, .jpg, .exr, .hdr)")
    p.add_argument("--distance", type=float, default=20.0, help="camera distance, R_S (default 20)")
    p.add_argument("--fov", type=float, default=60.0, help="horizontal field of view, degrees")
    p.add_argument("--size", default="960x540", help="WxH in pixels (default 960x540)")
    p.add_argument("--sky", default="default", help="star | default (procedural sky + star)")
    p.add_argument("--star-sigma-deg", type=float, default=1.0, help="star Gaussian sigma, degrees")
    p.add_argument("--star-brightness", type=float, default=1.0, help="star peak brightness")
    p.add_argument("--floor", type=float, default=0.0, help="uniform sky level")
    p.add_argument("--supersample", type=int, default=2, help="k x k samples a pixel")
    p.add_argument("--exposure", type=float, default=0.0, help="exposure in stops (PNG/JPEG)")
    p.set_defaults(run=run)


def run(args):
    w, h = _size(args.size)
    if not (0.0 < args.fov < 180.0):
        raise ValueError(f"--fov {args.fov} must be in (0, 180) degrees")
    camera = Camera(args.distance, math.radians(args.fov), w, h, supersample=args.supersample)
    star = GaussianStar(math.radians(args.star_sigma_deg), args.star_brightness)
    if args.sky == "star":
        sky = star
    elif args.sky == "default":
        sky = DefaultSky() + star
    else:
        raise ValueError(f"--sky {args.sky!r} is not one of: star, default")
    if args.floor:
        sky = sky + Uniform(args.floor)
    t = time.perf_counter()
    img = render(camera, sky)
    path = _io.write_image(args.output, img, exposure=args.exposure)
    print(
        f"wrote {path} ({w}x{h}, D = {args.distance:g} R_S, FOV = {args.fov:g} deg, "
        f"{time.perf_counter() - t:.1f} s)"
    )
    return 0
