"""The scene-file schema: typed keys, one validator, and a registry of table types.

Every TOML table of a scene file is checked by `table()` against a dict of `Key`s, so
all errors read alike: they name the table, the key, the value and what is valid. A
part of a scene that a file can name (a sky layer, a camera motion, a frequency
shift, a disk) registers its own table next to its class:

```python
@register("sky", "star", {"sigma_deg": Key("float", 1.0, in_range(0, 180), "...")})
def _star(t: dict, base: Path) -> GaussianStar: ...
```

and `build("sky", validate("sky", where, raw_table), base)` validates a raw table
(its `type` picks the entry) and returns the object. Adding a sky or an effect to the
file format is that one registration, in the file of its class. This module imports
none of those files (they import it): `_scene`, which imports them all, serves the
registry's public readers (`scene_table_types`, `scene_table_keys`).
"""

import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from ._messages import describe

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
    value) and `valid` (what is valid, in words, with the unit). Messages use `text`:
    `valid`, but for a whole number checked by a `Range` the range comes from the check."""

    kind: str
    default: Any
    check: Callable[[Any], bool]
    valid: str

    @property
    def text(self) -> str:
        """What is valid, as messages and `--scene-keys` say it: for a whole number
        checked by a `Range`, the range from the check itself (and the unit of `valid`,
        its last parenthesis), so that the words cannot say another range."""
        if self.kind != "int" or not isinstance(self.check, Range):
            return self.valid
        unit = re.search(r" \([^()]*\)$", self.valid)
        return self.check.whole_numbers() + (unit.group() if unit else "")


class Range(NamedTuple):
    """Predicate `lo < v < hi` (`lo`, `hi`: `None` for no bound), that also says its
    range in words, so that a key's message and `--scene-keys` give the range
    that is checked."""

    lo: float | None = None
    hi: float | None = None

    def __call__(self, v) -> bool:
        return (self.lo is None or v > self.lo) and (self.hi is None or v < self.hi)

    def whole_numbers(self) -> str:
        """The whole numbers in the range, in words."""
        lo = None if self.lo is None else math.floor(self.lo) + 1
        hi = None if self.hi is None else math.ceil(self.hi) - 1
        if lo is not None and hi is not None:
            return f"a whole number from {lo} to {hi}"
        return f"a whole number >= {lo}" if hi is None else f"a whole number <= {hi}"


def greater(lo):
    """Predicate `v > lo`."""
    return Range(lo, None)


def in_range(lo, hi):
    """Predicate `lo < v < hi`."""
    return Range(lo, hi)


def anything(v) -> bool:
    """Predicate that accepts every value of the key's kind."""
    return True


# No number in a scene is larger in magnitude: radiances beyond it overflow float32
# pixels once magnified or exposed, distances the float64 geometry (an all-NaN render
# from D ~ 1e77).
MAGNITUDE_MAX = 1e30


def coerce(where: str, name: str, value, key: Key, *, equals: str = " = ") -> Any:
    """Check the type and range of one value; return it in its Python type. The error
    names the table, the key (and the item of a list), the value and what is valid:
    "WHERE NAME = VALUE is not valid: expected ..." (`equals=" "` and `where=""` for a
    command-line option: "--distance -inf is not valid: ...")."""
    label = f"{where} {name}" if where else name

    def bad(v=value, at=""):
        return ValueError(f"{label}{at}{equals}{describe(v)} is not valid: expected {key.text}")

    def number(v, at=""):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise bad(v, at)
        try:
            f = float(v)
        except OverflowError:  # an integer beyond float range
            raise bad(v, at) from None
        if not math.isfinite(f):
            raise bad(v, at)
        if abs(f) > MAGNITUDE_MAX and (kind != "float" or key.check(f)):  # (else: range)
            raise ValueError(f"{label}{at}{equals}{describe(v)} is not valid: expected "
                             f"{key.text}, at most {MAGNITUDE_MAX:g} in magnitude")  # fmt: skip
        return f

    kind = key.kind

    def numbers(values):
        return [number(x, f"[{i}]") for i, x in enumerate(values)]

    if kind == "float":
        v = number(value)
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad()
        v = value
    elif kind == "bool":
        if not isinstance(value, bool):
            raise bad()
        v = value
    elif kind == "str":
        if not isinstance(value, str):
            raise bad()
        v = value
    elif kind == "color":
        if isinstance(value, list):
            if len(value) != 3:
                raise bad()
            return numbers(value)
        v = number(value)
    elif kind == "floats":
        if isinstance(value, list):
            if not value:
                raise bad()
            return numbers(value)
        return number(value)
    else:  # pragma: no cover - schema error
        raise AssertionError(kind)
    if not key.check(v):
        raise bad()
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


def entries(section: str) -> dict[str, Entry]:
    """The registered table types of `section`, by name, in registration order. Only
    the types of the modules imported so far are there: this module imports none of
    them (they import it), so a caller outside them reads the registry after importing
    `_scene`, which imports every module that registers a table and serves the public
    `scene_table_types` and `scene_table_keys`."""
    if section not in _REGISTRY:
        valid = f"one of {', '.join(_REGISTRY)}" if _REGISTRY else "none (import _scene first)"
        raise ValueError(f"section {describe(section)} is not valid: expected {valid}")
    return _REGISTRY[section]


def validate(section: str, where: str, data, *, default_type: str | None = None) -> dict:
    """Validate a raw table of `section`: its `type` key picks the entry (or
    `default_type` where the key is absent). **Returns:** the validated dict, with
    `type` set."""
    found = entries(section)
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a table, got {describe(data)}")
    kind = data.get("type", default_type)
    if kind not in found:
        raise ValueError(
            f"{where} type = {describe(kind)} is not valid: expected one of {', '.join(found)}"
        )
    entry = found[kind]
    out = table(f"{where} ({kind})", data, entry.keys, ignore=("type",))
    if entry.check is not None:
        entry.check(f"{where} ({kind})", out)
    return {"type": kind, **out}


def keys(section: str, name: str) -> dict[str, Key]:
    """The keys of table type `name` of `section` (see `entries` for which are there)."""
    return entries(section)[name].keys


def build(section: str, validated: dict, base: Path | str = ".") -> Any:
    """The object of a validated table of `section` (`validate`'s output); paths in it
    are relative to `base`."""
    fields = {k: v for k, v in validated.items() if k != "type"}
    return entries(section)[validated["type"]].build(fields, Path(base))


# The public name of a key (jaxlens.SceneKey), for tools that list or document what a
# scene file may hold (`_scene.scene_table_keys` gives them).
SceneKey = Key
