"""A static pinhole camera at radius D looking at the hole (PHYSICS.md conventions).

World frame: the hole at the origin, the camera on the $-z$ axis, so $+z$ points from
the camera through the hole ("behind the hole"); $x$ to the right and $y$ up in the
image when yaw = pitch = roll = 0.
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


def _concrete(x):
    try:
        return np.asarray(x)
    except Exception:  # a tracer: checked by the caller with eqx.error_if if at all
        return None


class Camera(eqx.Module):
    """Pinhole camera of a static observer at radius `distance`.

    **Fields:**
    - `distance`: camera radius $D > 1$ (units of R_S).
    - `fov`: horizontal field of view (radians, $0 < $ fov $< \\pi$).
    - `width`, `height`: image size in pixels (static).
    - `yaw`, `pitch`, `roll`: orientation (radians); yaw turns the view to the
      right (+x), pitch up (+y), roll about the line of sight. All zero: the hole
      is at the image centre.
    - `supersample`: area sampling with $k \\times k$ samples a pixel (static).
    """

    distance: Float[Array, ""]
    fov: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]
    supersample: int = eqx.field(static=True)

    def __init__(
        self,
        distance: ArrayLike,
        fov: ArrayLike,
        width: int,
        height: int,
        *,
        yaw: ArrayLike = 0.0,
        pitch: ArrayLike = 0.0,
        roll: ArrayLike = 0.0,
        supersample: int = 1,
    ):
        self.distance = jnp.asarray(distance, dtype=jnp.result_type(float, distance))
        self.fov = jnp.asarray(fov, dtype=jnp.result_type(float, fov))
        self.width = int(width)
        self.height = int(height)
        self.yaw = jnp.asarray(yaw, dtype=self.fov.dtype)
        self.pitch = jnp.asarray(pitch, dtype=self.fov.dtype)
        self.roll = jnp.asarray(roll, dtype=self.fov.dtype)
        self.supersample = int(supersample)

    def __check_init__(self):
        for name in ("width", "height", "supersample"):
            v = getattr(self, name)
            if v < 1:
                raise ValueError(f"{name}={v} must be a positive whole number")
        d = _concrete(self.distance)
        if d is not None and (not np.all(np.isfinite(d)) or not np.all(d > 1.0)):
            raise ValueError(f"distance={d!r} must be finite and > 1 (units of R_S, horizon at 1)")
        f = _concrete(self.fov)
        if f is not None and (not np.all(np.isfinite(f)) or not np.all((f > 0) & (f < math.pi))):
            raise ValueError(f"fov={np.degrees(f)!r} degrees must be in (0, 180) degrees")

    @property
    def focal(self) -> Float[Array, ""]:
        """Focal length in pixels: $(W/2) / \\tan(\\mathrm{FOV}/2)$."""
        return (0.5 * self.width) / jnp.tan(0.5 * self.fov)

    def sample_xy(self, row0=0, rows: int | None = None):
        """Image-plane coordinates of the area samples of rows `row0 .. row0+rows`.

        Pixel (i, j) has its centre at $x = i + 0.5 - W/2$, $y = H/2 - (j + 0.5)$;
        sample (m, n) of $k \\times k$ sits at column $i + (m + 0.5)/k$, row
        $j + (n + 0.5)/k$.

        **Returns:** `x, y` of shape `(rows, W, k*k)` (pixels).
        """
        rows = self.height if rows is None else rows
        k = self.supersample
        dtype = self.fov.dtype
        sub = (jnp.arange(k, dtype=dtype) + 0.5) / k
        col = jnp.arange(self.width, dtype=dtype)[:, None] + sub[None, :]  # (W, k)
        row = (jnp.asarray(row0, dtype) + jnp.arange(rows, dtype=dtype))[:, None] + sub
        x = col - 0.5 * self.width  # (W, k): sample column offset from the left edge
        y = 0.5 * self.height - row  # (rows, k)
        xs = jnp.broadcast_to(x[None, :, None, :], (rows, self.width, k, k))
        ys = jnp.broadcast_to(y[:, None, :, None], (rows, self.width, k, k))
        return xs.reshape(rows, self.width, k * k), ys.reshape(rows, self.width, k * k)

    def rotation(self) -> Float[Array, "3 3"]:
        """Camera-to-world rotation: roll about the view axis, then pitch, then yaw."""
        cy, sy = jnp.cos(self.yaw), jnp.sin(self.yaw)
        cp, sp = jnp.cos(self.pitch), jnp.sin(self.pitch)
        cr, sr = jnp.cos(self.roll), jnp.sin(self.roll)
        one, zero = jnp.ones_like(cy), jnp.zeros_like(cy)
        r_yaw = jnp.array([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
        r_pitch = jnp.array([[one, zero, zero], [zero, cp, sp], [zero, -sp, cp]])
        r_roll = jnp.array([[cr, -sr, zero], [sr, cr, zero], [zero, zero, one]])
        return r_yaw @ r_pitch @ r_roll

    def rays(self, row0=0, rows: int | None = None):
        """Local angles of the samples of rows `row0 .. row0+rows`.

        **Returns:** `alpha` (angle from the direction of the hole, radians),
        `cos_beta`, `sin_beta` (the orbital plane: the ray's direction across the
        line of sight), each of shape `(rows, W, k*k)`.
        """
        x, y = self.sample_xy(row0, rows)
        f = self.focal
        oriented = not all(
            (c := _concrete(a)) is not None and np.all(c == 0)
            for a in (self.yaw, self.pitch, self.roll)
        )
        if oriented:
            rot = self.rotation()
            dx = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * f
            dy = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * f
            dz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * f
        else:
            dx, dy, dz = x, y, jnp.broadcast_to(f, x.shape)
        rho = jnp.hypot(dx, dy)
        alpha = jnp.arctan2(rho, dz)
        safe = rho > 0
        rho_ = jnp.where(safe, rho, 1.0)
        return alpha, jnp.where(safe, dx / rho_, 1.0), jnp.where(safe, dy / rho_, 0.0)


def sky_direction(phi, cos_beta, sin_beta):
    """World direction of the escaping asymptote: angle `phi` from the hole-to-camera
    axis ($-z$) in the plane picked by beta.

    **Returns:** unit vectors `(..., 3)`; $+z$ (behind the hole) where $\\phi = \\pi$.
    """
    s, c = jnp.sin(phi), jnp.cos(phi)
    return jnp.stack([s * cos_beta, s * sin_beta, -c], axis=-1)
