"""The scene: a camera, a sky and the effects it calls for; and its TOML file format.

A scene file is TOML (read with `tomllib`, no code is executed; at most 1 MiB,
`SCENE_FILE_MAX`), validated key by key; every key is optional:

```toml
accuracy = 1e-8            # ray-map interpolation error, radians

[camera]
distance = 20.0            # camera radius, units of R_S (> 1)
fov_deg = 60.0             # horizontal field of view, degrees, in (0, 180)
width = 960                # pixels
height = 540
supersample = 2            # k x k area samples a pixel
sampling = "uniform"       # uniform | gauss (area-exact: Gauss-Legendre cells, exact edge)
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
type = "star"              # each sky type registers its keys (docs/rendering.md)
sigma_deg = 1.0

[effects]
method = "auto"            # auto | table | weak_field | trace
source_distance = 1e4      # the sky on a sphere of this radius (R_S); absent: at infinity
# source_plane = 200       # or on the plane this far behind the hole (R_S; not with the above)
[effects.motion]
type = "orbit"             # orbit (circular geodesic at the camera's D) | infall
angle_deg = 0.0            # orbit: direction of motion in the image, degrees
[effects.redshift]
mode = "spectral"          # spectral | bolometric
[effects.disk]
r_in = 3.0                 # units of R_S
r_out = 12.0
inclination_deg = 80.0
```

Each table type (a sky layer, a motion, the redshift, the disk) registers its own keys
beside its class (`_schema.register`; `docs/effects.md` and `docs/rendering.md` list
the keys); this module reads the file and assembles them. It imports every module
that registers a table, so the registry's public readers (`scene_table_types`,
`scene_table_keys`) live here, where the registry is complete.
"""

import dataclasses
import math
import tomllib
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from . import _schema
from ._camera import MAX_SIDE, MAX_SUPERSAMPLE, SAMPLINGS, Camera
from ._disk import Disk
from ._effects import AbstractMotion, Redshift
from ._messages import cut, describe, shown
from ._ray_inputs import MAX_DISTANCE, check_real
from ._schema import (
    ANIMATION_PATHS as ANIMATION_PATHS,
    ANIMATION_RANGES as ANIMATION_RANGES,
    DEFAULT_SKY as DEFAULT_SKY,
    Key,
    SceneKey,
    anything,
    greater,
    in_range,
)
from ._sky import AbstractSky
from ._units import length
from ._util import as_float, concrete

METHODS = ("auto", "table", "weak_field", "trace")

TOP_KEYS = {
    "accuracy": Key("float", 1e-8, in_range(0.0, 0.1), "a number in (0, 0.1) (radians)"),
}

CAMERA_KEYS = {
    "distance": Key("float", 20.0, greater(1.0), "a finite number > 1 (units of R_S)"),
    "fov_deg": Key("float", 60.0, in_range(0.0, 180.0), "a number in (0, 180) (degrees)"),
    "width": Key("int", 960, in_range(0, MAX_SIDE + 1), "a whole number (pixels)"),
    "height": Key("int", 540, in_range(0, MAX_SIDE + 1), "a whole number (pixels)"),
    "supersample": Key("int", 2, in_range(0, MAX_SUPERSAMPLE + 1), "a whole number"),
    "sampling": Key("str", "uniform", lambda v: v in SAMPLINGS, " | ".join(SAMPLINGS)),
    "yaw_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "pitch_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "roll_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "azimuth_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "elevation_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
}

OUTPUT_KEYS = {
    # 2^100 keeps float32 pixels finite (2^128 is their largest power of two).
    "exposure": Key("float", 0.0, in_range(-100.0, 100.0), "a number in (-100, 100) (stops)"),
}

ANIMATION_KEYS = {
    "path": Key("str", "approach", lambda v: v in ANIMATION_PATHS, " | ".join(ANIMATION_PATHS)),
    "frames": Key("int", 24, in_range(0, 10001), "a whole number from 1 to 10000"),
    "start": Key("float", None, anything, "a finite number (R_S for approach, else degrees)"),
    "stop": Key("float", None, anything, "a finite number (R_S for approach, else degrees)"),
    "fps": Key("float", 12.0, in_range(0.0, 1000.0), "a number in (0, 1000) (frames a second)"),
}

