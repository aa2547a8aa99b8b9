"""Scene files: TOML (read with `tomllib`, no code is executed), validated.

A scene is a camera, a sky (a list of layers that add up) and the accuracy of the ray
map; files may also carry output and animation settings. Every key is optional:

```toml
accuracy = 1e-8            # ray-map interpolation error, radians

[camera]
distance = 20.0            # camera radius, units of R_S (> 1)
fov_deg = 60.0             # horizontal field of view, degrees, in (0, 180)
width = 960                # pixels
height = 540
supersample = 2            # k x k area samples a pixel
yaw_deg = 0.0              # view turned right (+x) ...
pitch_deg = 0.0            # ... up (+y) ...
roll_deg = 0.0             # ... and about the line of sight, degrees
azimuth_deg = 0.0          # camera position around the hole (orbit), degrees
elevation_deg = 0.0

[output]
exposure = 0.0             # stops, applied to PNG/JPEG only

[animation]                # for `jaxlens animate`
path = "approach"          # approach | orbit | pan | zoom
frames = 24
start = 1e5                # approach: distance (R_S); orbit/pan: degrees; zoom: FOV degrees
stop = 3.0
fps = 12.0

[[sky]]                    # layers, summed; without any: "default" plus a "star"
type = "star"              # star | stars | panorama | plane | checker | default | uniform
sigma_deg = 1.0            # Gaussian standard deviation in angular distance, degrees
brightness = 1.0           # peak radiance
lon_deg = 0.0              # position: (0, 0) is exactly behind the hole
lat_deg = 0.0
color = [1.0, 1.0, 1.0]
```

Per layer type (see `SKY_KEYS` for the full list): `stars` takes `count` and `seed`
(random stars) or lists `lon_deg`, `lat_deg` (and a number or a list `brightness`),
with `sigma_deg`; `panorama` takes `path` (relative to the scene file), `brightness`,
`yaw_deg`, `pitch_deg`, `roll_deg`; `plane` takes `path` and either `width_deg` or
`size` and `plane_distance` (units of R_S), plus `brightness` and orientation;
`checker` takes `n_lon`, `n_lat`, `brightness` and orientation; `default` takes
`brightness` and `stars` (true/false); `uniform` takes `level` (a number or RGB).
"""

import math
import tomllib
from pathlib import Path
from typing import Any

import equinox as eqx
import numpy as np

from ._camera import Camera
from ._render import render
from ._sky import (
    AbstractSky,
    Checker,
    DefaultSky,
    GaussianStar,
    Panorama,
    PlaneImage,
    StarField,
    Uniform,
    direction_from_angles,
)

# ------------------------------------------------------------------ the schema
# Each key: (kind, default, check, what is valid). Kinds: "float", "int", "bool",
# "str", "color" (a number or 3 numbers), "floats" (a number or a list of numbers).


def _gt(lo):
    return lambda v: v > lo


def _in(lo, hi):
    return lambda v: lo < v < hi


def _any(v):
    return True


TOP_KEYS = {
    "accuracy": ("float", 1e-8, _in(0.0, 0.1), "a number in (0, 0.1) (radians)"),
}

CAMERA_KEYS = {
    "distance": ("float", 20.0, _gt(1.0), "a finite number > 1 (units of R_S)"),
    "fov_deg": ("float", 60.0, _in(0.0, 180.0), "a number in (0, 180) (degrees)"),
    "width": ("int", 960, _gt(0), "a whole number >= 1 (pixels)"),
    "height": ("int", 540, _gt(0), "a whole number >= 1 (pixels)"),
    "supersample": ("int", 2, _in(0, 65), "a whole number from 1 to 64"),
    "yaw_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "pitch_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "roll_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "azimuth_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "elevation_deg": ("float", 0.0, _any, "a finite number (degrees)"),
}

OUTPUT_KEYS = {
    "exposure": ("float", 0.0, _any, "a finite number (stops)"),
}

ANIMATION_PATHS = ("approach", "orbit", "pan", "zoom")
ANIMATION_KEYS = {
    "path": ("str", "approach", lambda v: v in ANIMATION_PATHS, " | ".join(ANIMATION_PATHS)),
    "frames": ("int", 24, _in(0, 10001), "a whole number from 1 to 10000"),
    "start": ("float", None, _any, "a finite number (R_S for approach, else degrees)"),
    "stop": ("float", None, _any, "a finite number (R_S for approach, else degrees)"),
    "fps": ("float", 12.0, _in(0.0, 1000.0), "a number in (0, 1000) (frames a second)"),
}

