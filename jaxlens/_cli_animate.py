"""`jaxlens animate`: a frame sequence and an animated GIF or an MP4 video of a camera
path (approach, orbit, pan, zoom), all frames rendered in batched compiled calls."""

import math
import time
from pathlib import Path

import numpy as np

from . import _io
from ._cli_render import add_scene_options, pixel_dtype, scene_dict
from ._schema import ANIMATION_PATHS, ANIMATION_RANGES

FRAME_FORMATS = ("png", "jpg", "exr", "hdr")


def register(sub):
    p = sub.add_parser(
        "animate",
        help="render an animation (frames and a GIF or MP4) of a camera path",
        description="Render the frames of a camera path and write them as a sequence and an "
        "animated GIF (-o NAME.gif) or an H.264 MP4 video (-o NAME.mp4, needs PyAV: pip "
        "install 'jaxlens[video]'). Paths: approach (distance, R_S, geometric steps), "
        "orbit (camera position around the hole, degrees), pan (yaw, degrees), zoom (FOV, "
        "degrees, geometric). Options override the scene file's [animation] table.",
    )
    add_scene_options(p, size_default="480x270", supersample_default=2)
    p.add_argument("--path", choices=ANIMATION_PATHS, help="camera path (default approach)")
    p.add_argument("--frames", type=int, help="number of frames (default 24)")
    p.add_argument("--start", type=float, help="first value of the path (see above)")
    p.add_argument("--stop", type=float, help="last value of the path")
    p.add_argument("--fps", type=float, help="frames a second of the GIF or MP4 (default 12)")
    p.add_argument("--frames-dir", help="folder for the frames (default: OUTPUT without its "
                   "extension, plus _frames)")  # fmt: skip
    p.add_argument("--frame-format", choices=FRAME_FORMATS, default="png",
                   help="file format of the frames (default png)")  # fmt: skip
    p.set_defaults(run=run)


def path_values(path: str, start: float, stop: float, frames: int) -> np.ndarray:
    """The values a camera path steps through: distances (R_S) for `approach` and FOVs
    (degrees) for `zoom` in geometric steps, angles (degrees) for `orbit` and `pan` in
    even steps (a full orbit leaves out the repeated last frame)."""
    if path in ("approach", "zoom"):
        return np.geomspace(start, stop, frames)
    full = path == "orbit" and math.isclose(abs(stop - start), 360.0) and frames > 1
    return np.linspace(start, stop, frames, endpoint=not full)


def _check(path, start, stop):
    for name, v in (("--start", start), ("--stop", stop)):
        if not math.isfinite(v):
            raise ValueError(f"{name} {v!r} is not valid: expected a finite number")
        if path == "approach" and not v > 1:
            raise ValueError(f"{name} {v!r} is not a valid distance: expected > 1 (units of R_S)")
        if path == "zoom" and not 0 < v < 180:
            raise ValueError(f"{name} {v!r} is not a valid FOV: expected (0, 180) degrees")


def run(args):
    from . import cli

    cli.enable_x64()

    import jaxlens as jl  # the public functions, looked up when the command runs

    out = _io.check_output_path(args.output)
    video = out.suffix.lower() == ".mp4"
    if out.suffix.lower() not in _io.ANIMATION_FORMATS:
        raise ValueError(f"output {str(out)!r} must be a .gif or .mp4 file (the frames go beside "
                         "it)")  # fmt: skip
    if video:
        _io.require_video()  # before the rendering, not after it
    if args.frames is not None and not 1 <= args.frames <= 10000:
        raise ValueError(f"--frames {args.frames} is not valid: expected 1 to 10000")
    if args.fps is not None and not (math.isfinite(args.fps) and 0 < args.fps < 1000):
        raise ValueError(f"--fps {args.fps!r} is not valid: expected a number in (0, 1000)")
    scene = scene_dict(args)
    anim = scene["animation"]
    kind = args.path or anim["path"]
    if args.path is not None and args.path != anim["path"]:
        anim["start"], anim["stop"] = ANIMATION_RANGES[kind]
    start = anim["start"] if args.start is None else args.start
    stop = anim["stop"] if args.stop is None else args.stop
    frames = anim["frames"] if args.frames is None else args.frames
    fps = anim["fps"] if args.fps is None else args.fps
    _io.check_fps(fps, video)  # before rendering: a rate the file format can store
    _check(kind, start, stop)
    _io.check_render_memory(scene["camera"]["width"], scene["camera"]["height"], frames)
    frames_dir = Path(args.frames_dir) if args.frames_dir else out.with_name(out.stem + "_frames")
    if not frames_dir.parent.is_dir():
        raise ValueError(f"frames folder {str(frames_dir)!r}: {str(frames_dir.parent)!r} does "
                         "not exist")  # fmt: skip
    if frames_dir.exists() and not frames_dir.is_dir():
        raise ValueError(f"frames folder {str(frames_dir)!r} exists and is not a folder")

    base = jl.Scene.from_validated(scene, dtype=pixel_dtype(args, scene))
    values = path_values(kind, start, stop, frames)
    step = {"approach": jl.approach, "orbit": jl.orbit, "pan": jl.pan, "zoom": jl.zoom}[kind]
    cameras = step(base.camera, values if kind == "approach" else np.radians(values))
    t = time.perf_counter()
    images = jl.render(base.replace(camera=cameras))
    exposure = base.exposure
    frames_dir.mkdir(exist_ok=True)
    _io.check_output_path(frames_dir / f"frame_0000.{args.frame_format}")
    for i, img in enumerate(images):
        _io.write_image(frames_dir / f"frame_{i:04d}.{args.frame_format}", img, exposure=exposure)
    write = _io.write_video if video else _io.write_gif
    write(out, images, exposure=exposure, fps=fps)
    print(
        f"wrote {out} and {len(images)} frames in {frames_dir}/ ({kind} from {start:g} to "
        f"{stop:g}, {time.perf_counter() - t:.1f} s)"
    )
    return 0
