"""Semi-implicit (symplectic) Euler, the original C++ program's scheme: first order.

$u'_{n+1} = u'_n + h f(u_n)$, then $u_{n+1} = u_n + h u'_{n+1}$: the velocity uses the
acceleration at the stage's own position (`a_velocity` has the diagonal), which makes
the method symplectic, so the first integral stays bounded at $O(h)$ and does not drift.
"""

from ._tableau import ButcherTableau

EULER = ButcherTableau(a=((),), b=(1.0,), c=(0.0,), order=1, a_velocity=((1.0,),))