# Defaults of start/stop for each animation path.
ANIMATION_RANGES = {
    "approach": (1e5, 3.0),
    "orbit": (0.0, 360.0),
    "pan": (-30.0, 30.0),
    "zoom": (90.0, 10.0),
}

_ORIENT = {
    "yaw_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "pitch_deg": ("float", 0.0, _any, "a finite number (degrees)"),
    "roll_deg": ("float", 0.0, _any, "a finite number (degrees)"),
}
_BRIGHT = {"brightness": ("float", 1.0, lambda v: v >= 0.0, "a finite number >= 0 (scale)")}
_SIGMA = {"sigma_deg": ("float", 1.0, _in(0.0, 180.0), "a number in (0, 180) (degrees)")}

SKY_KEYS: dict[str, dict[str, tuple]] = {
    "star": {
        **_SIGMA,
        "brightness": ("float", 1.0, _any, "a finite number (peak radiance)"),
        "lon_deg": ("float", 0.0, _any, "a finite number (degrees)"),
        "lat_deg": ("float", 0.0, _any, "a finite number (degrees)"),
        "color": ("color", [1.0, 1.0, 1.0], _any, "a number or a list of 3 numbers (RGB)"),
    },
    "stars": {
        "sigma_deg": ("float", 0.15, _in(0.0, 180.0), "a number in (0, 180) (degrees)"),
        "count": ("int", 200, _in(0, 100001), "a whole number from 1 to 100000"),
        "seed": ("int", 0, _any, "a whole number"),
        "lon_deg": ("floats", None, _any, "a list of finite numbers (degrees)"),
        "lat_deg": ("floats", None, _any, "a list of finite numbers (degrees)"),
        "brightness": ("floats", None, _any, "a number or a list of numbers (peak radiance)"),
    },
    "panorama": {
        "path": ("str", None, lambda v: len(v) > 0, "the path of an image file"),
        **_BRIGHT,
        **_ORIENT,
    },
    "plane": {
        "path": ("str", None, lambda v: len(v) > 0, "the path of an image file"),
        "width_deg": ("float", None, _in(0.0, 180.0), "a number in (0, 180) (degrees)"),
        "size": ("float", None, _gt(0.0), "a number > 0 (units of R_S)"),
        "plane_distance": ("float", None, _gt(0.0), "a number > 0 (units of R_S)"),
        **_BRIGHT,
        **_ORIENT,
    },
    "checker": {
        "n_lon": ("int", 24, _in(0, 100001), "a whole number >= 1"),
        "n_lat": ("int", 12, _in(0, 100001), "a whole number >= 1"),
        **_BRIGHT,
        **_ORIENT,
    },
    "default": {**_BRIGHT, "stars": ("bool", True, _any, "true or false")},
    "uniform": {"level": ("color", 0.0, _any, "a number or a list of 3 numbers (radiance)")},
}

SKY_TYPES = tuple(SKY_KEYS)


def _describe(value) -> str:
    return repr(value) if not isinstance(value, str) else f'"{value}"'


def _coerce(where: str, key: str, value, spec) -> Any:
    """Check the type and range of one value; return it in its Python type."""
    kind, _, check, valid = spec
    bad = ValueError(f"{where} {key} = {_describe(value)} is not valid: expected {valid}")

    def number(v):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise bad
        v = float(v)
        if not math.isfinite(v):
            raise bad
        return v

    if kind == "float":
        v = number(value)
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        v = value
    elif kind == "bool":
        if not isinstance(value, bool):
            raise bad
        v = value
    elif kind == "str":
        if not isinstance(value, str):
            raise bad
        v = value
    elif kind == "color":
        if isinstance(value, list):
            if len(value) != 3:
                raise bad
            v = [number(x) for x in value]
        else:
            v = number(value)
        return v
    elif kind == "floats":
        if isinstance(value, list):
            if not value:
                raise bad
            return [number(x) for x in value]
        return number(value)
    else:  # pragma: no cover - schema error
        raise AssertionError(kind)
    if not check(v):
        raise bad
    return v


def _table(where: str, table, keys: dict) -> dict:
    """Validate one TOML table against its keys; return it with defaults filled in."""
    if not isinstance(table, dict):
        raise ValueError(f"{where} must be a table, got {_describe(table)}")
    for key in table:
        if key not in keys:
            raise ValueError(
                f"{where} has an unknown key {key!r}; valid keys: {', '.join(keys) or 'none'}"
            )
    out = {}
    for key, spec in keys.items():
        if key in table:
            out[key] = _coerce(where, key, table[key], spec)
        elif spec[1] is not None:
            out[key] = spec[1]
    return out


