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
import re
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


# Values in messages are cut to about this many characters: a list of a million
# numbers or a path of megabytes would make an unreadable line.
SHOWN_MAX = 200


def cut(text: str, limit: int = SHOWN_MAX) -> str:
    """`text` cut to its first `limit` characters, saying how long it was."""
    text = str(text)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def describe(value) -> str:
    """A value as an error message shows it: strings in double quotes, floats with all
    their digits (`repr`: 179.99999999, not 180.0), and long strings, lists and tables
    cut to their start and their length (at most about `SHOWN_MAX` characters)."""
    if isinstance(value, str):
        if len(value) > SHOWN_MAX:
            return f'"{value[:SHOWN_MAX]}"... ({len(value)} characters)'
        return f'"{value}"'
    if isinstance(value, list):
        if len(value) > 8:
            first = ", ".join(cut(describe(v), 40) for v in value[:3])
            return f"[{first}, ... {len(value)} items]"
        return cut("[" + ", ".join(cut(describe(v), 40) for v in value) + "]")
    if isinstance(value, dict):
        items = [f"{cut(repr(k), 40)}: {cut(describe(v), 40)}" for k, v in list(value.items())[:8]]
        more = f", ... {len(value)} keys" if len(value) > 8 else ""
        return cut("{" + ", ".join(items) + more + "}")
    if isinstance(value, int) and value.bit_length() > 600:  # `repr` stops at 4300 digits
        return f"(an integer of about {round(value.bit_length() * math.log10(2))} digits)"
    return cut(repr(value))


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
