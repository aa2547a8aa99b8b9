"""Point sources: image positions by the lens equation on the ray map, magnification
from the Jacobian of the lens map by autodiff (static camera at $D$, units of R_S).

Camera frame as in `_camera`: the hole on $+z$. A source at infinity at angle
$\\theta$ from $+z$ (the direction behind the hole) and azimuth $\\beta_s$ has images in
the orbital plane of $\\beta_s$: where the escape angle $\\Phi(\\alpha) = (2m+1)\\pi -
\\theta$ on the source's side (order $m = 0$: the primary image) and $(2m+1)\\pi +
\\theta$ on the other side ($\\beta_s + \\pi$; $m = 0$: the secondary image).

The lens map sends an image-plane point $p = \\alpha(\\cos\\beta, \\sin\\beta)$ (azimuthal
equidistant coordinates about the hole's direction, radians) to the source point
$q = \\theta(\\cos\\beta', \\sin\\beta')$ (the same about $+z$). The magnification is the
ratio of solid angles, $\\mu = [\\sin\\alpha/\\alpha]\\,/\\,[\\sin\\theta/\\theta] \\,/\\,
\\det(\\partial q/\\partial p)$, signed by the image's parity; the Jacobian is
`jax.jacfwd` of the exact lens map.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._camera import Camera, sky_direction
from ._messages import shown
from ._ray_inputs import DISTANCE_MESSAGE, check_distance, check_real, distance_bad
from ._raymap import RayMap
from ._util import concrete


def _checked_map(ray_map: RayMap) -> RayMap:
    """`ray_map` with its distance checked as `trace` checks it (a map's distance may
    have been set by `eqx.tree_at`): a `ValueError` when known, `eqx.error_if` when
    traced, on the knot values (which every use reads; the distance itself may not be)."""
    if not isinstance(ray_map, RayMap):
        raise TypeError(f"ray_map={shown(ray_map)} must be a RayMap (jl.RayMap.build(distance))")
    if concrete(ray_map.distance) is not None:
        check_distance(concrete(ray_map.distance))
        return ray_map
    phi = eqx.error_if(ray_map.phi, distance_bad(ray_map.distance), DISTANCE_MESSAGE)
    return eqx.tree_at(lambda m: m.phi, ray_map, phi)


def _checked_points(name: str, x, valid: str, bad_of):
    """`x` (real numbers) checked with `bad_of(x, xp)` (True where bad): a `ValueError`
    naming `name`, the first bad value and `valid` when known, `eqx.error_if` (one
    reduction) when traced."""
    x = check_real(name, x)
    c = concrete(x)
    if c is not None:
        c = np.asarray(c, float)
        bad = bad_of(c, np)
        if np.any(bad):
            raise ValueError(f"{name}={shown(c[bad][0].tolist())} is not valid: {valid}")
        return x
    x = jnp.asarray(x, jnp.result_type(float, x))
    return eqx.error_if(x, jnp.any(bad_of(x, jnp)), f"{name} must be {valid}")


def lens_map(p: Float[Array, "... 2"], ray_map: RayMap) -> Float[Array, "... 2"]:
    """Source position of the image-plane point `p` (radians, azimuthal equidistant
    about the hole's direction) for the static camera of `ray_map` (a `RayMap`: the
    escape angle of the camera's distance, differentiable in it).

    **Returns:** $q$ `(..., 2)`: the escaping ray's asymptote, azimuthal equidistant
    about $+z$ (radians). Meaningful outside the shadow.
    """
    alpha = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
    n = sky_direction(ray_map.escape_angle(alpha), p[..., 0] / alpha, p[..., 1] / alpha)
    rho = jnp.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2)
    theta = jnp.arctan2(rho, n[..., 2])
    return (theta / rho)[..., None] * n[..., :2]


def point_lens_magnification(u: ArrayLike):
    """Weak-field point-lens magnifications $(\\mu_+, \\mu_-)$ at source offset `u` in
    Einstein angles: $\\mu_\\pm = 1/2 \\pm (u^2 + 2)/(2u\\sqrt{u^2 + 4})$, total
    $|\\mu_+| + |\\mu_-| = (u^2 + 2)/(u\\sqrt{u^2 + 4})$. $\\mu_-$ is negative (parity)."""
    u = jnp.asarray(u, jnp.result_type(float, u))
    a = (u * u + 2.0) / (2.0 * u * jnp.sqrt(u * u + 4.0))
    return 0.5 + a, 0.5 - a


def magnification(p: Float[Array, "... 2"], ray_map: RayMap) -> Float[Array, "..."]:
    """Signed magnification (solid-angle ratio; negative for mirrored images) of the
    image at image-plane point `p` (radians, see `lens_map`; finite, not at the origin,
    the direction of the hole, last axis of 2) for the camera of `ray_map` (its distance
    $1 < D \\le 10^{30}$, units of R_S), from `jax.jacfwd` of the lens map.

    A bad value is a `ValueError` naming it, eagerly, and an `eqx.error_if` error under
    `jit`."""
    ray_map = _checked_map(ray_map)
    if jnp.shape(p)[-1:] != (2,):
        raise ValueError(f"p has shape {jnp.shape(p)}: its last axis must hold 2 coordinates")
    p = _checked_points(
        "p", p, "finite and not (0, 0) (radians)",
        lambda x, xp: xp.any(~xp.isfinite(x), axis=-1) | xp.all(x == 0, axis=-1),
    )  # fmt: skip
    return _magnification(p, ray_map)


def _magnification(p, ray_map: RayMap):
    """`magnification` of checked values."""
    p = jnp.asarray(p, ray_map.phi.dtype)
    batch = p.shape[:-1]
    flat = p.reshape(-1, 2)

    def one(pp):
        jac = jax.jacfwd(lens_map)(pp, ray_map)
        q = lens_map(pp, ray_map)
        alpha = jnp.sqrt(pp[0] ** 2 + pp[1] ** 2)
        theta = jnp.sqrt(q[0] ** 2 + q[1] ** 2)
        det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
        return (jnp.sin(alpha) / alpha) / (jnp.sin(theta) / theta) / det

    return jax.vmap(one)(flat).reshape(batch)


class LensedImages(eqx.Module):
    """Images of point sources, a leading axis of two: `[0]` on the source's side
    (target $\\Phi = (2m+1)\\pi - \\theta$), `[1]` on the other side ($+\\theta$).

    **Fields:** `alpha` (angle from the hole's direction, radians), `beta` (azimuth
    about it, camera frame, radians), `magnification` (signed solid-angle ratio),
    `source_theta` (source angle from $+z$, radians); each `(2, ...)`.
    """

    alpha: Float[Array, "2 ..."]
    beta: Float[Array, "2 ..."]
    magnification: Float[Array, "2 ..."]
    source_theta: Float[Array, "..."]

    def pixels(self, camera: Camera):
        """Pixel coordinates (column, row; fractional, pixel centres at $+0.5$) of the
        images in a centred static `camera` (yaw = pitch = roll = 0, at its origin)."""
        if not (camera.is_centred() and camera.at_origin()):
            raise ValueError("LensedImages.pixels needs a centred camera at the origin")
        r = camera.focal * jnp.tan(self.alpha)
        x, y = r * jnp.cos(self.beta), r * jnp.sin(self.beta)
        return x + 0.5 * camera.width, 0.5 * camera.height - y


def point_source_images(
    direction: Float[Array, "... 3"], ray_map: RayMap, *, order: int = 0
) -> LensedImages:
    """Images of sources at infinity in camera-frame `direction`s (3-vectors, $+z$
    behind the hole) for the static camera of `ray_map`
    (`RayMap.build(distance, accuracy=...)`, distance $1 < D \\le 10^{30}$ in units of
    R_S).

    **Arguments:** `direction (..., 3)` (finite, non-zero; any length); `ray_map`;
    `order` (static, a whole number $\\ge 0$): 0 for the primary and secondary images,
    $m \\ge 1$ for the relativistic pair near the shadow.

    **Returns:** `LensedImages`. Works under `jit`, `vmap`, `grad`. A bad value is a
    `ValueError` naming it, eagerly, and an `eqx.error_if` error under `jit`.
    """
    if isinstance(order, bool) or not isinstance(order, int | np.integer) or order < 0:
        raise ValueError(f"order={shown(order)} must be a whole number >= 0")
    ray_map = _checked_map(ray_map)
    if jnp.shape(direction)[-1:] != (3,):
        raise ValueError(
            f"direction has shape {jnp.shape(direction)}: its last axis must hold 3 components"
        )
    direction = _checked_points(
        "direction", direction, "a finite, non-zero 3-vector",
        lambda x, xp: xp.any(~xp.isfinite(x), axis=-1) | xp.all(x == 0, axis=-1),
    )  # fmt: skip
    return _point_source_images(direction, ray_map, order=int(order))


@eqx.filter_jit
def _point_source_images(direction, ray_map: RayMap, *, order: int) -> LensedImages:
    n = jnp.asarray(direction, jnp.result_type(float, direction))
    rho = jnp.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2)
    theta = jnp.arctan2(rho, n[..., 2])
    beta = jnp.arctan2(n[..., 1], n[..., 0])
    base = (2 * order + 1) * jnp.pi
    targets = jnp.stack([base - theta, base + theta])
    alpha = ray_map.solve(targets)
    betas = jnp.stack([beta, beta + jnp.pi])
    p = jnp.stack([alpha * jnp.cos(betas), alpha * jnp.sin(betas)], axis=-1)
    mu = _magnification(p, ray_map)
    return LensedImages(alpha, betas, mu, theta)
