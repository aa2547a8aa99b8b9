"""A geometrically thin, optically thick equatorial accretion disk (units of R_S = 1).

Geometry, in the static camera frame of `_camera` (camera at $-D\\hat z$, the hole at
the origin). The disk lies in the plane through the hole with unit normal
$\\hat n = R_z(\\mathrm{pa})\\,(0, \\sin i, -\\cos i)$: inclination $i = 0$ is face-on
(the normal toward the camera), $i = \\pi/2$ edge-on with the normal up ($+y$);
`position_angle` turns the disk about the line of sight.

A ray leaving the camera at local angle $\\alpha$ in the plane of $\\beta$ moves at
azimuth $\\phi$ (from the camera's position) to
$r(\\phi)\\,(\\cos\\phi\\,\\hat e_0 + \\sin\\phi\\,\\hat e_\\perp)$, $\\hat e_0 = -\\hat z$,
$\\hat e_\\perp = (\\cos\\beta, \\sin\\beta, 0)$. It crosses the disk plane where
$A\\cos\\phi + B\\sin\\phi = 0$ ($A = \\hat e_0\\cdot\\hat n$, $B = \\hat e_\\perp\\cdot\\hat n$):
at $\\phi_k = \\phi_0 + k\\pi$, $k = 0, 1, \\dots$ (the crossing number). $u = 1/r$ at
those azimuths comes from RK4 steps of $u'' = 1.5u^2 - u$ (`_integrators.rk4_step`) that
land exactly on each $\\phi_k$, all rays in lock-step (a `lax.scan`, vmapped by
construction, reverse-differentiable). The first crossing inside
$r_{in} \\le r \\le r_{out}$ before the ray escapes or falls in is the one seen:
$k = 0$ the direct image (near side below, far side lensed above the shadow at
high inclination), $k = 1$ the secondary image, and so on.

Emitters move on circular geodesics: $\\Omega = \\sqrt{1/(2r^3)}$,
$u^t = 1/\\sqrt{1 - 3/(2r)}$; a photon of angular momentum $L_z$ about $\\hat n$ per
unit energy reaches infinity with $g = \\nu_\\infty/\\nu_{em} = 1/(u^t(1 - \\Omega L_z))$.
A static camera at $D$ sees $g/\\sqrt{1 - 1/D}$; a moving camera times its Doppler
factor (`_effects`).

Temperature: $T(r) \\propto (r/r_{in})^{-3/4}(1 - \\sqrt{r_{in}/r})^{1/4}$ (the
zero-torque thin disk, Newtonian profile), scaled to a peak `temperature` at
$r = (49/36)\\,r_{in}$; each annulus radiates as a blackbody.
"""

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from . import _effects, _limits
from ._integrators import rk4_step
from ._limits import radians, real
from ._schema import Key, anything, greater, in_range, register
from ._units import angle, length

_PEAK_X = (7.0 / 6.0) ** 2  # r / r_in at the profile's maximum
_PEAK_F = _PEAK_X**-0.75 * (1.0 - 1.0 / math.sqrt(_PEAK_X)) ** 0.25