DEFAULT_SKY = [{"type": "default"}, {"type": "star"}]


def validate(data: dict, *, source: str = "scene") -> dict:
    """Validate a scene dictionary (as read from TOML); fill in the defaults.

    **Returns:** a dict with `accuracy`, `camera`, `output`, `animation` (tables as
    dicts) and `sky` (a list of layer dicts, each with its `type`). Raises
    `ValueError` naming the table, the key, the value and what is valid.
    """
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a scene must be a table of keys")
    tables = {"camera": CAMERA_KEYS, "output": OUTPUT_KEYS, "animation": ANIMATION_KEYS}
    known = set(TOP_KEYS) | set(tables) | {"sky"}
    for key in data:
        if key not in known:
            raise ValueError(
                f"{source}: unknown key {key!r}; valid keys: {', '.join(sorted(known))}"
            )
    top = {k: v for k, v in data.items() if k in TOP_KEYS}
    out = _table(f"{source}:", top, TOP_KEYS)
    for name, keys in tables.items():
        out[name] = _table(f"{source}: [{name}]", data.get(name, {}), keys)
    anim = out["animation"]
    lo, hi = ANIMATION_RANGES[anim["path"]]
    anim.setdefault("start", lo)
    anim.setdefault("stop", hi)
    layers = data.get("sky", DEFAULT_SKY)
    if isinstance(layers, dict):
        layers = [layers]
    if not isinstance(layers, list) or not layers:
        raise ValueError(f"{source}: sky must be a list of [[sky]] tables, got {_describe(layers)}")
    sky = []
    for i, layer in enumerate(layers):
        where = f"{source}: [[sky]] #{i + 1}"
        if not isinstance(layer, dict):
            raise ValueError(f"{where} must be a table, got {_describe(layer)}")
        kind = layer.get("type")
        if kind not in SKY_KEYS:
            raise ValueError(
                f"{where} type = {_describe(kind)} is not valid: expected one of "
                f"{', '.join(SKY_TYPES)}"
            )
        rest = {k: v for k, v in layer.items() if k not in ("type", "_base")}
        entry = {"type": kind, **_table(f"{where} ({kind})", rest, SKY_KEYS[kind])}
        if "_base" in layer:
            entry["_base"] = layer["_base"]
        _check_layer(where, entry)
        sky.append(entry)
    out["sky"] = sky
    return out


def _check_layer(where, layer):
    kind = layer["type"]
    if kind in ("panorama", "plane") and "path" not in layer:
        raise ValueError(f'{where} ({kind}) needs a path = "IMAGE" (an image file)')
    if kind == "plane":
        has_width = "width_deg" in layer
        has_plane = "size" in layer or "plane_distance" in layer
        if has_width and has_plane:
            raise ValueError(
                f"{where} (plane): give width_deg or size and plane_distance, not both"
            )
        if has_plane and not ("size" in layer and "plane_distance" in layer):
            raise ValueError(f"{where} (plane): size and plane_distance go together")
    if kind == "stars":
        lon, lat = layer.get("lon_deg"), layer.get("lat_deg")
        if (lon is None) != (lat is None):
            raise ValueError(f"{where} (stars): lon_deg and lat_deg go together")
        if lon is not None:
            lon, lat = np.atleast_1d(lon), np.atleast_1d(lat)
            if lon.shape != lat.shape:
                raise ValueError(f"{where} (stars): lon_deg and lat_deg have different lengths "
                                 f"({lon.size} and {lat.size})")  # fmt: skip
            b = layer.get("brightness")
            if isinstance(b, list) and len(b) != lon.size:
                raise ValueError(f"{where} (stars): brightness has {len(b)} values for "
                                 f"{lon.size} stars")  # fmt: skip


