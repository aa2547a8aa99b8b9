"""The classical fourth-order Runge-Kutta method."""

from .._orbit import acceleration
from ._tableau import ButcherTableau, rk_step

RK4 = ButcherTableau(
    a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    c=(0.0, 0.5, 0.5, 1.0),
    order=4,
)


def rk4_step(u, v, h):
    """One classical fourth-order Runge-Kutta step of the orbit equation.

    **Arguments:**
    - `u, v`: $u = 1/r$ (units of $1/R_S$) and $du/d\\phi$, arrays of one shape.
    - `h`: the step in azimuth (radians).

    **Returns:** `(u, v)` after the step.
    """
    u1, v1, _ = rk_step(RK4, acceleration, u, v, h)
    return u1, v1
