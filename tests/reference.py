"""Independent references for the tests: mpmath quadrature and scipy elliptic integrals.

Nothing here shares code with jaxlens. The escape angle is the integral of
$1/\\sqrt{P(u)}$, $P = 1/b^2 - u^2 + u^3$, done by mpmath's tanh-sinh quadrature at
40 digits; at a turning point $u_t$ the substitution $u = u_t \\mp s^2$ removes the
square-root singularity, so the quadrature converges to full precision.
"""

import math

import mpmath as mp
import numpy as np
from scipy import special

B_CRIT = 1.5 * math.sqrt(3.0)


def escape_angle(alpha: float, distance: float, dps: int = 40):
    """Exact escape angle (radians) and outcome ('escaped' or 'captured') of a ray
    leaving a static camera at `distance` (R_S) at local angle `alpha` (radians).

    Evaluated at the exact binary values of the float inputs."""
    with mp.workdps(dps):
        a, d = mp.mpf(alpha), mp.mpf(distance)
        u0 = 1 / d
        b = d * abs(mp.sin(a)) / mp.sqrt(1 - u0)
        if b == 0:  # radial: straight in (captured) or straight out
            return 0.0, ("captured" if mp.cos(a) > 0 else "escaped")
        c = 1 / b**2
        roots = mp.polyroots([c, 0, -1, 1], maxsteps=400, extraprec=4 * dps, asc=True)
        real = sorted(mp.re(r) for r in roots if abs(mp.im(r)) < mp.mpf(10) ** (-dps + 5))
        inward = mp.cos(a) > 0
        p = lambda u: c - u**2 + u**3  # noqa: E731

        def plain(lo, hi):
            pts = [lo, hi]
            for r in [mp.mpf(2) / 3] + [mp.re(r) for r in roots]:
                if lo < r < hi:
                    pts.insert(-1, r)
            return mp.quad(lambda u: 1 / mp.sqrt(p(u)), sorted(pts))

        if len(real) == 3 and u0 <= real[1]:
            u1, u2, u3 = real

            def g(s):  # u = u2 - s^2
                return 2 / mp.sqrt((u2 - s * s - u1) * (u3 - u2 + s * s))

            i = mp.quad(g, [0, mp.sqrt(u2)])
            j = mp.quad(g, [0, mp.sqrt(u2 - u0)])
            return float(i + j if inward else i - j), "escaped"
        if len(real) == 3 and u0 >= real[2]:
            u1, u2, u3 = real

            def g(s):  # u = u3 + s^2
                return 2 / mp.sqrt((u3 + s * s - u1) * (u3 + s * s - u2))

            i = mp.quad(g, [0, mp.sqrt(1 - u3)])
            j = mp.quad(g, [0, mp.sqrt(u0 - u3)])
            return float(i - j if inward else i + j), "captured"
        if inward:
            return float(plain(u0, mp.mpf(1))), "captured"
        return float(plain(mp.mpf(0), u0)), "escaped"


def deflection_mp(alpha: float, distance: float, dps: int = 40) -> float:
    """Bending from the camera to infinity, Phi - (pi - alpha), for a ray with a
    turning point (b > b_c, camera outside the photon sphere), kept in mp digits."""
    with mp.workdps(dps + 20):
        a, d = mp.mpf(alpha), mp.mpf(distance)
        u0 = 1 / d
        b = d * abs(mp.sin(a)) / mp.sqrt(1 - u0)
        c = 1 / b**2
        roots = mp.polyroots([c, 0, -1, 1], maxsteps=400, extraprec=200, asc=True)
        roots = sorted(mp.re(r) for r in roots if abs(mp.im(r)) < mp.mpf(10) ** -50)
        u1, u2, u3 = roots

        def g(s):
            return 2 / mp.sqrt((u2 - s * s - u1) * (u3 - u2 + s * s))

        i = mp.quad(g, [0, mp.sqrt(u2)])
        j = mp.quad(g, [0, mp.sqrt(u2 - u0)])
        phi = i + j if mp.cos(a) > 0 else i - j
        return float(phi - (mp.pi - a))


def darwin_deflection(b: float) -> float:
    """Darwin (1959) exact deflection through scipy's Legendre integrals (M = 1/2)."""
    m = 0.5
    # periapsis r0: b^2 = r0^3 / (r0 - 1), largest root
    r0 = max(r.real for r in np.roots([1.0, 0.0, -b * b, b * b]) if abs(r.imag) < 1e-12)
    q = math.sqrt((r0 - 2 * m) * (r0 + 6 * m))
    k2 = (q - r0 + 6 * m) / (2 * q)
    chi = math.asin(math.sqrt((q - r0 + 2 * m) / (q - r0 + 6 * m)))
    return 4 * math.sqrt(r0 / q) * (special.ellipk(k2) - special.ellipkinc(chi, k2)) - math.pi


def shadow_angle(distance: float) -> float:
    """Synge's shadow angle, radians (PHYSICS.md), at 40 digits."""
    with mp.workdps(40):
        d = mp.mpf(distance)
        s = B_CRIT_MP() * mp.sqrt(1 - 1 / d) / d
        a = mp.asin(min(s, mp.mpf(1)))
        return float(a if d >= 1.5 else mp.pi - a)


def B_CRIT_MP():  # noqa: N802
    return 3 * mp.sqrt(3) / 2