class Disk(eqx.Module):
    """A thin equatorial accretion disk between `r_in` and `r_out` (units of R_S).

    **Fields:**
    - `r_in`, `r_out`: inner and outer radius (units of R_S; $1.5 < r_{in} < r_{out}$,
      default the ISCO, 3). A dimensionless astropy Quantity is read as R_S; a length
      in metres, km, ... is refused (`jaxlens.schwarzschild_radii` converts it).
    - `inclination`: angle between the disk's normal and the line of sight (radians,
      or an astropy angle Quantity; finite; 0 face-on, $\\pi/2$ edge-on).
    - `position_angle`: turn of the disk about the line of sight (radians, or an
      astropy angle Quantity; finite).
    - `temperature`: peak temperature of the profile (K, finite and >= 1: the local
      temperature is held at 1 K or above, so a colder peak would brighten the disk's
      every annulus by the ratio of their luminances, beyond any float).
    - `brightness`: luminance of an emitter at the peak temperature, at rest (the
      sky's radiance units; in [0, 1e30]: a negative one would be negative radiance).
    - `crossings` (static): how many crossings of the disk plane are followed
      (1: direct image only, 2: with the secondary image, ...).
    - `steps` (static): RK4 steps per half turn of the orbit ($\\pi$ in azimuth).
    """

    r_in: Float[Array, ""]
    r_out: Float[Array, ""]
    inclination: Float[Array, ""]
    position_angle: Float[Array, ""]
    temperature: Float[Array, ""]
    brightness: Float[Array, ""]
    crossings: int = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    limits: ClassVar = {
        # r_in and r_out: 1.5 < r_in < r_out < inf, checked together (here and in
        # `_kernel._checks`).
        "inclination": _limits.finite("radians"),
        "position_angle": _limits.finite("radians"),
        "temperature": _limits.Limit("finite and >= 1", "K", low=1.0),
        "brightness": _limits.scale("linear radiance"),
    }

    def __init__(self, r_in: ArrayLike = 3.0, r_out: ArrayLike = 12.0,
                 inclination: ArrayLike = math.radians(80.0), *,
                 position_angle: ArrayLike = 0.0, temperature: ArrayLike = 8000.0,
                 brightness: ArrayLike = 1.0, crossings: int = 3, steps: int = 48):  # fmt: skip
        self.r_in = real("r_in", length(r_in, "r_in"))
        self.r_out = real("r_out", length(r_out, "r_out"))
        self.inclination = radians("inclination", inclination)
        self.position_angle = radians("position_angle", position_angle)
        self.temperature = real("temperature", temperature)
        self.brightness = real("brightness", brightness)
        self.crossings, self.steps = int(crossings), int(steps)

    def __check_init__(self):
        if self.crossings < 1 or self.steps < 2:
            raise ValueError(f"crossings={self.crossings} must be >= 1, steps={self.steps} >= 2")
        try:
            r_in, r_out = float(self.r_in), float(self.r_out)
        except (TypeError, jax.errors.ConcretizationTypeError):
            r_in = r_out = None
        if r_in is not None and not (1.5 < r_in < r_out and math.isfinite(r_out)):
            raise ValueError(
                f"r_in={r_in!r}, r_out={r_out!r}: need 1.5 < r_in < r_out < inf (units of R_S;"
                " circular orbits end at the photon sphere, 1.5)"
            )
        _limits.check_fields(self)

    def normal(self, dtype=None) -> Float[Array, "3"]:
        """Unit normal of the disk plane, camera frame (the disk turns counter-clockwise
        seen from its tip)."""
        i = self.inclination if dtype is None else self.inclination.astype(dtype)
        pa = self.position_angle.astype(i.dtype)
        ny, nz = jnp.sin(i), -jnp.cos(i)
        return jnp.stack([-jnp.sin(pa) * ny, jnp.cos(pa) * ny, nz])

    def temperature_at(self, r: ArrayLike) -> Float[Array, "..."]:
        """Local temperature (K) at radius `r` (units of R_S); 0 inside `r_in`."""
        r = jnp.asarray(r)
        x = jnp.maximum(r / self.r_in.astype(r.dtype), 1.0)
        f = x**-0.75 * jnp.maximum(1.0 - 1.0 / jnp.sqrt(x), 0.0) ** 0.25
        return self.temperature.astype(r.dtype) * f / _PEAK_F


_DEG = "a number in [0, 180] (degrees)"


@register("disk", "thin", {
    "r_in": Key("float", 3.0, greater(1.5), "a number > 1.5 (units of R_S)"),
    "r_out": Key("float", 12.0, greater(1.5), "a number > r_in (units of R_S)"),
    "inclination_deg": Key("float", 80.0, lambda v: 0.0 <= v <= 180.0, _DEG),
    "position_angle_deg": Key("float", 0.0, anything, "a finite number (degrees)"),
    "temperature": Key("float", 8000.0, lambda v: v >= 1.0, "a number >= 1 (K)"),
    "brightness": Key("float", 1.0, lambda v: v >= 0.0, "a number >= 0"),
    "crossings": Key("int", 3, in_range(0, 65), "a whole number from 1 to 64"),
    "steps": Key("int", 48, in_range(1, 100_001), "a whole number from 2 to 100000"),
}, check=lambda where, t: _check_radii(where, t))  # fmt: skip
def _disk_from_table(t, base) -> Disk:
    rad = math.radians
    return Disk(
        t["r_in"], t["r_out"], rad(t["inclination_deg"]),
        position_angle=rad(t["position_angle_deg"]), temperature=t["temperature"],
        brightness=t["brightness"], crossings=t["crossings"], steps=t["steps"],
    )  # fmt: skip


def _check_radii(where, t):
    if not t["r_in"] < t["r_out"]:
        raise ValueError(
            f"{where} r_out = {t['r_out']!r} is not valid: expected a number > r_in "
            f"= {t['r_in']!r} (units of R_S)"
        )


