"""`ButcherTableau` and the one explicit Runge-Kutta step that it drives."""

import equinox as eqx


def _rows_are_triangular(rows, diagonal):
    return all(len(row) == i + diagonal for i, row in enumerate(rows))


class ButcherTableau(eqx.Module):
    """The coefficients of an explicit Runge-Kutta method, as data.

    A step of size $h$ from $(u, u')$ of the second-order equation $u'' = f(u)$
    (written as the first-order system $(u, u')' = (u', f(u))$) takes the stages
    $U_i = u + h \\sum_{j<i} a_{ij} V_j$, $V_i = u' + h \\sum_j \\hat a_{ij} f(U_j)$
    and returns $u + h \\sum_i b_i V_i$, $u' + h \\sum_i b_i f(U_i)$.

    **Fields:**
    - `a`: stage coefficients, strictly lower triangular: row $i$ has $i$ entries.
    - `b`: weights of the solution, one per stage.
    - `c`: nodes, $c_i = \\sum_j a_{ij}$ (the stage's fraction of the step; kept
      for the order conditions, the orbit equation does not depend on $\\phi$).
    - `order`: order of the solution; the exponent of the step-size control is
      $1 / \\mathrm{order}$.
    - `b_error`: `None` for a fixed-step method, else $b - b^*$ with $b^*$ the weights
      of the embedded lower-order solution: the step's error estimate is
      $h \\sum_i (b_i - b^*_i) k_i$ and the step size adapts to it.
    - `a_velocity`: `None` for an ordinary Runge-Kutta method ($\\hat a = a$), else
      the coefficients $\\hat a$ of the velocity stages, lower triangular with the
      diagonal (row $i$ has $i + 1$ entries): stage $i$'s velocity may use the
      acceleration at its own position $U_i$. This is a partitioned Runge-Kutta
      method, still explicit because $f$ depends on $u$ alone; semi-implicit
      (symplectic) Euler is the one-stage case $a = ((),)$, $\\hat a = ((1,),)$.
    """

    a: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b: tuple[float, ...] = eqx.field(static=True)
    c: tuple[float, ...] = eqx.field(static=True)
    order: int = eqx.field(static=True)
    b_error: tuple[float, ...] | None = eqx.field(static=True, default=None)
    a_velocity: tuple[tuple[float, ...], ...] | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        stages = len(self.b)
        if len(self.a) != stages or len(self.c) != stages:
            raise ValueError(
                f"a has {len(self.a)} rows and c {len(self.c)} entries; b has {stages} "
                "stages: all three must agree"
            )
        if not _rows_are_triangular(self.a, 0):
            raise ValueError(
                f"a={self.a!r} must be strictly lower triangular (row i has i entries)"
            )
        if self.b_error is not None and len(self.b_error) != stages:
            raise ValueError(
                f"b_error has {len(self.b_error)} entries, not one per stage ({stages})"
            )
        if self.a_velocity is not None and not (
            len(self.a_velocity) == stages and _rows_are_triangular(self.a_velocity, 1)
        ):
            raise ValueError(
                f"a_velocity={self.a_velocity!r} must be lower triangular with the diagonal "
                f"(row i has i + 1 entries), {stages} rows"
            )
        if not self.order >= 1:
            raise ValueError(f"order={self.order!r} must be >= 1")

    @property
    def adaptive(self) -> bool:
        """True when the tableau carries an embedded error estimate."""
        return self.b_error is not None


def _combine(x, h, coefficients, slopes):
    # x + h * sum_j coefficients[j] * slopes[j], zero coefficients skipped (exactly the
    # same sum in floating point for finite slopes, and fewer operations).
    terms = [c * k for c, k in zip(coefficients, slopes) if c != 0.0]
    return x + h * sum(terms) if terms else x


def rk_step(tableau: ButcherTableau, f, u, v, h):
    """One explicit Runge-Kutta step of $u'' = f(u)$ driven by `tableau`.

    **Arguments:**
    - `tableau`: the method's `ButcherTableau`.
    - `f`: the acceleration, a function of $u$ alone.
    - `u, v`: the state $(u, u')$, arrays of one shape.
    - `h`: the step in the independent variable (for the orbit, azimuth in radians).

    **Returns:** `(u1, v1, error)`: the state after the step and, for an adaptive
    tableau, the error estimates `(eu, ev)` of both components (else `None`).
    """
    velocity_rows = tableau.a if tableau.a_velocity is None else tableau.a_velocity
    slopes_u, slopes_v = [], []  # u' = V_i and v' = f(U_i) at each stage
    for row, row_velocity in zip(tableau.a, velocity_rows):
        k = f(_combine(u, h, row, slopes_u))
        slopes_v.append(k)
        slopes_u.append(_combine(v, h, row_velocity, slopes_v))
    u1 = _combine(u, h, tableau.b, slopes_u)
    v1 = _combine(v, h, tableau.b, slopes_v)
    if tableau.b_error is None:
        return u1, v1, None
    error = tuple(
        h * sum(e * k for e, k in zip(tableau.b_error, s) if e != 0.0) for s in (slopes_u, slopes_v)
    )
    return u1, v1, error
