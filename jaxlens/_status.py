"""`RayStatus`: the outcome of a ray, as an enumeration with a message each."""

import equinox as eqx


class RayStatus(eqx.Enumeration):
    """The outcome of tracing a ray. `TraceResult.status` holds, per ray, the
    position of its item in this enumeration: `ESCAPED` (0), `CAPTURED` (1),
    `UNRESOLVED` (2). `RayStatus[RayStatus.unresolved]` is the message."""

    escaped = "the ray escaped to infinity ($u = 0$)"
    captured = "the ray crossed the horizon ($r = 1$, units of R_S)"
    unresolved = (
        "the ray is unresolved: it went beyond the winding budget (max_windings) or "
        "the step budget (max_steps) before escaping or being captured; it is never "
        "painted as captured"
    )


# The per-ray codes stored in `TraceResult.status`: the items' positions, in the order
# declared above (tests/test_trace.py checks the correspondence).
ESCAPED = 0
CAPTURED = 1
UNRESOLVED = 2