def disk_redshift(r: ArrayLike, lz: ArrayLike) -> Float[Array, "..."]:
    """$g = \\nu_\\infty/\\nu_{em} = \\sqrt{1 - 3/(2r)}/(1 - \\Omega L_z)$ of a photon of
    angular momentum `lz` (about the disk axis, per unit energy, units of R_S)
    leaving a Keplerian emitter at radius `r` > 1.5 (units of R_S),
    $\\Omega = \\sqrt{1/(2r^3)}$."""
    r = length(r, "r")
    lz = length(lz, "lz")
    r = jnp.asarray(r)
    omega = jnp.sqrt(0.5 / (r * r * r))
    return jnp.sqrt(1.0 - 1.5 / r) / (1.0 - omega * lz)


def reach_radius(r: ArrayLike) -> Float[Array, "..."]:
    """Impact parameter of the ray whose periapsis is `r` > 1.5: $b = r^{3/2}/\\sqrt{r-1}$
    (units of R_S). Inward rays of smaller $b$ come closer than `r`."""
    r = jnp.asarray(r)
    return r * jnp.sqrt(r / (r - 1.0))


def can_reach(alpha, distance, r_out):
    """True for the rays (local angle `alpha` from the hole, radians; camera at
    `distance`, units of R_S) that come within `r_out` of the hole: all of them when
    the camera is inside `r_out`, else the inward ones with $b$ < `reach_radius(r_out)`."""
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    r_out = length(r_out, "r_out")
    d = jnp.asarray(distance, jnp.asarray(alpha).dtype)
    b = d * jnp.abs(jnp.sin(alpha)) * jnp.sqrt(d / (d - 1.0))
    return (d <= r_out) | ((jnp.cos(alpha) > 0) & (b < reach_radius(r_out)))


class DiskHits(eqx.Module):
    """Where rays meet the disk.

    **Fields:** `hit` (bool), `radius` (units of R_S, of the crossing seen),
    `crossing` (its number $k$: 0 direct, 1 secondary, ...; $-1$ without a hit),
    `azimuth` (of that crossing in the ray's plane, from the camera's position,
    radians: above $\\pi/2$ it lies behind the hole), `g` ($\\nu_\\infty/\\nu_{em}$ of
    the light from there), `lz` (the photon's angular momentum about the disk axis per
    unit energy, units of R_S).
    """

    hit: Array
    radius: Float[Array, "..."]
    crossing: Int[Array, "..."]
    azimuth: Float[Array, "..."]
    g: Float[Array, "..."]
    lz: Float[Array, "..."]


