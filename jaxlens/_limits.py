"""The valid range of each array field of a scene part, declared once beside the field.

A scene part (a sky, a motion, the disk) lists its fields' ranges in its class's
`limits` (`{field name: Limit}`); they are checked where the values are used:

- `check_fields` in `__check_init__`: a known value is a `ValueError` when the part
  is built (the earliest place), naming the field, its value and the range;
- `checks` in the kernel's scene checks (`_kernel.checked`, `_kernel.verify`): the
  same ranges in the pixel dtype, once a render, with `eqx.error_if` for traced
  values (so `jit` raises at run time) and on the host for known ones.

Every limit asks for a finite value; radiances are also bounded in magnitude, so that
sums over a pixel's samples and a sky's layers stay finite in float32 (the dtype of
`render`'s images).
"""

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._messages import real_array, shown as _shown
from ._schema import MAGNITUDE_MAX
from ._units import angle
from ._util import as_float, concrete, has_tracer

_MAX = f"{MAGNITUDE_MAX:g}".replace("e+", "e")  # 1e30


@dataclasses.dataclass(frozen=True)
class Limit:
    """A field's valid range: finite and between `low` and `high` (open or closed).

    **Fields:** `text` (the range in words, as messages say it), `unit`, `low`,
    `high`, `low_open`, `high_open`; `texture`: an array of pixels (an image), checked
    in the program only where it is traced (a known image is checked when its sky is
    built: a pass over its pixels is not repeated on every render).
    """

    text: str
    unit: str
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    texture: bool = False

    def bad(self, value, xp, dtype=None):
        """Where `value` is outside the range (`xp`: `np` or `jnp`), after rounding to
        `dtype` if given: a value the dtype rounds to inf or, for a range open at 0, to
        below its smallest normal number, is refused too."""
        v = xp.asarray(value)
        if dtype is not None and v.dtype != dtype:
            with np.errstate(over="ignore"):  # what overflows is what is refused
                v = v.astype(dtype)
        if xp is np and v.ndim == 0:  # a known scalar: Python floats, ~20 times faster
            return not self._holds(v.item(), dtype)
        out = ~xp.isfinite(v)
        if self.low > -math.inf:
            low = self.low
            if self.low_open and low == 0.0 and dtype is not None:
                out = out | ~(v >= np.finfo(dtype).tiny)
            else:
                out = out | ~((v > low) if self.low_open else (v >= low))
        if self.high < math.inf:
            out = out | ~((v < self.high) if self.high_open else (v <= self.high))
        return out

    def _holds(self, v: float, dtype) -> bool:
        """Whether the float `v` (rounded to `dtype` already) is in the range."""
        if not math.isfinite(v):
            return False
        low = self.low
        if self.low_open and low == 0.0 and dtype is not None:
            low, low_open = float(np.finfo(dtype).tiny), False
        else:
            low_open = self.low_open
        if not ((v > low) if low_open else (v >= low)):
            return False
        return (v < self.high) if self.high_open else (v <= self.high)

    def describe(self) -> str:
        """`"finite and > 0 (radians)"`: the range and its unit."""
        return f"{self.text} ({self.unit})"


def finite(unit: str) -> Limit:
    """Any finite value (angles, positions)."""
    return Limit("finite", unit)


def positive(unit: str) -> Limit:
    """A finite value > 0 (widths, temperatures)."""
    return Limit("finite and > 0", unit, low=0.0, low_open=True)


def between(low: float, high: float, text: str, unit: str) -> Limit:
    """A value in the open interval (`low`, `high`); `text` says it in words."""
    return Limit(text, unit, low=low, high=high, low_open=True, high_open=True)


def radiance(unit: str = "linear radiance") -> Limit:
    """A radiance, or a weight of one, of either sign (a fit may pass through negative
    values): finite and at most `MAGNITUDE_MAX` in magnitude."""
    return Limit(f"finite and at most {_MAX} in magnitude", unit,
                 low=-MAGNITUDE_MAX, high=MAGNITUDE_MAX)  # fmt: skip


def scale(unit: str = "scale") -> Limit:
    """A non-negative brightness scale: in [0, `MAGNITUDE_MAX`] (a negative one gives
    negative radiance)."""
    return Limit(f"in [0, {_MAX}]", unit, low=0.0, high=MAGNITUDE_MAX)


ORIENTATION = {name: finite("radians") for name in ("yaw", "pitch", "roll")}


def texture(unit: str = "linear radiance") -> Limit:
    """The pixels of an image: finite."""
    return Limit("finite", unit, texture=True)


def real(name: str, x, dtype=None):
    """`x` as a float array (`as_float`), after checking that it holds real numbers
    (`_messages.real_array`): a complex, boolean, string or object value is a
    `TypeError` naming `name`."""
    if not isinstance(x, jax.Array | np.ndarray) and has_tracer(x):
        x = jnp.asarray(x)  # a list holding tracers
    return as_float(real_array(name, x), dtype)


def radians(name: str, x, dtype=None):
    """`real` of an angle: radians, an astropy angle Quantity converted first
    (`_units.angle`; a Quantity of another dimension is a `ValueError` naming `name`)."""
    return real(name, angle(x, name), dtype)


def shown(value, bad) -> str:
    """The first bad entry of `value` as a message shows it."""
    v = np.asarray(value)
    return _shown(v[np.asarray(bad)].flat[0] if v.ndim else v)


def check_fields(module: Any) -> None:
    """`ValueError` for the first known field of `module` outside its `limits`, naming
    the field, its value and the range (for `__check_init__`)."""
    for name, limit in type(module).limits.items():
        v = concrete(getattr(module, name))
        if v is None or limit.texture:  # an image: checked as it was read (`to_rgb`)
            continue
        bad = limit.bad(v, np)
        if np.any(bad):
            raise ValueError(f"{name}={shown(v, bad)} must be {limit.describe()}")


def checks(module: Any, where, path: str, xp, dtype) -> list:
    """Each check of `module`'s fields and of the scene parts inside it (a sum's
    parts, a turned sky): `(where, bad, message)` as `_kernel._checks` lists them,
    `where` the field's getter from the scene (`where(scene)` gives `module`), `path`
    its name in messages (`"sky.parts[0]"`), `dtype` the pixel dtype."""
    out = []
    kind = type(module).__name__
    for name, limit in type(module).limits.items():
        value = getattr(module, name)
        if limit.texture and not isinstance(value, jax.core.Tracer):
            continue
        get = _getter(where, name)
        out.append((get, limit.bad(value, xp, dtype),
                    f"{path}.{name} ({kind}) must be {limit.describe()}"))  # fmt: skip
    for f in dataclasses.fields(module):
        value = getattr(module, f.name)
        if isinstance(value, eqx.Module) and hasattr(type(value), "limits"):
            out += checks(value, _getter(where, f.name), f"{path}.{f.name}", xp, dtype)
        elif isinstance(value, tuple):
            for i, part in enumerate(value):
                if isinstance(part, eqx.Module) and hasattr(type(part), "limits"):
                    get = _item(_getter(where, f.name), i)
                    out += checks(part, get, f"{path}.{f.name}[{i}]", xp, dtype)
    return out


def _getter(where, name):
    return lambda s: getattr(where(s), name)


def _item(where, i):
    return lambda s: where(s)[i]