def read_scene_file(path) -> dict:
    """Parse a TOML scene file (no validation); paths inside are taken relative to
    the file's folder. Raises `ValueError` naming the file for unreadable files and
    TOML syntax errors."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"scene file {str(path)!r} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"scene file {str(path)!r} is a folder") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scene file {str(path)!r} is not valid TOML: {e}") from None
    except UnicodeDecodeError:
        raise ValueError(f"scene file {str(path)!r} is not a UTF-8 text file") from None
    layers = data.get("sky")
    if isinstance(layers, list):
        for layer in layers:
            if isinstance(layer, dict):
                layer["_base"] = str(path.parent)
    return data


def _layer_sky(layer: dict) -> AbstractSky:
    kind = layer["type"]
    rad = math.radians
    orient = {k[:-4]: rad(layer[k]) for k in ("yaw_deg", "pitch_deg", "roll_deg") if k in layer}
    base = Path(layer.get("_base", "."))
    if kind == "star":
        return GaussianStar(
            rad(layer["sigma_deg"]), layer["brightness"],
            color=np.broadcast_to(np.asarray(layer["color"], float), (3,)),
            lon=rad(layer["lon_deg"]), lat=rad(layer["lat_deg"]),
        )  # fmt: skip
    if kind == "stars":
        sigma = rad(layer["sigma_deg"])
        if "lon_deg" in layer:
            b = layer.get("brightness", 1.0)
            d = direction_from_angles(
                np.radians(np.atleast_1d(layer["lon_deg"])),
                np.radians(np.atleast_1d(layer["lat_deg"])),
            )
            return StarField(d, sigma, np.asarray(b, float))
        b = layer.get("brightness")
        rng = (0.05, 2.0) if b is None else (min(np.atleast_1d(b)), max(np.atleast_1d(b)))
        return StarField.random(layer["count"], seed=layer["seed"], sigma=sigma, brightness=rng)
    if kind == "panorama":
        return Panorama.from_file(base / layer["path"], brightness=layer["brightness"], **orient)
    if kind == "plane":
        from ._io import read_image
        from ._sky import to_rgb

        path = base / layer["path"]
        image = to_rgb(read_image(path), name=f"plane image {str(path)!r}")
        kw = dict(brightness=layer["brightness"], **orient)
        if "size" in layer:
            return PlaneImage.at_distance(image, layer["size"], layer["plane_distance"], **kw)
        width = rad(layer.get("width_deg", 30.0))
        return PlaneImage(image, width, **kw)
    if kind == "checker":
        return Checker(layer["n_lon"], layer["n_lat"], brightness=layer["brightness"], **orient)
    if kind == "default":
        return DefaultSky(layer["brightness"], stars=layer["stars"])
    if kind == "uniform":
        return Uniform(layer["level"])
    raise AssertionError(kind)  # pragma: no cover - validated


def build_sky(layers: list[dict]) -> AbstractSky:
    """The sky of a list of validated layer dicts (summed)."""
    skies = [_layer_sky(layer) for layer in layers]
    sky = skies[0]
    for s in skies[1:]:
        sky = sky + s
    return sky


def build_camera(cam: dict, *, dtype=None) -> Camera:
    """The camera of a validated `[camera]` table."""
    rad = math.radians
    return Camera(
        cam["distance"], rad(cam["fov_deg"]), cam["width"], cam["height"],
        yaw=rad(cam["yaw_deg"]), pitch=rad(cam["pitch_deg"]), roll=rad(cam["roll_deg"]),
        azimuth=rad(cam["azimuth_deg"]), elevation=rad(cam["elevation_deg"]),
        supersample=cam["supersample"], dtype=dtype,
    )  # fmt: skip


class Scene(eqx.Module):
    """A camera, a sky and the ray-map accuracy: everything an image depends on.

    **Fields:** `camera` (a `Camera`), `sky` (an `AbstractSky`), `accuracy`
    (static: interpolation error of the ray map, radians), `exposure` (static:
    stops, for PNG/JPEG output).
    """

    camera: Camera
    sky: AbstractSky
    accuracy: float = eqx.field(static=True, default=1e-8)
    exposure: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if not (0.0 < self.accuracy < 0.1):
            raise ValueError(f"accuracy={self.accuracy!r} must be in (0, 0.1) radians")

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "scene", dtype=None) -> "Scene":
        """A scene from a dictionary of the TOML schema (see the module docstring);
        validated, with errors naming the key, its value and what is valid."""
        v = validate(data, source=source)
        return cls(
            build_camera(v["camera"], dtype=dtype),
            build_sky(v["sky"]),
            v["accuracy"],
            v["output"]["exposure"],
        )

    def render(self, **kwargs) -> np.ndarray:
        """`render(self.camera, self.sky, accuracy=self.accuracy, **kwargs)`."""
        return render(self.camera, self.sky, accuracy=self.accuracy, **kwargs)


def load_scene(path, *, dtype=None) -> Scene:
    """Read and validate a TOML scene file; image paths in it are relative to it."""
    return Scene.from_dict(read_scene_file(path), source=str(path), dtype=dtype)
