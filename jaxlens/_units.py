"""astropy `Quantity` inputs: converted to jaxlens' units where their meaning is known,
refused with a `ValueError` where it is not, never read as bare numbers.

jaxlens' units: lengths in Schwarzschild radii $R_S = 2GM/c^2$ (one solar mass:
`RS_SUN_M` = 2953.25 m), angles in radians, masses in solar masses. A public entry
point passes each length, angle or mass argument through `length`, `angle` or
`solar_masses` before anything else reads it (before a trace too: a Quantity held by
the caller's Python code is converted eagerly, a plain number or array is returned as
it is, at the cost of one dictionary look-up). astropy is an optional extra: it is
never imported here; a Quantity can exist only once the caller has imported it.

- an angle: a Quantity in any angle unit (deg, arcmin, arcsec, rad, ...) becomes
  radians; a dimensionless one is radians (astropy's `dimensionless_angles`).
- a length: a dimensionless Quantity is a number in units of R_S, as a plain number
  is; a physical length (m, km, pc, ...) needs the hole's mass: where the argument's
  caller knows it (`mass_msun`) it is divided by $R_S$ of that mass, elsewhere it is
  refused with the fix (a plain number in R_S, or `schwarzschild_radii`).
- a mass: a Quantity in any mass unit becomes solar masses (astropy's nominal
  `u.M_sun`); a plain number is in solar masses.

A Quantity of another dimension (seconds for an angle, ...) is a `ValueError` naming
the argument, its value and what is valid (astropy's `UnitConversionError` is one).
"""

import sys

import numpy as np

from ._constants import RS_SUN_M


def astropy_units():
    """`astropy.units` where the caller has imported astropy (a Quantity can exist
    only then), else None: astropy, an optional extra, is not imported here."""
    return sys.modules.get("astropy.units")


def is_quantity(x) -> bool:
    """Whether `x` is an `astropy.units.Quantity` (or a subclass: `Angle`, `Distance`)."""
    u = sys.modules.get("astropy.units")
    return u is not None and isinstance(x, u.Quantity)


def _quantity(x):
    """`x` as one Quantity where it is one or a list or tuple holding one (astropy joins
    `[1 * u.deg, 2 * u.arcmin]` in the first one's unit), else None."""
    u = sys.modules.get("astropy.units")
    if u is None:
        return None
    if isinstance(x, u.Quantity):
        return x
    if isinstance(x, list | tuple) and any(isinstance(v, u.Quantity) for v in x):
        try:
            return u.Quantity(x)
        except (TypeError, ValueError) as e:  # a list of Quantities and bare numbers, ...
            raise ValueError(f"{_shown(x)}: {e}") from None
    return None


def _shown(q) -> str:
    """A short text of a Quantity (or list) for an error message."""
    text = str(q)
    return text if len(text) <= 80 else text[:77] + "..."


def _unit_of(q) -> str:
    return q.unit.to_string() or "dimensionless"


def _in(q, name: str, unit, kind: str, plain: str, units: str, equivalencies=None):
    """The Quantity `q` as a number in `unit`, or a `ValueError` naming `name`: `q` is
    not `kind`; give `plain` as a plain number, or a Quantity in `units`."""
    u = astropy_units()
    try:
        return q.to_value(unit, equivalencies=equivalencies or [])
    except u.UnitsError:
        raise ValueError(
            f"{name}={_shown(q)} is not {kind} ({q.unit.physical_type}): give {plain} as a "
            f"plain number, or a Quantity in {units}"
        ) from None


def angle(x, name: str):
    """`x` in radians: an astropy angle Quantity converted (a dimensionless one taken
    as radians), anything else returned as it is. A Quantity of another dimension is
    a `ValueError` naming `name`."""
    q = _quantity(x)
    if q is None:
        return x
    u = astropy_units()
    return _in(q, name, u.rad, "an angle", "radians", "an angle unit (u.deg, u.arcsec, u.rad)",
               u.dimensionless_angles())  # fmt: skip


