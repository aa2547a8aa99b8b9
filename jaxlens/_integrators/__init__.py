"""Integrators of the orbit equation: each scheme is a `ButcherTableau` (one file a
scheme) on one explicit Runge-Kutta step (`rk_step`) and one loop (`integrate`)."""

from ._tableau import ButcherTableau as ButcherTableau, rk_step as rk_step
from .dopri5 import DOPRI5 as DOPRI5
from .euler import EULER as EULER
from .integrate import integrate as integrate
from .rk4 import RK4 as RK4, rk4_step as rk4_step
