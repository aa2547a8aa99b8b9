"""`jaxlens animate`: an animated GIF or an MP4 video of a camera path (approach, orbit,
pan, zoom), and optionally its frames as image files. Frames are rendered in batched
compiled calls of one size and streamed to the files as they come."""

import math
import time
from pathlib import Path

import numpy as np

from . import _io, _multi, _schema, cli
from ._cli_render import add_scene_options, pixel_dtype, scene_dict
from ._schema import ANIMATION_PATHS, ANIMATION_RANGES

# `_scene` (and with it JAX) is imported in the functions that run the command: at
# module level it would load JAX for `jaxlens --help`, which builds this parser.

FRAME_FORMATS = ("png", "jpg", "exr", "hdr")


def register(sub):
    p = sub.add_parser(
        "animate",
        help="render an animation (frames and a GIF or MP4) of a camera path",
        description="Render the frames of a camera path into an animated GIF (-o NAME.gif) "
        "or an H.264 MP4 video (-o NAME.mp4, needs PyAV: pip install 'jaxlens-bh[video]'), "
        "and, with --frames-dir, as image files too. Frames are rendered in groups and "
        "written as they come: memory holds one group, not the animation. Paths: approach "
        "(distance, R_S, geometric steps), orbit (camera position around the hole, "
        "degrees), pan (yaw, degrees), zoom (FOV, degrees, geometric). Options override "
        "the scene file's [animation] table.",
    )
    add_scene_options(p, size_default="480x270", supersample_default=2)
    _multi.add_options(p)
    p.add_argument("--path", choices=ANIMATION_PATHS, help="camera path (default approach)")
    p.add_argument("--frames", type=int, help="number of frames, 1 to 10000 (default 24)")
    p.add_argument("--start", type=float, help="first value of the path (see above: a "
                   "distance in (1, 1e30], a FOV in (0, 180), an angle with |angle| <= "
                   "1e30)")  # fmt: skip
    p.add_argument("--stop", type=float, help="last value of the path")
    p.add_argument("--fps", type=float, help="frames a second of the GIF or MP4, in (0, 1000) "
                   "(default 12)")  # fmt: skip
    p.add_argument("--frames-dir", help="also write each frame as an image file into this "
                   "folder (made if missing; frame_0000.png, ...). The frames an earlier run "
                   "wrote there, as recorded in its hidden .jaxlens-frames.json, are replaced "
                   "or removed; other files are never touched, and one with a new frame's "
                   "name is an error")  # fmt: skip
    p.add_argument("--frame-format", choices=FRAME_FORMATS, default="png",
                   help="file format of the frames (default png)")  # fmt: skip
    p.set_defaults(run=run, kept=kept_frames)


def path_values(path: str, start: float, stop: float, frames: int) -> np.ndarray:
    """The values a camera path steps through: distances (R_S) for `approach` and FOVs
    (degrees) for `zoom` in geometric steps, angles (degrees) for `orbit` and `pan` in
    even steps (a full orbit leaves out the repeated last frame)."""
    if path in ("approach", "zoom"):
        return np.geomspace(start, stop, frames)
    full = path == "orbit" and math.isclose(abs(stop - start), 360.0) and frames > 1
    return np.linspace(start, stop, frames, endpoint=not full)


def _check_path(args, path: str, start: float, stop: float) -> None:
    """The first and last value of a camera path against the scene key they stand for:
    a distance (R_S) for `approach`, a FOV (degrees) for `zoom`, an angle (degrees) for
    `orbit` (the camera's azimuth) and `pan` (its yaw). The message names the option,
    or the scene file's key where the value is the file's."""
    from ._scene import CAMERA_KEYS

    key = CAMERA_KEYS[{"approach": "distance", "zoom": "fov_deg", "orbit": "azimuth_deg",
                       "pan": "yaw_deg"}[path]]  # fmt: skip
    for name, v in (("start", start), ("stop", stop)):
        if getattr(args, name) is not None:
            _schema.coerce("", f"--{name}", v, key, equals=" ")
        else:
            _schema.coerce(f"{args.scene}: [animation] ({path})", name, v, key)


