"""How a value appears in an error message, and the check that a value holds real numbers.

Every layer names the value it refuses (a scene file's key, a command-line option, an
argument of `trace` or of a sky), so these helpers sit below all of them: they import
NumPy and, of jaxlens, only `_units` (NumPy and constants), and load no JAX (the
command line's parser uses them).
"""

import math

import numpy as np

from ._units import plain

# Values in messages are cut to about this many characters: a list of a million
# numbers or a path of megabytes would make an unreadable line.
SHOWN_MAX = 200


def cut(text, limit: int = SHOWN_MAX) -> str:
    """`str(text)` cut to its first `limit` characters, saying how long it was."""
    text = str(text)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def shown(value, limit: int = SHOWN_MAX) -> str:
    """`repr(value)` cut to `limit` characters; a NumPy scalar or 0-d array as the Python
    number it holds (`2.0`, not `np.float64(2.0)`)."""
    if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
        value = value.item()
    return cut(repr(value), limit)


def describe(value) -> str:
    """A value of a scene file or option as a message shows it: strings in double
    quotes, floats with all their digits (`repr`: 179.99999999, not 180.0), and long
    strings, lists and tables cut to their start and their length (at most about
    `SHOWN_MAX` characters)."""
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


def real_array(name: str, x):
    """`x` as an array of real numbers: `x` itself if it has a `dtype` (a NumPy or JAX
    array, a tracer), else `np.asarray(x)`. A complex, boolean, string or object value,
    or a ragged list, is a `TypeError` naming `name` and the value (NumPy would drop an
    imaginary part with a warning, or fail deep inside the render). A list holding
    tracers is the caller's to convert first (`jnp.asarray`). An astropy Quantity is a
    `ValueError`: an argument that takes one converts it before this check
    (`_units`), and no unit is dropped silently anywhere else."""
    x = plain(x, name, "a plain number or array (in the unit its docstring gives)")
    given = x
    if not hasattr(x, "dtype"):
        try:
            x = np.asarray(x)
        except (TypeError, ValueError) as e:  # ragged lists, ...
            raise TypeError(f"{name}={shown(given)} must be real numbers: {e}") from None
    try:
        kind = np.dtype(x.dtype).kind
    except TypeError:  # a `dtype` that is none
        kind = "O"
    if kind not in "iuf":
        raise TypeError(f"{name}={shown(given)} must be real numbers, not {x.dtype}")
    return x
