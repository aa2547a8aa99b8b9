"""`RayStatus` and `TraceResult`: the outcome of one ray (an enumeration with a message
each) and of tracing a batch of rays."""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


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


class TraceResult(eqx.Module):
    """Outcome of tracing rays from a static camera.

    **Fields:**
    - `phi`: escape angle, the azimuth swept in the orbital plane from the camera
      to the escaping asymptote (radians; $\\pi - \\alpha$ in flat space). For a
      captured ray, the azimuth at which it crosses the horizon.
    - `status`: per ray, an int8 code: `ESCAPED` (0), `CAPTURED` (1) or
      `UNRESOLVED` (2: beyond the winding budget or the step budget; never painted
      as captured), the positions of the items of `RayStatus`, which holds the
      message of each. An array, not an `eqx.Enumeration` item, so that it indexes,
      shards and compares like the other fields.
    - `r_min`: smallest radius reached (units of R_S; 1 for captured rays).
    """

    phi: Float[Array, "..."]
    status: Int[Array, "..."]
    r_min: Float[Array, "..."]

    @property
    def captured(self):
        """True where the ray falls into the horizon."""
        return self.status == CAPTURED

    @property
    def escaped(self):
        """True where the ray reaches infinity."""
        return self.status == ESCAPED

    @property
    def unresolved(self):
        """True where the ray ran out of its winding or step budget."""
        return self.status == UNRESOLVED

    @property
    def half_turns(self):
        """Number of completed half-turns, $\\lfloor \\phi / \\pi \\rfloor$."""
        return jnp.floor(self.phi / jnp.pi).astype(jnp.int32)