EFFECTS_KEYS = {
    "method": Key("str", "auto", lambda v: v in METHODS, " | ".join(METHODS)),
    "source_distance": Key("float", None, greater(1.0), "a number > 1 (units of R_S: the "
                           "radius of the sphere the sky lies on; absent: at infinity)"),
    "source_plane": Key("float", None, greater(0.0), "a number > 0 (units of R_S: the "
                        "distance behind the hole of the plane the sky lies on, perpendicular "
                        "to the line of sight; absent: at infinity)"),
}  # fmt: skip
EFFECT_SECTIONS = {"motion": None, "redshift": "redshift", "disk": "thin"}  # default types


def validate(data: dict, *, source: str = "scene") -> dict:
    """Validate a scene dictionary (as read from TOML); fill in the defaults.

    **Returns:** a dict with `accuracy`, `camera`, `output`, `animation` (tables as
    dicts), `sky` (a list of validated layer dicts, each with its `type` and `_base`,
    the folder its paths are relative to) and `effects` (`method` and the validated
    `motion`, `redshift`, `disk` tables present). Raises `ValueError` naming the
    table, the key, the value and what is valid.
    """
    source = cut(source)  # (a file's path, named in every message)
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a scene must be a table of keys")
    tables = {"camera": CAMERA_KEYS, "output": OUTPUT_KEYS, "animation": ANIMATION_KEYS}
    known = set(TOP_KEYS) | set(tables) | {"sky", "effects"}
    for key in data:
        if key not in known:
            raise ValueError(
                f"{source}: unknown key {key!r}; valid keys: {', '.join(sorted(known))}"
            )
    top = {k: v for k, v in data.items() if k in TOP_KEYS}
    out = _schema.table(f"{source}:", top, TOP_KEYS)
    for name, keys in tables.items():
        out[name] = _schema.table(f"{source}: [{name}]", data.get(name, {}), keys)
    anim = out["animation"]
    lo, hi = ANIMATION_RANGES[anim["path"]]
    anim.setdefault("start", lo)
    anim.setdefault("stop", hi)
    layers = data.get("sky", DEFAULT_SKY)
    if isinstance(layers, dict):
        layers = [layers]
    if not isinstance(layers, list) or not layers:
        raise ValueError(f"{source}: sky must be a list of [[sky]] tables, got {describe(layers)}")
    sky = []
    for i, layer in enumerate(layers):
        where = f"{source}: [[sky]] #{i + 1}"
        if not isinstance(layer, dict):
            raise ValueError(f"{where} must be a table, got {describe(layer)}")
        rest = {k: v for k, v in layer.items() if k != "_base"}
        entry = _schema.validate("sky", where, rest)
        entry["_base"] = layer.get("_base", ".")
        sky.append(entry)
    out["sky"] = sky
    effects = data.get("effects", {})
    where = f"{source}: [effects]"
    if not isinstance(effects, dict):
        raise ValueError(f"{where} must be a table, got {describe(effects)}")
    plain = {k: v for k, v in effects.items() if k not in EFFECT_SECTIONS}
    eff = _schema.table(where, plain, EFFECTS_KEYS, ignore=())
    for name, default_type in EFFECT_SECTIONS.items():
        if name in effects:
            eff[name] = _schema.validate(
                name, f"{source}: [effects.{name}]", effects[name], default_type=default_type
            )
    out["effects"] = eff
    return out


def scene_table_types(section: str) -> tuple[str, ...]:
    """The table types a scene file may name in `section` (`"sky"`, `"motion"`,
    `"redshift"`, `"disk"`), in registration order: e.g. the `type` of a `[[sky]]`.

    **Raises:** `ValueError` for a `section` that has no table types."""
    return tuple(_schema.entries(section))


def scene_table_keys(section: str, name: str) -> dict[str, SceneKey]:
    """The keys of table type `name` of `section`: each a `SceneKey` (kind, default,
    check, and what is valid, in words with its unit)."""
    return _schema.keys(section, name)


