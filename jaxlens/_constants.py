"""Physical constants the library's unit conversions share (SI)."""

GM_SUN = 1.3271244e20  # IAU 2015 nominal solar mass parameter, m^3 / s^2
C_LIGHT = 299792458.0  # m / s
RS_SUN_M = 2.0 * GM_SUN / C_LIGHT**2  # Schwarzschild radius of one solar mass: 2953.25 m
