"""A flat picture behind the hole."""

import math
from pathlib import Path
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .. import _limits, _schema
from .._io import read_image
from .._limits import real
from .._messages import describe
from .._schema import Key, greater, in_range
from .._util import concrete as _concrete
from ._base import AbstractRGBSky, bilinear, to_rgb, unrotate
from ._table import BRIGHTNESS, IMAGE_PATH, ORIENTATION, orientation


class PlaneImage(AbstractRGBSky):
    """A flat picture behind the hole: an image of angular width `width` centred on
    $+z$, in gnomonic (pinhole) projection, zero outside it.

    A picture of physical width $S$ on a plane at distance $L$ behind the hole (the
    original C++ program's background) is `PlaneImage.at_distance(image, S, L)`:
    width $= 2\\arctan(S / 2L)$; this takes each ray's asymptote through the hole's
    centre, exact when $L$ is large against the rays' impact parameters (off by
    $b/|\\cos\\Phi|$ on the plane). In a `Scene(..., source_plane=L)` it is read at
    each ray's exact crossing of the plane (`plane_crossings`), and with
    `source_distance=L` at its crossing of the sphere $r = L$, off by about
    $(\\rho/L)^2 b/2$ at a point $\\rho$ from the axis.

    **Fields:** `image (h, w, 3)` linear radiance (finite), `width` (radians, full
    horizontal angle, in $(0, \\pi)$), `brightness` (scale, in [0, 1e30]), `yaw`,
    `pitch`, `roll` (radians, finite, as `Rotated`).
    """

    image: Float[Array, "h w 3"]
    width: Float[Array, ""]
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]
    limits: ClassVar = {
        "image": _limits.texture(),
        "width": _limits.between(0.0, math.pi, "finite and in (0, pi)", "radians"),
        "brightness": _limits.scale(),
        **_limits.ORIENTATION,
    }

    def __init__(self, image, width, *, brightness=1.0, yaw=0.0, pitch=0.0, roll=0.0):
        if isinstance(image, jax.core.Tracer):
            self.image = image
        else:
            self.image = jnp.asarray(to_rgb(image, name="plane image"))
        self.width = real("width", width)
        self.brightness = real("brightness", brightness)
        self.yaw, self.pitch, self.roll = real("yaw", yaw), real("pitch", pitch), real("roll", roll)

    def __check_init__(self):
        wv = _concrete(self.width)
        if wv is not None and not np.all(np.isfinite(wv) & (wv > 0) & (wv < math.pi)):
            raise ValueError(
                f"width={np.degrees(wv).tolist()!r} degrees must be in (0, 180) degrees"
            )

    @classmethod
    def at_distance(cls, image, size, distance, **kwargs) -> "PlaneImage":
        """A picture `size` wide (units of R_S) on a plane `distance` behind the hole
        (units of R_S)."""
        if not (size > 0 and distance > 0):
            raise ValueError(f"size={size!r} and distance={distance!r} must be > 0 (R_S)")
        return cls(image, 2.0 * math.atan(0.5 * size / distance), **kwargs)

    @classmethod
    def from_file(cls, path, width, **kwargs) -> "PlaneImage":
        """Read the picture with OpenImageIO; `width` in radians."""
        return cls(to_rgb(read_image(path), name=f"plane image {str(path)!r}"), width, **kwargs)

    def __call__(self, n):
        dt = n.dtype
        n = unrotate(n, self.yaw, self.pitch, self.roll)
        h, w = self.image.shape[:2]
        front = n[..., 2] > 0
        nz = jnp.where(front, n[..., 2], 1.0)
        scale = (0.5 * w) / jnp.tan(0.5 * self.width.astype(dt))  # pixels per unit tangent
        u = n[..., 0] / nz * scale + (0.5 * w - 0.5)
        v = (0.5 * h - 0.5) - n[..., 1] / nz * scale
        # Bilinear with zero texels outside: a one-texel fade at the border. The
        # image is sampled with a one-texel zero frame, so every index is in range.
        framed = jnp.pad(self.image, ((1, 1), (1, 1), (0, 0)))
        u = jnp.clip(u + 1.0, 0.0, w + 1.0)
        v = jnp.clip(v + 1.0, 0.0, h + 1.0)
        u0 = jnp.minimum(jnp.floor(u), w)
        v0 = jnp.minimum(jnp.floor(v), h)
        i0, j0 = u0.astype(jnp.int32), v0.astype(jnp.int32)
        val = bilinear(framed, j0, i0, u - u0, v - v0, dt)
        return self.brightness.astype(dt) * jnp.where(front[..., None], val, 0.0)


class PlaneCrossings(NamedTuple):
    """Where rays from a static camera cross the plane $z = L$ behind the hole, on
    their way out (`plane_crossings`).

    **Fields:** `phi`: the azimuth swept from the camera to the crossing point, in the
    ray's orbital plane (radians: the point lies in the direction at `phi` from the
    hole->camera axis, a sky direction as for a sky at infinity); `radius`: its distance
    from the hole (units of R_S); `hit`: whether the ray crosses the plane outward (it
    escapes, its asymptote heads behind the hole, and Newton's iteration converged).
    Where `hit` is false both values are 0.
    """

    phi: Array
    radius: Array
    hit: Array


