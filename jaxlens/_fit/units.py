"""Units: the Schwarzschild radius of a solar mass, conversions between R_S, metres
and solar masses, lengths read from text with their unit (`parse_length`), and
astropy `Quantity` in and out where astropy is installed (an optional extra)."""

import dataclasses
import math
import re

from jaxtyping import ArrayLike

from .._constants import C_LIGHT as C_LIGHT, GM_SUN as GM_SUN, RS_SUN_M as RS_SUN_M
from .._units import (
    astropy_units as _astropy_units,
    is_quantity as is_quantity,
    length,
    metres,
    solar_masses,
)


def schwarzschild_radius_m(mass_msun: ArrayLike):
    """Schwarzschild radius $2GM/c^2$ in metres of a mass in solar masses (or an
    astropy mass Quantity)."""
    return RS_SUN_M * solar_masses(mass_msun, "mass_msun")


def distance_in_metres(distance: ArrayLike, mass_msun: ArrayLike):
    """Camera distance in metres, from the distance in units of R_S (a plain number or
    a dimensionless Quantity) and the mass of the hole in solar masses (or an astropy
    mass Quantity)."""
    return length(distance, "distance", mass_msun) * schwarzschild_radius_m(mass_msun)


def mass_from_distance(distance: ArrayLike, distance_m: ArrayLike):
    """Mass of the hole in solar masses, from the camera distance in units of R_S (a
    plain number or a dimensionless Quantity) and the same distance in metres (or an
    astropy length Quantity)."""
    return metres(distance_m, "distance_m") / (length(distance, "distance") * RS_SUN_M)


# Lengths a command line or a user may give a distance in, in metres: the IAU 2012
# astronomical unit (exact), the parsec from it (648000 / pi au), the Julian light year.
AU_M = 149_597_870_700.0
PC_M = AU_M * 648_000.0 / math.pi  # 3.0856775814913673e16 m
LY_M = C_LIGHT * 365.25 * 86_400.0  # 9.4607304725808e15 m
LENGTH_UNITS_M = {
    "m": 1.0,
    "km": 1e3,
    "au": AU_M,
    "pc": PC_M,
    "kpc": 1e3 * PC_M,
    "Mpc": 1e6 * PC_M,
    "ly": LY_M,
}
# The unit of lengths in units of the Schwarzschild radius (not a length in metres).
RS_UNIT = "Rs"
LENGTH_UNITS = (*LENGTH_UNITS_M, RS_UNIT)

_LENGTH = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z]+)\s*")


@dataclasses.dataclass(frozen=True)
class Length:
    """A length read from text (`parse_length`): `value` in `unit`, one of
    `LENGTH_UNITS` (`"Rs"`: units of the Schwarzschild radius)."""

    value: float
    unit: str

    @property
    def in_rs(self) -> bool:
        """Whether the length is in units of R_S (else a length in metres)."""
        return self.unit == RS_UNIT

    @property
    def metres(self) -> float:
        """The length in metres (`ValueError` for one in units of R_S, which needs
        the mass)."""
        if self.in_rs:
            raise ValueError(f"{self.value:g} {RS_UNIT} is in units of the Schwarzschild "
                             "radius: its length in metres needs the mass")  # fmt: skip
        return self.value * LENGTH_UNITS_M[self.unit]


def parse_length(text: str, *, name: str = "length") -> Length:
    """A positive, finite length with its unit, from text such as `"8.5kpc"`,
    `"8.5 kpc"`, `"3e20 m"` or `"40Rs"` (units: m, km, au, pc, kpc, Mpc, ly, and Rs
    for units of R_S; case as written). Raises `ValueError` naming `name`, the text
    and the valid units otherwise."""
    units = ", ".join(LENGTH_UNITS)
    m = _LENGTH.fullmatch(str(text))
    if m is None or m.group(2) not in LENGTH_UNITS:
        raise ValueError(f"{name} {str(text)[:80]!r} is not a length: expected a positive "
                         f"number and a unit, one of {units} (Rs: units of the "
                         "Schwarzschild radius), e.g. 8.5kpc")  # fmt: skip
    value = float(m.group(1))
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} {str(text)[:80]!r} is not valid: expected a positive, "
                         f"finite number and a unit, one of {units}")  # fmt: skip
    return Length(value, m.group(2))


def _plain(x, name: str, unit: str) -> float:
    """`x` as a positive, finite float, or a `ValueError` naming `name` and `unit`."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={x!r} is not a number ({unit})") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name}={x!r} must be positive and finite ({unit})")
    return v


def to_metres(x, *, name: str = "distance") -> float:
    """A length as a float in metres: an astropy length `Quantity` converted, a plain
    number taken as metres. Positive and finite, else a `ValueError` naming `name`."""
    return _plain(metres(x, name), name, "metres")


def to_solar_masses(x, *, name: str = "mass") -> float:
    """A mass as a float in solar masses: an astropy mass `Quantity` converted (at the
    nominal solar mass, `u.M_sun`), a plain number taken as solar masses. Positive and
    finite, else a `ValueError` naming `name`."""
    return _plain(solar_masses(x, name), name, "solar masses")


def as_metres(value: float, quantity: bool):
    """A length in metres as an astropy `Quantity` in metres where `quantity` (the
    inputs were Quantities), else the float."""
    return value * _astropy_units().m if quantity else value


def as_solar_masses(value: float, quantity: bool):
    """A mass in solar masses as an astropy `Quantity` where `quantity`, else the float."""
    return value * _astropy_units().M_sun if quantity else value