def scene_keys_text() -> str:
    """Every table and key a scene file takes, with its default and what is valid (units
    included), from the schema the files are checked against: `jaxlens render
    --scene-keys` prints it."""

    def toml(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, list):
            return "[" + ", ".join(toml(x) for x in v) + "]"
        return describe(v)

    def keys(table: dict[str, Key]) -> list[str]:
        out = []
        for name, key in table.items():
            if key.default is None:
                out.append(f"  {name}    # {key.text}")
            else:
                out.append(f"  {name} = {toml(key.default)}    # {key.text}")
        return out or ["  (no keys)"]

    lines = ["# top level", *keys(TOP_KEYS)]
    for name, table in (("camera", CAMERA_KEYS), ("output", OUTPUT_KEYS),
                        ("animation", ANIMATION_KEYS)):  # fmt: skip
        lines += ["", f"[{name}]", *keys(table)]
    lines += ["", "[[sky]]    # layers, summed; none given: a default sky and a star"]
    for kind in scene_table_types("sky"):
        lines += [f'  type = "{kind}"', *("  " + x for x in keys(scene_table_keys("sky", kind)))]
    lines += ["", "[effects]", *keys(EFFECTS_KEYS)]
    for section, default in EFFECT_SECTIONS.items():
        lines.append(f"[effects.{section}]" + (f'    # type = "{default}" if not given'
                                                 if default else ""))  # fmt: skip
        for kind in scene_table_types(section):
            lines += [f'  type = "{kind}"',
                      *("  " + x for x in keys(scene_table_keys(section, kind)))]  # fmt: skip
    return "\n".join(lines)


# The largest scene file read. A scene is a few dozen keys; what makes one large is
# a table of stars, whose lists (lon_deg, lat_deg, brightness, temperature) take
# about 4 x 12 bytes a star at 8 digits: 1 MiB holds some 20,000 stars (the 9,110 of
# the Yale Bright Star Catalogue twice over). Larger star sets belong in a panorama.
# The bound keeps `/dev/zero` or a wrong file from filling memory.
SCENE_FILE_MAX = 1 << 20


def read_scene_file(path) -> dict:
    """Parse a TOML scene file (no validation); paths inside are taken relative to
    the file's folder. At most `SCENE_FILE_MAX` bytes (1 MiB) are read: a larger file
    (or an endless one, such as `/dev/zero`) is refused. Raises `ValueError` naming
    the file for unreadable, too large or not UTF-8 files and TOML syntax errors."""
    path = Path(path)
    name = cut(repr(str(path)))
    try:
        with open(path, "rb") as f:
            raw = f.read(SCENE_FILE_MAX + 1)
    except FileNotFoundError:
        raise ValueError(f"scene file {name} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"scene file {name} is a folder") from None
    except OSError as e:
        raise ValueError(f"scene file {name} cannot be read: {e.strerror or e}") from None
    if len(raw) > SCENE_FILE_MAX:
        raise ValueError(f"scene file {name} is larger than {SCENE_FILE_MAX >> 20} MiB, the "
                         "most a scene file may hold (large star tables belong in a panorama "
                         "image)")  # fmt: skip
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"scene file {name} is not a UTF-8 text file") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scene file {name} is not valid TOML: {e}") from None
    except RecursionError:
        raise ValueError(f"scene file {name} nests its tables too deeply") from None
    layers = data.get("sky")
    if isinstance(layers, dict):  # a single [sky] table: one layer
        layers = data["sky"] = [layers]
    if isinstance(layers, list):
        for i, layer in enumerate(layers):
            if isinstance(layer, dict):
                if "_base" in layer:
                    raise ValueError(f"scene file {name}: [[sky]] #{i + 1} has an unknown "
                                     "key '_base'")  # fmt: skip
                layer["_base"] = str(path.parent)  # paths relative to the file's folder
    return data


def _sky_of(layers: list[dict]) -> AbstractSky:
    """The sky of a list of validated layer dicts (summed)."""
    skies = [
        _schema.build("sky", {k: v for k, v in la.items() if k != "_base"}, la["_base"])
        for la in layers
    ]
    sky = skies[0]
    for s in skies[1:]:
        sky = sky + s
    return sky


SOURCE_DISTANCE_RANGE = (
    f"> 1 and at most {MAX_DISTANCE:g} (units of R_S: outside the horizon; None or inf "
    "for a sky at infinity)"
)