def length(x, name: str, mass_msun=None):
    """`x` in units of R_S: a dimensionless astropy Quantity as its number, a physical
    length converted with the hole's mass `mass_msun` (solar masses, or a mass
    Quantity) where the caller knows it, refused otherwise; anything else returned as
    it is. A physical length without a mass, or a Quantity of another dimension, is
    a `ValueError` naming `name` and the fix."""
    q = _quantity(x)
    if q is None:
        return x
    u = astropy_units()
    if q.unit.physical_type == "dimensionless":
        return q.to_value(u.dimensionless_unscaled)
    try:
        metres = q.to_value(u.m)
    except u.UnitsError:
        raise ValueError(
            f"{name}={_shown(q)} is not a length ({q.unit.physical_type}): give it in "
            "units of the Schwarzschild radius R_S as a plain number"
        ) from None
    if mass_msun is None:
        raise ValueError(
            f"{name}={_shown(q)} is a length in {_unit_of(q)}, but jaxlens takes lengths in "
            "units of the Schwarzschild radius R_S = 2GM/c^2, which depends on the hole's "
            f"mass: give {name} in R_S as a plain number, or convert it with "
            f"jaxlens.schwarzschild_radii({name}, mass) (mass a Quantity, or solar masses)"
        )
    return metres / (RS_SUN_M * solar_masses(mass_msun, "mass"))


def solar_masses(x, name: str):
    """`x` in solar masses: an astropy mass Quantity converted (at astropy's nominal
    `u.M_sun`), anything else returned as it is. A Quantity of another dimension is a
    `ValueError` naming `name`."""
    q = _quantity(x)
    if q is None:
        return x
    return _in(q, name, astropy_units().M_sun, "a mass", "solar masses",
               "a mass unit (u.kg, u.M_sun)")  # fmt: skip


def metres(x, name: str):
    """`x` in metres: an astropy length Quantity converted, anything else returned as
    it is. A Quantity of another dimension (a dimensionless one included: it would be
    in R_S) is a `ValueError` naming `name`."""
    q = _quantity(x)
    if q is None:
        return x
    return _in(q, name, astropy_units().m, "a length", "metres",
               "a length unit (u.km, u.pc)")  # fmt: skip


def plain(x, name: str, what: str):
    """`x` where it is not an astropy Quantity, else a `ValueError` naming `name`: the
    argument is `what` (e.g. "a speed in units of c"), for which jaxlens reads no
    Quantity, and its unit is not dropped silently."""
    q = _quantity(x)
    if q is None:
        return x
    raise ValueError(
        f"{name}={_shown(q)} is an astropy Quantity, but {name} is {what}: give it as a "
        "plain number (jaxlens does not convert this unit)"
    )


def schwarzschild_radii(length, mass) -> np.ndarray | float:
    """A length in units of the Schwarzschild radius $R_S = 2GM/c^2$ of a hole of
    mass `mass`: the unit jaxlens takes lengths in (camera distance, disk radii, source
    distance, ...).

    **Arguments:**
    - `length`: an astropy length Quantity (`20 * u.km`, `8 * u.kpc`), or metres.
    - `mass`: the hole's mass, an astropy mass Quantity (`u.kg`, `u.M_sun`), or solar
      masses; positive and finite.

    **Returns:** `length` in units of R_S (a float, or a NumPy array for an array
    `length` or `mass`): $L / (R_{S,\\odot} M)$ with $R_{S,\\odot}$ = 2953.25 m.
    """
    m = np.asarray(solar_masses(mass, "mass"), dtype=float)
    if not np.all(np.isfinite(m) & (m > 0)):
        raise ValueError(f"mass={_shown(mass)} must be positive and finite (solar masses, or "
                         "a mass Quantity)")  # fmt: skip
    value = np.asarray(metres(length, "length"), dtype=float) / (RS_SUN_M * m)
    return float(value) if value.ndim == 0 else value
