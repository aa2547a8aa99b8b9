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

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _exact
from ._camera import Camera, sky_direction
from ._constants import C_LIGHT, RS_SUN_M
from ._messages import shown
from ._ray_inputs import (
    DISTANCE_MESSAGE,
    MAX_DISTANCE,
    check_distance,
    check_real,
    distance_bad,
)
from ._raymap import RayMap
from ._units import length, solar_masses
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
    `source_theta` (source angle from $+z$, radians); each `(2, ...)`; `time`
    (`point_source_images_at` only, else `None`): the coordinate time light takes from
    the source to the camera along each image's ray, less a part all images of one
    source share (units of R_S/c; see `point_source_images_at`): differences between
    images, of any order, are their time delays.
    """

    alpha: Float[Array, "2 ..."]
    beta: Float[Array, "2 ..."]
    magnification: Float[Array, "2 ..."]
    source_theta: Float[Array, "..."]
    time: Float[Array, "2 ..."] | None = None

    def delay_seconds(self, mass_msun) -> Float[Array, "2 ..."]:
        """`time` in seconds for a hole of `mass_msun` solar masses (or an astropy mass
        Quantity; one R_S/c is
        $2GM/c^3$ = 9.85 microseconds per solar mass); differences between images are
        their delays in seconds."""
        if self.time is None:
            raise ValueError("these images carry no times: point_source_images_at computes them")
        mass_msun = solar_masses(mass_msun, "mass_msun")
        return self.time * (RS_SUN_M / C_LIGHT) * jnp.asarray(mass_msun)

    def pixels(self, camera: Camera):
        """Pixel coordinates (column, row; fractional, pixel centres at $+0.5$) of the
        images in a centred static `camera` (yaw = pitch = roll = 0, at its origin)."""
        if not (camera.is_centred() and camera.at_origin()):
            raise ValueError("LensedImages.pixels needs a centred camera at the origin")
        r = camera.focal * jnp.tan(self.alpha)
        x, y = r * jnp.cos(self.beta), r * jnp.sin(self.beta)
        return x + 0.5 * camera.width, 0.5 * camera.height - y


def _checked_source(order, direction):
    """`(order, direction)` checked: a whole `order` >= 0 (a `ValueError` else), and
    `direction (..., 3)` finite and non-zero (`_checked_points`)."""
    if isinstance(order, bool) or not isinstance(order, int | np.integer) or order < 0:
        raise ValueError(f"order={shown(order)} must be a whole number >= 0")
    if jnp.shape(direction)[-1:] != (3,):
        raise ValueError(
            f"direction has shape {jnp.shape(direction)}: its last axis must hold 3 components"
        )
    direction = _checked_points(
        "direction", direction, "a finite, non-zero 3-vector",
        lambda x, xp: xp.any(~xp.isfinite(x), axis=-1) | xp.all(x == 0, axis=-1),
    )  # fmt: skip
    return int(order), direction


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
    order, direction = _checked_source(order, direction)
    return _point_source_images(direction, _checked_map(ray_map), order=order)


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


# Bisection steps of the exact image solve, in the log of the offset from the end of a
# branch (a span of 70 in the log: offsets down to 1e-30 of the branch's width, which
# the tenth relativistic image is above): 80 halve it to 6e-23, below float64's
# resolution of the log.
_BISECT = 80
_LOG_SPAN = 70.0


def _source_angle(phi, d, r):
    """The source's signed angle from the hole's direction as the camera would see it in
    flat space (radians): the point at azimuth `phi` (from the hole's camera side, in the
    image's orbital plane) on the sphere r = `r` about a hole `d` away; `r = inf`: the
    direction at azimuth `phi`."""
    far = jnp.isinf(r)
    rr = jnp.where(far, 1.0, r)
    flat = jnp.arctan2(rr * jnp.sin(phi), d - rr * jnp.cos(phi))
    return jnp.where(far, jnp.arctan2(jnp.sin(phi), -jnp.cos(phi)), flat)


def _branch_phi(g, end, sign, d, r, alpha_sh, far: bool):
    """The crossing azimuth (radians) on a branch at the log-offset `g`: the local angle
    is `end + sign * exp(g)`, `end` the branch's end (the shadow's edge for the branch
    after the turning point, `sign` +1; the angle whose periapsis is `r`, or the edge,
    for the first crossing, `sign` -1), its offset from the edge `end - alpha_sh`
    exactly where `end` is the edge; `far`: every source at infinity (`r` not read),
    False: none, None: not known (each as it is)."""
    gap = jnp.exp(g)
    offset = (end - alpha_sh) + sign * gap
    alpha = alpha_sh + offset
    kappa = _exact.kappa_from_offset(offset, alpha_sh)
    if far:
        return _exact.escape_angle(alpha, d, max_windings=1e6, _kappa=kappa)[0]
    crossings = _exact.radius_crossings if far is None else _exact.finite_crossings
    c = crossings(alpha, d, r, max_windings=1e6, _kappa=kappa)
    after = jnp.where(r < d, c.second, c.first)
    return jnp.where(sign > 0, after, c.first)


def _solve_branch(target, end, sign, g_lo, g_hi, d, r, alpha_sh, far):
    """The log-offset `g` on a branch where the azimuth equals `target` (`_root`), and
    the azimuth's slope `dphi/dg` there: `(g, slope)`, both differentiable in the
    arguments."""
    g = _root(far, (target, end, d, r, alpha_sh), sign, g_lo, g_hi)
    slope = jax.jvp(lambda gg: _branch_phi(gg, end, sign, d, r, alpha_sh, far), (g,),
                    (jnp.ones_like(g),))[1]  # fmt: skip
    return g, slope


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _root(far, args, sign, g_lo, g_hi):
    """The log-offset in [`g_lo`, `g_hi`] where the branch's azimuth (`_branch_phi` of
    `args` = (target, end, d, r, alpha_sh)) equals the target, by bisection to float
    resolution (the azimuth falls as the offset grows on both branches). Its derivative
    is the implicit function's (`_root_jvp`)."""
    target, end, d, r, alpha_sh = args

    def bisect(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        above = _branch_phi(mid, end, sign, d, r, alpha_sh, far) > target
        return jnp.where(above, mid, lo), jnp.where(above, hi, mid)

    lo, hi = jax.lax.fori_loop(0, _BISECT, bisect, (g_lo, g_hi))
    return 0.5 * (lo + hi)


@_root.defjvp
def _root_jvp(far, primals, tangents):
    args, sign, g_lo, g_hi = primals
    g = _root(far, args, sign, g_lo, g_hi)

    def residual(gg, a):
        target, end, d, r, alpha_sh = a
        return _branch_phi(gg, end, sign, d, r, alpha_sh, far) - target

    moved = jax.jvp(lambda a: residual(g, a), (args,), (tangents[0],))[1]
    slope = jax.jvp(lambda gg: residual(gg, args), (g,), (jnp.ones_like(g),))[1]
    return g, -moved / slope


def _images_at(theta, d, r, order, far):
    """The images' local angles (radians), signed magnifications and reduced light
    travel times (`_exact.crossing_times`, units of R_S/c) for sources at angle `theta`
    from +z on the sphere r = `r` (inf: at infinity; `far`: whether every one is, None
    where not known), the two sides stacked first: `(alpha, mu, time)`, each
    `(2, ...)`."""
    base = (2 * order + 1) * jnp.pi
    target = jnp.stack([base - theta, base + theta])
    d, r = (jnp.broadcast_to(v, target.shape) for v in (d, r))
    alpha_sh = _exact.shadow_angle(d)
    # Where the ray's periapsis is r (a sphere inside the camera's radius and outside
    # the photon sphere): the two branches meet there.
    meet = jnp.isfinite(r) & (r < d) & (r > 1.5)
    alpha_r = jnp.where(meet, _exact.grazing_angle(d, jnp.where(meet, r, 2.0)), alpha_sh)
    # After the turning point (or the only crossing, r >= d): from the edge up to the
    # meeting angle (r < d) or straight away (pi); the first crossing (r < d): down
    # from the meeting angle (or the edge, r <= 1.5) to the hole's own direction. Both
    # solved in one program, the branch a leading axis of data.
    after_hi = jnp.where(r >= d, jnp.pi, alpha_r)
    ends, signs = [alpha_sh], [1.0]
    tops = [jnp.log(jnp.maximum(after_hi - alpha_sh, 1e-300)) - 1e-12]
    if not far:
        ends.append(alpha_r)
        signs.append(-1.0)
        tops.append(jnp.log(jnp.maximum(alpha_r, 1e-300)) - 1e-12)
    n = len(ends)
    top = jnp.stack(tops)
    sign = jnp.broadcast_to(jnp.asarray(signs).reshape((n,) + (1,) * target.ndim), top.shape)
    stack = lambda v: jnp.broadcast_to(v, top.shape)  # noqa: E731
    g, slope = _solve_branch(stack(target), jnp.stack(ends), sign, top - _LOG_SPAN, top,
                             stack(d), stack(r), stack(alpha_sh), far)  # fmt: skip
    # A root at a branch's end is no root: the target lies beyond the branch's range.
    # Sources on the far side of a sphere inside the camera's radius are seen after the
    # turning point, those on the near side on the first crossing.
    on_after = r >= d
    if not far:
        on_after = on_after | (meet & (g[0] < top[0] - 1e-9))
    pick = jnp.where(on_after, 0, n - 1)
    gap = jnp.exp(jnp.take_along_axis(g, pick[None], 0)[0])
    alpha = jnp.where(on_after, alpha_sh + gap, alpha_r - gap)
    # dPhi/dalpha: the offset grows with alpha after the turning point, falls with it
    # on the first crossing.
    dphi = jnp.where(on_after, 1.0, -1.0) * jnp.take_along_axis(slope, pick[None], 0)[0] / gap
    phi = target
    vt, dvt = jax.jvp(lambda p: _source_angle(p, d, r), (phi,), (jnp.ones_like(phi),))
    mu = jnp.sin(alpha) / (jnp.sin(vt) * dvt * dphi)
    # The light travel time along the image's ray, its kappa from the offset as solved.
    offset = jnp.where(on_after, gap, (alpha_r - alpha_sh) - gap)
    kappa = _exact.kappa_from_offset(offset, alpha_sh)
    t_first, t_second = _exact.crossing_times(alpha, d, r, _kappa=kappa)
    time = jnp.where(on_after & (r < d), t_second, t_first)
    return alpha, mu, time


def point_source_images_at(
    direction: Float[Array, "... 3"], distance, source_distance=np.inf, *, order: int = 0
) -> LensedImages:
    """Images of point sources at a finite distance from the hole (or at infinity),
    solved on the exact closed form: every order at the closed form's own accuracy.

    The source lies `source_distance` from the hole in the camera-frame `direction`
    (from the hole; $+z$ is behind it, seen from the camera). The images of order $m$
    lie where a ray's crossing of the sphere $r$ = `source_distance` (`radius_crossings`)
    sweeps $(2m+1)\\pi - \\theta$ on the source's side and $(2m+1)\\pi + \\theta$ on the
    other, $\\theta$ the source's angle from $+z$. Each is solved in the log of the
    local angle's offset from the shadow's edge (or from the ray that grazes the
    source's sphere), where the azimuth is smooth, so that a relativistic image's
    offset keeps full relative accuracy.

    The magnification is the ratio of the image's solid angle to the source's as the
    camera would see it without the hole (flat space, the source `source_distance`
    from a point `distance` away): $\\mu = \\sin\\alpha / (\\sin\\vartheta\\,
    d\\vartheta/d\\alpha)$, $\\vartheta$ the source's flat-space angle from the hole's
    direction, signed by the image's parity. At infinity it is `point_source_images`'.

    **Arguments:**
    - `direction (..., 3)`: finite, non-zero (any length).
    - `distance`: the camera's radius $D > 1.5$ (units of R_S, or a dimensionless
      astropy Quantity, as `source_distance`; a camera inside the
      photon sphere sees sources at a finite distance along more branches than these).
    - `source_distance`: the source's radius $R > 1$ (units of R_S; `inf`: at
      infinity). Broadcast to the directions' batch shape.
    - `order` (static, whole, $\\ge 0$): 0 for the primary and secondary images, $m$
      for the relativistic pair that winds $m$ more times.

    The time delays: `time` is the coordinate time light takes from the source to the
    camera along each image's ray (`crossing_times`: $b\\,\\Phi$ plus the radial action,
    exact to float64's eps times the impact parameter), less $D + \\ln(D-1) +
    R + \\ln(R-1)$, which all images of one source share (at infinity less $D +
    \\ln(D-1)$ and the diverging rest: a plane wave's delays). The delay between any two
    images of the source, of any orders, is the difference of their `time`s (units of
    R_S/c; `LensedImages.delay_seconds(mass)` in seconds). It is coordinate time: a
    static camera's own clock runs $\\sqrt{1 - 1/D}$ as fast.

    **Returns:** `LensedImages` (`source_theta`: the angle from $+z$ of the source's
    direction from the hole; `time` as above). Works under `jit`, `vmap`, `grad`. A bad value is a
    `ValueError` naming it, eagerly, and an `eqx.error_if` error under `jit`.
    """
    order, direction = _checked_source(order, direction)
    distance = length(distance, "distance")
    source_distance = length(source_distance, "source_distance")
    distance = _checked_points(
        "distance", distance, "finite and > 1.5 (units of R_S: a camera outside the photon "
        "sphere)", lambda x, xp: ~xp.isfinite(x) | ~(x > 1.5) | (x > MAX_DISTANCE),
    )  # fmt: skip
    source_distance = _checked_points(
        "source_distance", source_distance, "> 1 (units of R_S: outside the horizon; inf: "
        "at infinity)", lambda x, xp: xp.isnan(x) | ~(x > 1.0),
    )  # fmt: skip
    # Whether every source is at infinity (escape_angle's program only), none is (the
    # finite crossings' only), or that is not known here (both, each where it applies).
    c = concrete(source_distance)
    inf = None if c is None else np.isinf(np.asarray(c, float))
    far = None if inf is None or (inf.any() and not inf.all()) else bool(inf.all())
    return _point_source_images_at(direction, distance, source_distance, order=order, far=far)


@eqx.filter_jit
def _point_source_images_at(direction, distance, source_distance, *, order: int, far):
    n = jnp.asarray(direction, jnp.result_type(float, direction))
    dtype = n.dtype
    rho = jnp.sqrt(n[..., 0] ** 2 + n[..., 1] ** 2)
    theta = jnp.arctan2(rho, n[..., 2])
    beta = jnp.arctan2(n[..., 1], n[..., 0])
    d = jnp.broadcast_to(jnp.asarray(distance, dtype), theta.shape)
    r = jnp.broadcast_to(jnp.asarray(source_distance, dtype), theta.shape)
    alpha, mu, time = _images_at(theta, d, r, order, far)
    return LensedImages(alpha, jnp.stack([beta, beta + jnp.pi]), mu, theta, time)