def _source_distance(r):
    """`Scene.source_distance` as given: `None` (or a concrete `inf`) for the sky at
    infinity, else a float array of shape `()` checked where concrete: $1 < R \\le$
    `MAX_DISTANCE` (units of R_S), a `ValueError` naming the value otherwise."""
    if r is None:
        return None
    r = check_real("source_distance", length(r, "source_distance"))
    c = concrete(r)
    if c is not None:
        c = np.asarray(c, np.float64)
        if c.shape != ():
            raise ValueError(f"source_distance has shape {c.shape}: it must be one number "
                             "(units of R_S)")  # fmt: skip
        if np.isinf(c) and c > 0:
            return None
        if not (c > 1.0 and c <= MAX_DISTANCE):
            raise ValueError(f"source_distance={shown(c)} is not valid: it must be "
                             + SOURCE_DISTANCE_RANGE)  # fmt: skip
    return as_float(r)


def _source_plane(plane):
    """`Scene.source_plane` as given: `None`, else a float array of shape `()` checked
    where concrete: $0 < L \\le$ `MAX_DISTANCE` (units of R_S), a `ValueError` naming
    the value otherwise."""
    if plane is None:
        return None
    plane = check_real("source_plane", length(plane, "source_plane"))
    c = concrete(plane)
    if c is not None:
        c = np.asarray(c, np.float64)
        if c.shape != () or not (c > 0.0 and c <= MAX_DISTANCE):
            raise ValueError(f"source_plane={shown(c)} is not valid: it must be one number > 0 "
                             f"and at most {MAX_DISTANCE:g} (units of R_S: the distance of "
                             "the plane behind the hole)")  # fmt: skip
    return as_float(plane)


def _camera_of(cam: dict, *, dtype=None) -> Camera:
    rad = math.radians
    return Camera(
        cam["distance"], rad(cam["fov_deg"]), cam["width"], cam["height"],
        yaw=rad(cam["yaw_deg"]), pitch=rad(cam["pitch_deg"]), roll=rad(cam["roll_deg"]),
        azimuth=rad(cam["azimuth_deg"]), elevation=rad(cam["elevation_deg"]),
        supersample=cam["supersample"], sampling=cam["sampling"], dtype=dtype,
    )  # fmt: skip


def check_disk_shell(scene) -> None:
    """A `ValueError` when a scene's disk and its sky's sphere ($R$ = `source_distance`)
    are both concrete and the sphere is not outside both the camera and the disk
    ($R \\ge D$ and $R \\ge r_{out}$): only then does every ray cross the sphere after
    any disk crossing, so that the opaque disk hides what lies behind it exactly."""
    r = concrete(scene.source_distance)
    d = concrete(scene.camera.distance)
    r_out = concrete(scene.disk.r_out)
    if r is None or d is None or r_out is None:
        return
    if not (np.all(r >= d) and np.all(r >= r_out)):
        raise ValueError(
            f"source_distance={shown(r)} with a Disk (r_out={shown(np.max(r_out))}) seen "
            f"from distance={shown(np.max(d))}: a disk is supported with a source sphere "
            "outside both the camera and the disk (source_distance >= distance and >= "
            "r_out, units of R_S); see docs/limits.md"
        )