def trace_disk(
    alpha: ArrayLike, cos_beta: ArrayLike, sin_beta: ArrayLike, distance: ArrayLike, disk: Disk
) -> DiskHits:
    """Follow rays from a static camera to their crossings of the disk plane.

    **Arguments:** `alpha` (local angle from the hole's direction, radians),
    `cos_beta`, `sin_beta` (the orbital plane, camera frame), of one shape;
    `distance` (camera radius, units of R_S); `disk`.

    **Returns:** `DiskHits` of the rays' shape. Pure array code: works under `jit`,
    `vmap` and `grad`; cost `disk.crossings * disk.steps` RK4 steps a ray.
    """
    alpha = angle(alpha, "alpha")
    distance = length(distance, "distance")
    alpha = jnp.asarray(alpha)
    dt = alpha.dtype
    cb, sb = jnp.asarray(cos_beta, dt), jnp.asarray(sin_beta, dt)
    d = jnp.asarray(distance, dt)
    n = disk.normal(dt)
    a = -n[2]  # e0 . n
    bb = cb * n[0] + sb * n[1]  # e_perp . n
    # A cos(phi) + B sin(phi) = 0  <=>  phi = atan2(B, A) + pi/2 (mod pi)
    phi0 = jnp.mod(jnp.arctan2(bb, jnp.broadcast_to(a, bb.shape)) + 0.5 * jnp.pi, jnp.pi)
    # A crossing at the camera itself (a camera in the disk plane) is not one.
    phi0 = jnp.where(phi0 < 1e-9, phi0 + jnp.pi, phi0)
    sa, ca = jnp.sin(alpha), jnp.cos(alpha)
    sa_ = jnp.maximum(sa, jnp.finfo(dt).tiny ** 0.25)
    u0 = 1.0 / d
    root = u0 * jnp.sqrt((d - 1.0) / d)
    u = jnp.broadcast_to(u0, alpha.shape)
    v = root * ca / sa_
    k_steps = disk.steps

    def segment(carry, h):
        u, v, alive = carry

        def step(c, _):
            u, v, alive = c
            u1, v1 = rk4_step(u, v, h)
            ok = alive & (u1 > 0.0) & (u1 < 1.0)
            return (jnp.where(ok, u1, u), jnp.where(ok, v1, v), ok), None

        (u, v, alive), _ = jax.lax.scan(step, (u, v, alive), None, length=k_steps)
        return (u, v, alive), (u, alive)

    hs = jnp.stack(
        [phi0 / k_steps] + [jnp.full_like(phi0, jnp.pi / k_steps)] * (disk.crossings - 1)
    )
    alive0 = jnp.ones(alpha.shape, bool)
    _, (uk, alivek) = jax.lax.scan(segment, (u, v, alive0), hs)
    r_in, r_out = disk.r_in.astype(dt), disk.r_out.astype(dt)
    rk = 1.0 / uk
    inside = alivek & (rk >= r_in) & (rk <= r_out)  # (K, ...)
    ks = jnp.arange(disk.crossings).reshape((-1,) + (1,) * alpha.ndim)
    first = jnp.min(jnp.where(inside, ks, disk.crossings), axis=0)
    hit = first < disk.crossings
    sel = jnp.minimum(first, disk.crossings - 1)
    radius = jnp.take_along_axis(rk, sel[None], axis=0)[0]
    radius = jnp.where(hit, radius, r_out)
    b = d * sa * jnp.sqrt(d / (d - 1.0))
    # photon angular momentum: minus that of the traced (backward) ray, b (e0 x e_perp)
    lz = -b * (sb * n[0] - cb * n[1])
    g = disk_redshift(radius, lz)
    azimuth = phi0 + jnp.pi * sel.astype(dt)
    crossing = jnp.where(hit, first, -1).astype(jnp.int32)
    return DiskHits(hit, radius, crossing, azimuth, g, lz)


def disk_radiance(
    disk: Disk, hits: DiskHits, g_camera: ArrayLike | None = None, mode: str | None = None
) -> Float[Array, "... 3"]:
    """Linear sRGB radiance of the disk where `hits.hit` (0 elsewhere).

    **Arguments:** `disk`, `hits` (`trace_disk`); `g_camera`: the camera's frequency
    ratio for light from infinity along each ray (`_effects.frequency_ratio`);
    `mode`: `None` (rest-frame colours: no redshift, no beaming), `"bolometric"`
    (colour of $T$, intensity $\\times g^4$) or `"spectral"` (a blackbody of $gT$),
    with $g$ = `hits.g` $\\times$ `g_camera`.

    **Returns:** `(..., 3)`; an emitter at the peak temperature at rest has luminance
    `disk.brightness`.
    """
    dt = hits.radius.dtype
    t = jnp.maximum(disk.temperature_at(hits.radius), 1.0)
    log_t = jnp.log(t)
    log_peak = jnp.log(disk.temperature.astype(dt))
    log_y_peak, _ = _effects._lookup(log_peak)
    if mode is None:
        log_y, rgb = _effects._lookup(log_t)
    else:
        g = hits.g if g_camera is None else hits.g * jnp.asarray(g_camera, dt)
        if mode == "spectral":
            log_y, rgb = _effects._lookup(log_t + jnp.log(g))
        elif mode == "bolometric":
            log_y, rgb = _effects._lookup(log_t)
            log_y = log_y + 4.0 * jnp.log(g)
        else:
            raise ValueError(f"mode={mode!r} must be None, 'bolometric' or 'spectral'")
    scale = disk.brightness.astype(dt) * jnp.exp(log_y - log_y_peak)
    return jnp.where(hits.hit[..., None], scale[..., None] * rgb, 0.0)


def disk_angle_bound(distance, r_out) -> float:
    """Host-side: the largest local angle (radians) of a ray from a static camera at
    `distance` (units of R_S, concrete) that can come within `r_out`; $\\pi$ when the
    camera is inside `r_out`."""
    distance = length(distance, "distance")
    r_out = length(r_out, "r_out")
    d, r = float(distance), float(r_out)
    if d <= r:
        return math.pi
    s = float(reach_radius(np.float64(r))) * math.sqrt(1.0 - 1.0 / d) / d
    return math.asin(min(s, 1.0))
