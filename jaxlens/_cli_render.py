"""`jaxlens render`: one image of a scene (a TOML file, command-line options, or both;
options override the file)."""

import argparse
import math
import time
from pathlib import Path

from . import _io, _multi, _schema
from ._messages import cut
from ._schema import DEFAULT_SKY

SKY_CHOICES = "star | default | checker | panorama:PATH | plane:PATH"


def _size(text):
    """`--size WxH`: (width, height), each checked against the scene file's keys."""
    from ._scene import CAMERA_KEYS

    shown = cut(repr(text))
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--size {shown} is not WxH with whole numbers, e.g. 1280x720") from None
    if w < 1 or h < 1:
        raise ValueError(f"--size {shown}: width and height must be >= 1 pixel")
    for name, v in (("width", w), ("height", h)):
        _schema.coerce(f"--size {shown}:", name, v, CAMERA_KEYS[name], equals=" ")
    return w, h


def _sky_layers(text) -> list[dict]:
    kind, _, path = text.partition(":")
    if kind in ("panorama", "plane"):
        if not path:
            raise ValueError(f"--sky {text!r}: give the image as {kind}:PATH")
        return [{"type": kind, "path": str(Path(path)), "_base": "."}]
    if path or kind not in ("star", "default", "checker"):
        raise ValueError(f"--sky {text!r} is not one of: {SKY_CHOICES}")
    if kind == "default":
        return [dict(layer) for layer in DEFAULT_SKY]
    return [{"type": kind}]


class _SceneKeys(argparse.Action):
    """`--scene-keys`: print the scene-file schema and exit (like `--help`)."""

    def __call__(self, parser, namespace, values, option_string=None):
        from ._scene import scene_keys_text  # imports the sky and effect modules

        print(scene_keys_text())
        parser.exit()


def add_scene_options(p, *, size_default: str, supersample_default: int):
    """The options `render` and `animate` share (each overrides the scene file)."""
    p.add_argument("scene", nargs="?", help="TOML scene file (its tables and keys: "
                   "--scene-keys)")  # fmt: skip
    p.add_argument("--scene-keys", action=_SceneKeys, nargs=0,
                   help="print every table and key a scene file takes, with defaults and "
                   "valid values, and exit")  # fmt: skip
    p.add_argument("-o", "--output", required=True, help="output file")
    p.add_argument(
        "--distance", type=float, help="camera distance, units of R_S, in (1, 1e30] (default 20)"
    )
    # Degrees are named in the option (as in the scene file's keys); R_S and radians,
    # the library's own units, are not. The short old names stay as aliases.
    p.add_argument("--fov-deg", "--fov", dest="fov", metavar="DEG", type=float,
                   help="horizontal field of view, degrees, in (0, 180) (default 60)")  # fmt: skip
    p.add_argument("--size", help=f"WxH in pixels, each 1 to 1048575 (default {size_default})")
    p.add_argument("--sky", help=f"{SKY_CHOICES} (default: default, a procedural sky and a star)")
    p.add_argument(
        "--star-sigma-deg",
        type=float,
        help="Gaussian sigma of the star, degrees, in (0, 180) (default 1)",
    )
    p.add_argument(
        "--star-brightness", type=float, help="peak brightness of the star, |b| <= 1e30 (default 1)"
    )
    p.add_argument("--floor", type=float, help="uniform sky level added to the sky, |v| <= 1e30")
    p.add_argument("--supersample", type=int, help=f"k x k samples a pixel, k from 1 to 64 "
                   f"(default {supersample_default})")  # fmt: skip
    p.add_argument("--sampling", choices=("uniform", "gauss"), help="uniform: k x k point "
                   "samples a pixel (default); gauss: area-exact Gauss-Legendre cells")  # fmt: skip
    p.add_argument(
        "--exposure", type=float, help="exposure in stops, PNG/JPEG, in (-100, 100) (default 0)"
    )
    for name, what in (("yaw", "view turned right"), ("pitch", "view turned up"),
                       ("roll", "view turned about the line of sight")):  # fmt: skip
        p.add_argument(f"--{name}-deg", f"--{name}", dest=name, metavar="DEG", type=float,
                       help=f"{what}, degrees, |angle| <= 1e30")  # fmt: skip
    p.add_argument(
        "--accuracy", type=float, help="ray-map accuracy, radians, in (0, 0.1) (default 1e-8)"
    )
    p.add_argument("--source-distance", type=float, metavar="R",
                   help="the sky on a transparent sphere of radius R about the hole, units of "
                   "R_S, in (1, 1e30] (default: the sky at infinity)")  # fmt: skip
    p.add_argument("--source-plane", type=float, metavar="L",
                   help="the sky on the plane L behind the hole, perpendicular to the line of "
                   "sight, units of R_S, in (0, 1e30] (default: the sky at infinity)")  # fmt: skip
    p.add_argument(
        "--float64", action="store_true", help="compute pixels in float64 (default float32)"
    )
    p.set_defaults(_size_default=size_default, _supersample_default=supersample_default)