class Scene(eqx.Module):
    """Everything an image depends on: a camera, a sky and the effects a scene calls for.

    **Fields:**
    - `camera`: a `Camera` (distance in units of R_S, angles in radians); it may hold
      a batch of frames (`approach`, `orbit`, ...). Its pixels are in the moving
      frame when `motion` is set.
    - `sky`: an `AbstractSky` (skies sum with `+`).
    - `motion`: `None` (a static camera), `CircularOrbit` or `RadialInfall`.
    - `redshift`: `None` (no frequency shift) or `Redshift(mode)`.
    - `disk`: `None` or a `Disk`.
    - `source_distance`: `None` (the sky at infinity: a function of direction), or
      the radius $R$ of a transparent emitting sphere about the hole that carries the
      whole sky (units of R_S; $1 < R \\le 10^{30}$; a concrete `inf` is `None`). Each
      ray's crossings of $r = R$ (at most two: inward, then outward after its
      periapsis) add the sky's radiance in the direction from the hole to the
      crossing point. An array leaf: differentiable, traced in a fit. A dimensionless
      astropy Quantity is read as R_S, a length in metres, km, ... is refused (as for
      `Camera.distance`; `jaxlens.schwarzschild_radii` converts it).
    - `source_plane`: `None`, or the distance $L > 0$ (units of R_S, as
      `source_distance`) of a plane
      perpendicular to the line of sight behind the hole that carries the sky: the sky
      is called with the direction from the hole to each ray's outward crossing of
      $z = L$ (`plane_crossings`), so that `PlaneImage.at_distance(image, S, L)` draws
      a picture $S$ wide on that plane exactly. Not with `source_distance`, a disk or
      `sampling="gauss"`.
    - `accuracy` (static): the error allowed in the escape angle (radians).
    - `method` (static): `"auto"` (the plan chooses the source of the escape angle),
      or force `"table"`, `"weak_field"` or `"trace"`.
    - `exposure` (static): stops, applied when written to PNG/JPEG.

    A stage the scene does not name is not in the compiled program (`plan`).
    """

    camera: Camera
    sky: AbstractSky
    motion: AbstractMotion | None = None
    redshift: Redshift | None = None
    disk: Disk | None = None
    source_distance: jax.Array | None = eqx.field(default=None, converter=_source_distance)
    source_plane: jax.Array | None = eqx.field(default=None, converter=_source_plane)
    accuracy: float = eqx.field(static=True, default=1e-8)
    method: str = eqx.field(static=True, default="auto")
    exposure: float = eqx.field(static=True, default=0.0)

    def __check_init__(self):
        if not isinstance(self.camera, Camera):
            raise ValueError(f"camera={self.camera!r} must be a Camera")
        if not isinstance(self.sky, AbstractSky):
            raise ValueError(f"sky={self.sky!r} must be an AbstractSky (e.g. jl.GaussianStar)")
        if not (0.0 < self.accuracy < 0.1):
            raise ValueError(f"accuracy={self.accuracy!r} must be in (0, 0.1) radians")
        if self.method not in METHODS:
            raise ValueError(f"method={self.method!r} must be one of {', '.join(METHODS)}")
        if self.motion is not None and not isinstance(self.motion, AbstractMotion):
            raise ValueError(f"motion={self.motion!r} must be CircularOrbit, RadialInfall or None")
        if self.redshift is not None and not isinstance(self.redshift, Redshift):
            raise ValueError(f"redshift={self.redshift!r} must be Redshift(mode) or None")
        if self.disk is not None and not isinstance(self.disk, Disk):
            raise ValueError(f"disk={self.disk!r} must be a Disk or None")
        if self.motion is not None:
            d = concrete(self.camera.distance)
            if d is not None:
                self.motion.check_distance(d)
        if self.disk is not None and self.source_distance is not None:
            check_disk_shell(self)
        if self.source_plane is not None:
            if self.source_distance is not None:
                raise ValueError("give source_distance (a sphere) or source_plane (a plane), "
                                 "not both")  # fmt: skip
            if self.disk is not None:
                raise ValueError("source_plane with a Disk is not supported (docs/limits.md)")

    def replace(self, **changes) -> "Scene":
        """A copy with the given fields replaced (e.g. `scene.replace(disk=None)`)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "scene", dtype=None) -> "Scene":
        """A scene from a dictionary of the TOML schema (see the module docstring);
        validated, with errors naming the key, its value and what is valid."""
        return cls.from_validated(validate(data, source=source), dtype=dtype)

    @classmethod
    def from_validated(cls, v: dict, *, dtype=None) -> "Scene":
        """A scene from `validate`'s output (`dtype`: of the camera's arrays)."""
        eff = v["effects"]
        parts = {name: _schema.build(name, eff[name]) for name in EFFECT_SECTIONS if name in eff}
        return cls(
            _camera_of(v["camera"], dtype=dtype), _sky_of(v["sky"]), **parts,
            source_distance=eff.get("source_distance"), source_plane=eff.get("source_plane"),
            accuracy=v["accuracy"],
            method=eff["method"], exposure=v["output"]["exposure"],
        )  # fmt: skip


def load_scene(path, *, dtype=None) -> Scene:
    """Read and validate a TOML scene file (camera, sky layers, effects) of at most
    `SCENE_FILE_MAX` bytes (1 MiB); image paths in it are relative to the file's folder.
    Raises `ValueError` naming the file, or the table, key and value that is not valid
    and the valid range (`jaxlens render --scene-keys` lists them)."""
    return Scene.from_dict(read_scene_file(path), source=str(path), dtype=dtype)