def run(args):
    cli.enable_x64()
    index, count = _multi.join() if args.distributed else (0, 1)

    import jaxlens as jl  # the public functions, looked up when the command runs

    out = cli.output_file(args.output)  # its folder is made once the arguments are checked
    video = out.suffix.lower() == ".mp4"
    if out.suffix.lower() not in _io.ANIMATION_FORMATS:
        raise ValueError(f"output {str(out)!r} must be a .gif or .mp4 file (the frames go beside "
                         "it)")  # fmt: skip
    if video:
        _io.require_video()  # before the rendering, not after it
    from ._scene import ANIMATION_KEYS

    for flag in ("frames", "fps"):
        if getattr(args, flag) is not None:
            _schema.coerce("", f"--{flag}", getattr(args, flag), ANIMATION_KEYS[flag], equals=" ")
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
    _check_path(args, kind, start, stop)
    width, height = scene["camera"]["width"], scene["camera"]["height"]
    group = frames_per_call(width, height, frames)
    if count > 1:
        # Groups small enough to share out, of at least 2 frames where one process would
        # batch them (a lone frame runs another program, whose pixels differ by an ulp).
        group = max(min(group, 2), frames_per_call(width, height, -(-frames // count)))
    _io.check_render_memory(width, height, group)
    frames_dir = None if args.frames_dir is None else _check_frames_dir(Path(args.frames_dir))

    values = path_values(kind, start, stop, frames)
    dtype = pixel_dtype(args, scene, distances=values if kind == "approach" else (),
                        fovs_deg=values if kind == "zoom" else ())  # fmt: skip
    base = jl.Scene.from_validated(scene, dtype=dtype)
    out = cli.make_output_folder(out)
    if frames_dir is not None:  # its parents; `frame_folder` makes the folder itself
        cli.make_output_folder(frames_dir, folder=frames_dir.parent)
    step = {"approach": jl.approach, "orbit": jl.orbit, "pan": jl.pan, "zoom": jl.zoom}[kind]
    exposure = base.exposure

    def render_group(lo):
        # Frames in groups of the same size (the last padded with its final value), so
        # one compiled program serves them all and only a group is in memory.
        part = values[lo : lo + group]
        padded = np.concatenate([part, np.repeat(part[-1:], group - len(part))])
        cameras = step(base.camera, padded if kind == "approach" else np.radians(padded))
        images = jl.render(base.replace(camera=cameras), progress=False)
        return np.asarray(images)[: len(part)]

    from tqdm.auto import tqdm

    t = time.perf_counter()
    cli.status("rendering the first frames (compiling on first use)")
    write = _io.write_video if video else _io.write_gif
    with tqdm(total=frames, desc="animate", unit="frame", delay=2.0, leave=False,
              disable=index != 0) as bar:  # fmt: skip
        if args.distributed:
            settings = [scene, kind, values.tolist(), str(np.dtype(dtype))]
            stage = _multi.Stage(out, "frames", settings)
            earlier = stage.finished()
            groups = [range(lo, min(lo + group, frames)) for lo in range(0, frames, group)]
            stage.fill(groups, lambda g: render_group(groups[g].start), index, count, bar)
            if index != 0:
                return 0  # process 0 writes the files
            stage.wait(frames, bar)
            rendered = (stage.load(i) for i in range(frames))
        else:
            rendered = (img for lo in range(0, frames, group) for img in render_group(lo))
        with _io.frame_folder(frames_dir, args.frame_format) as save:

            def stream():
                for i, img in enumerate(rendered):
                    save(i, img, exposure=exposure)
                    if not args.distributed:
                        bar.update()
                    yield img

            write(out, stream(), exposure=exposure, fps=fps)
    if args.distributed:
        stage.remove()
    where = f" and {frames} frames in {frames_dir}/" if frames_dir is not None else ""
    cli.stop_status()
    over = f", {count} processes" if count > 1 else ""
    if args.distributed and earlier:
        over += f", {earlier} frames from an earlier run"
    print(f"wrote {out}{where} ({kind} from {start:.12g} to {stop:.12g}, "
          f"{time.perf_counter() - t:.1f} s{over})")  # fmt: skip
    return 0


def kept_frames(args) -> str:
    """What a failed distributed run left for the next: the finished frames."""
    return _multi.kept(args.output, "frames")


# Frames rendered in one call: as many as fit in this many bytes of float32 RGB.
GROUP_BYTES = 256 << 20


def frames_per_call(width: int, height: int, frames: int) -> int:
    """How many frames one render call makes: up to `GROUP_BYTES` of output, at least 1,
    at most `frames`, spread evenly (24 frames in groups of 8, not 10 + 10 + 4)."""
    most = max(1, min(frames, GROUP_BYTES // (width * height * 3 * 4)))
    calls = -(-frames // most)
    return -(-frames // calls)


def _check_frames_dir(folder: Path) -> Path:
    # A missing folder (and its parents) is made once every argument is checked.
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"frames folder {str(folder)!r} exists and is not a folder")
    return folder
