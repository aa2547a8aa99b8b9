"""`SourceDistance`: how far behind the hole a fit's source is, in the terms a user
knows it (its radius in R_S, or its distance behind the hole with the observer's
distance or the hole's mass), and the radius of the source sphere it gives the model."""

import dataclasses
import math

from .units import (
    RS_SUN_M,
    as_metres,
    as_solar_masses,
    is_quantity,
    schwarzschild_radius_m,
    to_metres,
    to_solar_masses,
)


@dataclasses.dataclass(frozen=True, kw_only=True)
class SourceDistance:
    """Where the fitted source lies: on a sphere of radius $R$ (units of R_S) about the
    hole, the camera at $D$ in front of it (a lens at distance $D_{OL}$ from the
    observer, the source $D_{LS}$ behind it). Give one of three combinations, by
    keyword:

    - `SourceDistance(radius=R)`: $R$ in units of R_S, held fixed. The fit gives $D$
      in R_S; `Fit.distance_m(mass)` and `Fit.mass_msun(distance_m)` scale it.
    - `SourceDistance(behind=D_LS, observer=D_OL)`: both distances known in metres
      (the observer's is the camera's). Then $R = D \\, D_{LS} / D_{OL}$ follows the
      fitted $D$ (its derivative is in the fit's Jacobian, so $D$'s error allows for
      it) and the fit reports the mass $M = D_{OL} / (D \\, R_{S\\odot})$ with its
      standard error (`Fit.mass`, `Fit.mass_err`).
    - `SourceDistance(behind=D_LS, mass=M)`: the source's distance behind the hole and
      the mass known: $R = D_{LS} / R_S(M)$ is held fixed and the fit reports the
      observer's distance $D_{OL} = D \\, R_S(M)$ (`Fit.observer_distance`,
      `Fit.observer_distance_err`).

    Distances are astropy length `Quantity`s or plain numbers in metres; the mass an
    astropy mass `Quantity` or a number of solar masses. Where any input is a Quantity
    the results are Quantities too (metres, `u.M_sun`), else floats. $R$ and
    $D_{OL}$, $D_{LS}$ are measured from the hole's centre (Schwarzschild $r$), which
    for a real lens is the distance to within $R_S$.

    **Fields:** `radius` (R_S), `behind` ($D_{LS}$), `observer` ($D_{OL}$), `mass`;
    the ones not given are None. Raises `ValueError` for any other combination, or a
    value that is not positive and finite (a radius at most 1 R_S, inside the horizon,
    included).
    """

    radius: float | None = None
    behind: object = None
    observer: object = None
    mass: object = None

    def __post_init__(self):
        given = tuple(n for n in ("radius", "behind", "observer", "mass")
                      if getattr(self, n) is not None)  # fmt: skip
        if given not in (("radius",), ("behind", "observer"), ("behind", "mass")):
            raise ValueError(
                f"SourceDistance({', '.join(f'{n}=...' for n in given)}) is not one of the "
                "three ways to place the source: radius=R (units of R_S); behind=D_LS "
                "with observer=D_OL (metres or astropy lengths: the mass is measured); "
                "behind=D_LS with mass=M (solar masses: the observer's distance is measured)"
            )
        if self.radius is not None:
            if is_quantity(self.radius):
                raise ValueError(f"radius={self.radius!r} is in units of R_S, a plain "
                                 "number (a distance in metres is behind=..., with "
                                 "observer= or mass=)")  # fmt: skip
            r = float(self.radius)
            if not (math.isfinite(r) and r > 1.0):
                raise ValueError(f"radius={self.radius!r} must be finite and > 1 (units of "
                                 "R_S: outside the horizon)")  # fmt: skip
        # Each given value converted once, so that a bad one is refused here.
        self.behind_m, self.observer_m, self.mass_msun  # noqa: B018
        if self.mass is not None and not (r := self.linear()[1]) > 1.0:
            raise ValueError(
                f"behind={self.behind!r} is {r:.6g} R_S for mass={self.mass!r}: the "
                "source sphere must lie outside the horizon (> 1 R_S)"
            )

    @property
    def behind_m(self) -> float | None:
        """$D_{LS}$ in metres (None where not given)."""
        return None if self.behind is None else to_metres(self.behind, name="behind")

    @property
    def observer_m(self) -> float | None:
        """$D_{OL}$ in metres (None where not given)."""
        return None if self.observer is None else to_metres(self.observer, name="observer")

    @property
    def mass_msun(self) -> float | None:
        """The mass in solar masses (None where not given)."""
        return None if self.mass is None else to_solar_masses(self.mass, name="mass")

    @property
    def quantities(self) -> bool:
        """Whether any input is an astropy `Quantity` (the results then are too)."""
        return any(is_quantity(v) for v in (self.behind, self.observer, self.mass))

    @property
    def follows_distance(self) -> bool:
        """Whether $R$ changes with the fitted $D$ (`behind` and `observer` given)."""
        return self.observer is not None

    def linear(self) -> tuple[float, float]:
        """`(slope, offset)` with $R = \\mathrm{slope} \\cdot D + \\mathrm{offset}$
        (units of R_S): `(D_LS / D_OL, 0)` where $R$ follows $D$, else `(0, R)`."""
        if self.follows_distance:
            return self.behind_m / self.observer_m, 0.0
        if self.radius is not None:
            return 0.0, float(self.radius)
        return 0.0, self.behind_m / schwarzschild_radius_m(self.mass_msun)

    def radius_of(self, distance):
        """The source sphere's radius $R$ (units of R_S) for a camera at `distance`
        (units of R_S; an array or a traced value: differentiable)."""
        slope, offset = self.linear()
        return slope * distance + offset

    def mass_of(self, distance: float, error: float):
        """The mass $D_{OL} / (D R_{S\\odot})$ and its standard error for a fitted `distance`
        (R_S) of standard error `error` (solar masses, Quantities where the inputs
        were); None where the observer's distance is not given."""
        if self.observer is None:
            return None
        m = self.observer_m / (distance * RS_SUN_M)
        q = self.quantities
        return as_solar_masses(m, q), as_solar_masses(m * error / distance, q)

    def observer_distance_of(self, distance: float, error: float):
        """The observer's distance $D \\, R_S(M)$ and its standard error for a fitted
        `distance` (R_S) of standard error `error` (metres, Quantities where the inputs
        were); the given one (error 0) where `observer` was given, None for `radius`."""
        q = self.quantities
        if self.observer is not None:
            return as_metres(self.observer_m, q), as_metres(0.0, q)
        if self.mass is None:
            return None
        rs = float(schwarzschild_radius_m(self.mass_msun))
        return as_metres(distance * rs, q), as_metres(error * rs, q)