def scene_dict(args) -> dict:
    """The validated scene: the file (if any), then the command-line options over it.
    Each option is checked first against the scene key it sets, so that its message
    names the option and its value (`--distance -inf is not valid: expected ...`)."""
    from ._scene import (
        CAMERA_KEYS,
        EFFECTS_KEYS,
        OUTPUT_KEYS,
        TOP_KEYS,
        read_scene_file,
        validate,
    )

    star, uniform = _schema.keys("sky", "star"), _schema.keys("sky", "uniform")
    options = [
        ("--distance", args.distance, CAMERA_KEYS["distance"]),
        ("--fov-deg", args.fov, CAMERA_KEYS["fov_deg"]),
        ("--star-sigma-deg", args.star_sigma_deg, star["sigma_deg"]),
        ("--star-brightness", args.star_brightness, star["brightness"]),
        ("--floor", args.floor, uniform["level"]),
        ("--exposure", args.exposure, OUTPUT_KEYS["exposure"]),
        ("--yaw-deg", args.yaw, CAMERA_KEYS["yaw_deg"]),
        ("--pitch-deg", args.pitch, CAMERA_KEYS["pitch_deg"]),
        ("--roll-deg", args.roll, CAMERA_KEYS["roll_deg"]),
        ("--accuracy", args.accuracy, TOP_KEYS["accuracy"]),
        ("--supersample", args.supersample, CAMERA_KEYS["supersample"]),
        ("--source-distance", args.source_distance, EFFECTS_KEYS["source_distance"]),
        ("--source-plane", args.source_plane, EFFECTS_KEYS["source_plane"]),
    ]
    for flag, value, key in options:
        if value is not None:
            _schema.coerce("", flag, value, key, equals=" ")

    data = read_scene_file(args.scene) if args.scene else {}
    source = args.scene or "command line"
    if any(not isinstance(data.get(t, {}), dict) for t in ("camera", "output", "animation")):
        return validate(data, source=source)  # it says which must be a table
    cam = dict(data.get("camera", {}))
    if not args.scene:
        w, h = _size(args._size_default)
        cam.update(width=w, height=h, supersample=args._supersample_default)
    if args.size is not None:
        cam["width"], cam["height"] = _size(args.size)
    flags = {"distance": "distance", "fov": "fov_deg", "supersample": "supersample",
             "sampling": "sampling",
             "yaw": "yaw_deg", "pitch": "pitch_deg", "roll": "roll_deg"}  # fmt: skip
    for flag, key in flags.items():
        if getattr(args, flag) is not None:
            cam[key] = getattr(args, flag)
    if cam or "camera" in data:
        data["camera"] = cam
    if args.exposure is not None:
        data["output"] = {**data.get("output", {}), "exposure": args.exposure}
    if args.accuracy is not None:
        data["accuracy"] = args.accuracy
    for name in ("source_distance", "source_plane"):
        value = getattr(args, name)
        if value is not None and isinstance(data.get("effects", {}), dict):
            data["effects"] = {**data.get("effects", {}), name: value}
    layers = data.get("sky", [dict(layer) for layer in DEFAULT_SKY])
    if args.sky is not None:
        layers = _sky_layers(args.sky)
    if not isinstance(layers, list):
        layers = [layers]
    star = {}
    if args.star_sigma_deg is not None:
        star["sigma_deg"] = args.star_sigma_deg
    if args.star_brightness is not None:
        star["brightness"] = args.star_brightness
    if star:
        stars = [la for la in layers if isinstance(la, dict) and la.get("type") == "star"]
        if not stars:
            layers.append({"type": "star"})
            stars = layers[-1:]
        for layer in stars:
            layer.update(star)
    if args.floor is not None:
        floors = [la for la in layers if isinstance(la, dict) and la.get("type") == "uniform"]
        for layer in floors:
            layer["level"] = args.floor
        if not floors and args.floor != 0:
            layers.append({"type": "uniform", "level": args.floor})
    data["sky"] = layers
    return validate(data, source=source)


