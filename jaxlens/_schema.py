"""The scene-file schema: typed keys, one validator, and a registry of table types.

Every TOML table of a scene file is checked by `table()` against a dict of `Key`s, so
all errors read alike: they name the table, the key, the value and what is valid. A
part of a scene that a file can name (a sky layer, a camera motion, a frequency
shift, a disk) registers its own table next to its class:

```python
@register("sky", "star", {"sigma_deg": Key("float", 1.0, in_range(0, 180), "...")})
def _star(t: dict, base: Path) -> GaussianStar: ...
```

and `build("sky", where, raw_table, base)` validates a raw table (its `type` picks
the entry) and returns the object. Adding a sky or an effect to the file format is
that one registration, in the file of its class.
"""

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

# Constants the command line's parser needs (kept here, free of JAX, so that building
# the parser, and `jaxlens --help`, does not import it).
ANIMATION_PATHS = ("approach", "orbit", "pan", "zoom")
# Defaults of start/stop for each animation path.
ANIMATION_RANGES = {
    "approach": (1e5, 3.0),
    "orbit": (0.0, 360.0),
    "pan": (-30.0, 30.0),
    "zoom": (90.0, 10.0),
}
DEFAULT_SKY = [{"type": "default"}, {"type": "star"}]


class Key(NamedTuple):
    """One key of a table: `kind` (`"float"`, `"int"`, `"bool"`, `"str"`, `"color"`: a
    number or 3 numbers, `"floats"`: a number or a list), `default` (`None`: no
    default, the key is absent unless given), `check` (a predicate on the coerced
    value) and `valid` (what is valid, in words, with the unit)."""

    kind: str
    default: Any
    check: Callable[[Any], bool]
    valid: str


def greater(lo):
    """Predicate `v > lo`."""
    return lambda v: v > lo


def in_range(lo, hi):
    """Predicate `lo < v < hi`."""
    return lambda v: lo < v < hi


def anything(v) -> bool:
    """Predicate that accepts every value of the key's kind."""
    return True


def describe(value) -> str:
    """A value as an error message shows it."""
    return repr(value) if not isinstance(value, str) else f'"{value}"'


# No number in a scene is larger in magnitude: radiances beyond it overflow float32
# pixels once magnified or exposed, distances the float64 geometry (an all-NaN render
# from D ~ 1e77).
MAGNITUDE_MAX = 1e30


def coerce(where: str, name: str, value, key: Key) -> Any:
    """Check the type and range of one value; return it in its Python type."""
    bad = ValueError(f"{where} {name} = {describe(value)} is not valid: expected {key.valid}")

    def number(v):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise bad
        try:
            v = float(v)
        except OverflowError:  # an integer beyond float range
            raise bad from None
        if not math.isfinite(v):
            raise bad
        if abs(v) > MAGNITUDE_MAX:
            raise ValueError(f"{where} {name} = {describe(value)} is not valid: expected "
                             f"{key.valid}, at most {MAGNITUDE_MAX:g} in magnitude")  # fmt: skip
        return v

    kind = key.kind
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
            return [number(x) for x in value]
        v = number(value)
    elif kind == "floats":
        if isinstance(value, list):
            if not value:
                raise bad
            return [number(x) for x in value]
        return number(value)
    else:  # pragma: no cover - schema error
        raise AssertionError(kind)
    if not key.check(v):
        raise bad
    return v


def table(where: str, data, keys: dict[str, Key], *, ignore: tuple[str, ...] = ()) -> dict:
    """Validate one TOML table against its keys; return it with defaults filled in.
    Keys in `ignore` are passed over (e.g. `type`, read by the caller)."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a table, got {describe(data)}")
    for name in data:
        if name not in keys and name not in ignore:
            raise ValueError(
                f"{where} has an unknown key {name!r}; valid keys: {', '.join(keys) or 'none'}"
            )
    out = {}
    for name, key in keys.items():
        if name in data:
            out[name] = coerce(where, name, data[name], key)
        elif key.default is not None:
            out[name] = key.default
    return out


class Entry(NamedTuple):
    keys: dict[str, Key]
    build: Callable[[dict, Path], Any]
    check: Callable[[str, dict], None] | None


_REGISTRY: dict[str, dict[str, Entry]] = {}


def register(section: str, name: str, keys: dict[str, Key], *, check=None):
    """Decorator: register `build(validated_table, base_folder) -> object` as the
    table type `name` of `section` (`"sky"`, `"motion"`, `"redshift"`, `"disk"`).
    `check(where, validated_table)`, if given, raises `ValueError` for combinations
    of keys that are not valid together."""

    def deco(build):
        _REGISTRY.setdefault(section, {})[name] = Entry(keys, build, check)
        return build

    return deco


def types(section: str) -> tuple[str, ...]:
    """The table types a scene file may name in `section` (`"sky"`, `"motion"`,
    `"redshift"`, `"disk"`), in registration order: e.g. the `type` of a `[[sky]]`."""
    _load()
    return tuple(_REGISTRY.get(section, {}))


def keys(section: str, name: str) -> dict[str, Key]:
    """The keys of table type `name` of `section`: each a `Key` (kind, default, check,
    and what is valid, in words with its unit)."""
    _load()
    return _REGISTRY[section][name].keys


def validate(section: str, where: str, data, *, default_type: str | None = None) -> dict:
    """Validate a raw table of `section`: its `type` key picks the entry (or
    `default_type` where the key is absent). **Returns:** the validated dict, with
    `type` set."""
    _load()
    entries = _REGISTRY.get(section, {})
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a table, got {describe(data)}")
    kind = data.get("type", default_type)
    if kind not in entries:
        raise ValueError(
            f"{where} type = {describe(kind)} is not valid: expected one of {', '.join(entries)}"
        )
    entry = entries[kind]
    out = table(f"{where} ({kind})", data, entry.keys, ignore=("type",))
    if entry.check is not None:
        entry.check(f"{where} ({kind})", out)
    return {"type": kind, **out}


def build(section: str, validated: dict, base: Path | str = ".") -> Any:
    """The object of a validated table of `section` (`validate`'s output); paths in it
    are relative to `base`."""
    _load()
    fields = {k: v for k, v in validated.items() if k != "type"}
    return _REGISTRY[section][validated["type"]].build(fields, Path(base))


def _load():
    # The registrations live beside their classes; importing the modules runs them.
    from . import _disk, _effects, _sky  # noqa: F401


# Public names (jaxlens.SceneKey, scene_table_types, scene_table_keys): for tools that
# list or document what a scene file may hold.
SceneKey = Key
scene_table_types = types
scene_table_keys = keys
