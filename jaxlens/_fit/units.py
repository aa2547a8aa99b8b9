"""Units: the Schwarzschild radius of a solar mass, and conversions between R_S,
metres and solar masses."""

from jaxtyping import ArrayLike

GM_SUN = 1.3271244e20  # IAU 2015 nominal solar mass parameter, m^3 / s^2
C_LIGHT = 299792458.0  # m / s
RS_SUN_M = 2.0 * GM_SUN / C_LIGHT**2  # Schwarzschild radius of one solar mass: 2953.25 m


def schwarzschild_radius_m(mass_msun: ArrayLike):
    """Schwarzschild radius $2GM/c^2$ in metres of a mass in solar masses."""
    return RS_SUN_M * mass_msun


def distance_in_metres(distance: ArrayLike, mass_msun: ArrayLike):
    """Camera distance in metres, from the distance in units of R_S and the mass of the
    hole in solar masses."""
    return distance * schwarzschild_radius_m(mass_msun)


def mass_from_distance(distance: ArrayLike, distance_m: ArrayLike):
    """Mass of the hole in solar masses, from the camera distance in units of R_S and
    the same distance in metres."""
    return distance_m / (distance * RS_SUN_M)
