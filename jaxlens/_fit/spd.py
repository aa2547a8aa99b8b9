"""Small symmetric positive definite systems solved without LAPACK."""


def solve_spd(a, b):
    """`x (p,)` with `a @ x = b` for a small symmetric positive definite `a (p, p)` (p
    static, a few parameters) by Gauss-Jordan elimination written out: p steps of
    array operations, no pivots (none is needed for such a matrix), no LAPACK call.

    The fit's loops call it where they called `jnp.linalg.solve`, `eigh` or lineax's QR
    (the Levenberg-Marquardt step, `solve.ScaledNormalEquations`): in the
    solver's loop, `eigh` of the accepted point's Jacobian gave one executable
    different results from run to run (a ring fit: 11 of 15 runs in one process
    agreed, the others ended at D = 1.5, 1e40, ...), a race of XLA's CPU runtime
    around the call; and a program without LAPACK calls loads without setting up
    JAX's LAPACK kernels (which imports scipy.linalg).

    A zero pivot (a zero row and column) gives non-finite values, as `solve` does."""
    x = b
    for k in range(a.shape[0]):
        row, xk = a[k] / a[k, k], x[k] / a[k, k]
        col = a[:, k].at[k].set(0.0)
        a = (a - col[:, None] * row[None, :]).at[k].set(row)
        x = (x - col * xk).at[k].set(xk)
    return x
