"""Scene-file tables of skies: the keys several sky types share, and `sky_from_table`.

Each sky type registers its own table (`_schema.register("sky", name, keys)`) in the
file of its class; this module holds what they have in common.
"""

import math
from pathlib import Path

import numpy as np

from .. import _schema
from .._messages import describe
from .._schema import Key, anything, greater, in_range
from ._base import AbstractSky, direction_from_angles

ORIENTATION = {
    "yaw_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "pitch_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "roll_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
}
BRIGHTNESS = {"brightness": Key("float", 1.0, lambda v: v >= 0.0, "a finite number >= 0 (scale)")}
SIGMA = {"sigma_deg": Key("float", 1.0, in_range(0.0, 180.0), "a number in (0, 180) (degrees)")}
IMAGE_PATH = {"path": Key("str", None, lambda v: len(v) > 0, "the path of an image file")}


def star_list_keys(sigma_deg: float) -> dict:
    """The keys of a list of stars (`stars`, `blackbody`): a Gaussian width (default
    `sigma_deg`, degrees) and either `count` random stars from `seed` or the lists
    `lon_deg`, `lat_deg`."""
    return {
        "sigma_deg": Key(
            "float", sigma_deg, in_range(0.0, 180.0), "a number in (0, 180) (degrees)"
        ),
        "count": Key("int", 200, in_range(0, 100001), "a whole number from 1 to 100000"),
        "seed": Key("int", 0, greater(-1), "a whole number >= 0"),  # numpy's seeds
        "lon_deg": Key("floats", None, anything, "a list of finite numbers (degrees)"),
        "lat_deg": Key("floats", None, anything, "a list of finite numbers (degrees)"),
    }


def orientation(fields: dict) -> dict:
    """The `yaw`, `pitch`, `roll` keyword arguments (radians) of a validated table."""
    keys = ("yaw_deg", "pitch_deg", "roll_deg")
    return {k[:-4]: math.radians(fields[k]) for k in keys if k in fields}


def bad_value(where: str, fields: dict, name: str, valid: str) -> ValueError:
    """The error of a key whose value is not valid, in the wording of `_schema`."""
    return ValueError(f"{where} {name} = {describe(fields[name])} is not valid: expected {valid}")


def sky_from_table(table: dict | list[dict], *, base: Path | str = ".") -> AbstractSky:
    """The sky of a scene file's `[[sky]]` table (a dict, as TOML reads it), or the sum
    of a list of them.

    The table's `type` names the sky (`star`, `stars`, `panorama`, `plane`, `checker`,
    `default`, `uniform`, `blackbody`); its other keys are checked as in a scene file
    (`ValueError` naming the key, its value and what is valid) and defaults filled in.

    **Arguments:** `table`: one table or a non-empty list of them; `base`: the folder
    that image paths in it are relative to.

    **Returns:** an `AbstractSky` (a `SkySum` for several tables).
    """
    tables = table if isinstance(table, list) else [table]
    if not tables:
        raise ValueError("table=[] must be a sky table or a non-empty list of them")
    skies = []
    for i, t in enumerate(tables):
        where = "sky" if len(tables) == 1 else f"sky #{i + 1}"
        skies.append(_schema.build("sky", _schema.validate("sky", where, t), base))
    sky = skies[0]
    for s in skies[1:]:
        sky = sky + s
    return sky


def check_star_lists(where: str, fields: dict, per_star: tuple[str, ...]) -> None:
    """Cross-key checks of a table of many stars: `lon_deg` and `lat_deg` go together
    and have one length; each key of `per_star` given as a list has one value a star."""
    lon, lat = fields.get("lon_deg"), fields.get("lat_deg")
    if (lon is None) != (lat is None):
        raise ValueError(f"{where}: lon_deg and lat_deg go together")
    if lon is None:
        return
    lon, lat = np.atleast_1d(lon), np.atleast_1d(lat)
    if lon.shape != lat.shape:
        raise ValueError(
            f"{where}: lon_deg and lat_deg have different lengths ({lon.size} and {lat.size})"
        )
    for name in per_star:
        v = fields.get(name)
        if isinstance(v, list) and len(v) != lon.size:
            raise ValueError(f"{where}: {name} has {len(v)} values for {lon.size} stars")


def star_directions(fields: dict):
    """Unit vectors `(N, 3)` of a validated table's `lon_deg`, `lat_deg` (degrees)."""
    return direction_from_angles(
        np.radians(np.atleast_1d(fields["lon_deg"])), np.radians(np.atleast_1d(fields["lat_deg"]))
    )


def value_range(value, default: tuple[float, float]) -> tuple[float, float]:
    """`(min, max)` of a number or list of numbers; `default` for `None`."""
    if value is None:
        return default
    return (min(np.atleast_1d(value)), max(np.atleast_1d(value)))
