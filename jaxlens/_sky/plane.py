"""A flat picture behind the hole."""

import math
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .. import _limits, _schema
from .._io import read_image
from .._limits import radians, real
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

    **Fields:** `image (h, w, 3)` linear radiance (finite), `width` (radians or an
    astropy angle, full horizontal angle, in $(0, \\pi)$), `brightness` (scale, in
    [0, 1e30]), `yaw`, `pitch`, `roll` (radians or astropy angles, finite, as
    `Rotated`).
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
        self.width = radians("width", width)
        self.brightness = real("brightness", brightness)
        self.yaw, self.pitch = radians("yaw", yaw), radians("pitch", pitch)
        self.roll = radians("roll", roll)

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