def pixel_dtype(args, scene, *, distances=(), fovs_deg=()):
    """float32 pixels unless --float64, or a distance (R_S) float32 cannot tell from 1
    (1 + 1e-9), or a field of view (degrees) it cannot tell from 0 or 180 (179.99999999):
    values that are valid in the scene but not in float32. `distances` and `fovs_deg`:
    more of them (an animation's path)."""
    import jax.numpy as jnp
    import numpy as np

    cam = scene["camera"]
    d = np.float32([cam["distance"], *distances])
    fov = np.float32(np.radians([cam["fov_deg"], *fovs_deg])).astype(float)
    if args.float64 or not (np.all(d > 1.0) and np.all((fov > 0) & (fov < math.pi))):
        return jnp.float64
    return jnp.float32


def register(sub):
    p = sub.add_parser(
        "render",
        help="render an image of the black hole",
        description="Render what a static camera near a Schwarzschild black hole sees. "
        "Options override the scene file.",
    )
    add_scene_options(p, size_default="960x540", supersample_default=2)
    _multi.add_options(p)
    p.set_defaults(run=run, kept=kept_blocks)


def kept_blocks(args) -> str:
    """What a failed distributed render left for the next: its finished blocks."""
    return _multi.kept(args.output, "blocks")


def run(args):
    from . import cli

    cli.enable_x64()
    index, count = _multi.join() if args.distributed else (0, 1)

    import jaxlens as jl  # the public functions, looked up when the command runs

    out = cli.output_file(args.output)  # its folder is made once the scene is checked
    if out.suffix.lower() in _io.ANIMATION_FORMATS:
        kind = out.suffix[1:].upper()
        raise ValueError(f"output {str(out)!r}: {kind} files are animations; use `jaxlens animate`")
    v = scene_dict(args)
    _io.check_render_memory(v["camera"]["width"], v["camera"]["height"])
    scene = jl.Scene.from_validated(v, dtype=pixel_dtype(args, v))
    out = cli.make_output_folder(out)
    t = time.perf_counter()
    cli.status("rendering (compiling on first use)")
    if args.distributed:
        # Every process renders its share of the blocks into a folder beside the output,
        # named for the scene and its input files (a rerun reuses what a failed one
        # finished of the same work); process 0 puts the image together and writes it.
        from ._render import render_share

        stage = _multi.Stage(out, "blocks", [v, str(scene.camera.dtype)])
        img = render_share(scene, stage, index, count)
        if img is None:
            return 0  # process 0 writes the image
    else:
        img = jl.render(scene)
    cli.status(f"writing {out}")
    # One ray a pixel samples it at its centre; more average it over its area.
    sampling = "point" if scene.camera.supersample == 1 else "area"
    path = _io.write_image(out, img, exposure=scene.exposure, sampling=sampling)
    if args.distributed:
        stage.remove()
    c = v["camera"]
    cli.stop_status()
    over = f", {count} processes" if count > 1 else ""
    print(
        f"wrote {path} ({c['width']}x{c['height']}, D = {c['distance']:.12g} R_S, "
        f"FOV = {c['fov_deg']:.12g} deg, {time.perf_counter() - t:.1f} s{over})"
    )
    return 0