def plane_crossings(alpha, distance, plane_distance, *, steps: int = 12) -> PlaneCrossings:
    """Exact outward crossings of the plane $z = L$ (perpendicular to the line of sight,
    `plane_distance` $L$ behind the hole) by rays from a static camera at `distance`.

    The point where a ray leaves through the plane lies on the sphere of some radius
    $R$, at the azimuth $\\varphi_R$ of the ray's outward crossing of that sphere
    (`radius_crossings`: its only crossing for $R \\ge D$, its second for $R < D$);
    Newton's method solves $-R\\cos\\varphi_R = L$ for $R$ (the slope from
    $d\\varphi/dr = u^2/\\sqrt{1/b^2 - u^2 + u^3}$, $u = 1/r$), from the point where
    the ray's asymptote, taken through the hole's centre, meets the plane: what
    `PlaneImage.at_distance` reads.
    The direction from the hole to that point, given to a `PlaneImage.at_distance` of
    the same $L$, is the picture's exact point (its gnomonic projection is the plane's).

    **Arguments:** `alpha` (local angle, radians), `distance` $D > 1$ and
    `plane_distance` $L > 0$ (units of R_S), broadcasting; `steps` (static): Newton
    steps (the iteration converges quadratically from an error of order $b/L$).

    **Returns:** `PlaneCrossings(phi, radius, hit)`.
    """
    from .._exact import ESCAPED, escape_angle, finite_crossings, impact_parameter

    alpha, d, plane = jnp.broadcast_arrays(
        *(jnp.asarray(v, jnp.result_type(float, alpha, distance, plane_distance))
          for v in (alpha, distance, plane_distance))
    )  # fmt: skip
    phi_inf, status, r_min = escape_angle(alpha, d)
    heads_behind = (status == ESCAPED) & (jnp.cos(phi_inf) < 0)
    c0 = jnp.where(heads_behind, -jnp.cos(phi_inf), 1.0)
    # The crossing of the outgoing branch lies beyond the periapsis.
    floor = r_min * (1.0 + 1e-6)

    def crossing(r):  # the azimuth of the outward crossing of r = R
        c = finite_crossings(alpha, d, r)
        return jnp.where(r >= d, c.first, c.second)

    inv_b2 = 1.0 / impact_parameter(alpha, d) ** 2

    def step(_, r):
        phi = crossing(r)
        # On the way out d(phi)/dr = u^2 / sqrt(G(u)), G = 1/b^2 - u^2 + u^3, u = 1/r.
        u = 1.0 / r
        dphi = u * u / jnp.sqrt(jnp.maximum(inv_b2 - u * u * (1.0 - u), jnp.finfo(u.dtype).tiny))
        z = -r * jnp.cos(phi)
        dz = -jnp.cos(phi) + r * jnp.sin(phi) * dphi
        new = r - (z - plane) / jnp.where(dz > 0, dz, 1.0)
        return jnp.where(heads_behind & (dz > 0), jnp.maximum(new, floor), r)

    r = jnp.maximum(plane / c0, floor)
    r = jax.lax.fori_loop(0, steps, step, r)
    phi = crossing(r)
    tol = 1e4 * jnp.finfo(r.dtype).eps  # relative: 2e-12 in float64, 1e-3 in float32
    hit = heads_behind & (jnp.abs(-r * jnp.cos(phi) - plane) <= tol * jnp.maximum(plane, r))
    return PlaneCrossings(jnp.where(hit, phi, 0.0), jnp.where(hit, r, 0.0), hit)


def _check(where: str, fields: dict) -> None:
    if "path" not in fields:
        raise ValueError(f'{where} needs a path = "IMAGE" (an image file)')
    has_width = "width_deg" in fields
    has_plane = "size" in fields or "plane_distance" in fields
    if has_width and has_plane:
        raise ValueError(f"{where}: give width_deg or size and plane_distance, not both")
    if has_plane and not ("size" in fields and "plane_distance" in fields):
        raise ValueError(f"{where}: size and plane_distance go together")
    if has_plane:
        size, dist = fields["size"], fields["plane_distance"]
        if not math.degrees(2.0 * math.atan(0.5 * size / dist)) < 180.0:
            raise ValueError(f"{where}: size = {describe(size)} at plane_distance = "
                             f"{describe(dist)} is a picture 180 degrees wide: size / "
                             "plane_distance must be finite (units of R_S)")  # fmt: skip


@_schema.register(
    "sky",
    "plane",
    {
        **IMAGE_PATH,
        "width_deg": Key("float", None, in_range(0.0, 180.0), "a number in (0, 180) (degrees)"),
        "size": Key("float", None, greater(0.0), "a number > 0 (units of R_S)"),
        "plane_distance": Key("float", None, greater(0.0), "a number > 0 (units of R_S)"),
        **BRIGHTNESS,
        **ORIENTATION,
    },
    check=_check,
)
def _plane(fields: dict, base: Path) -> PlaneImage:
    """`path` is relative to `base`; the width is `width_deg`, or that of a picture
    `size` wide at `plane_distance` (units of R_S), or 30 degrees."""
    path = base / fields["path"]
    image = to_rgb(read_image(path), name=f"plane image {str(path)!r}")
    kw = dict(brightness=fields["brightness"], **orientation(fields))
    if "size" in fields:
        return PlaneImage.at_distance(image, fields["size"], fields["plane_distance"], **kw)
    return PlaneImage(image, math.radians(fields.get("width_deg", 30.0)), **kw)
