"""Scenes with effects: compile only the stages a scene names, on the cheapest path.

A scene is a camera, a sky and optional effects: the camera's motion
(`CircularOrbit`, `RadialInfall`), a frequency shift of all light (`Redshift`), an
accretion disk (`Disk`). `plan(scene)` decides, in Python from the scene's structure
and (where they are concrete) its values, which stages run and how, and says why:

- **geometry of sky rays**: the static-frame ray map is always one-dimensional, so
  a moving camera's pixels are boosted to the static frame (`aberrate`; a radial
  motion only rescales $\\alpha$, a tangential one needs 3-vectors) and go through
  the same alpha table (`RayMap`). When every ray in view has its periapsis far out
  (impact parameter $b \\gg b_c$) and the truncation bound of the weak-field series
  (`weak_field_escape_angle`) is below the requested accuracy, the series replaces
  the table, with no table to build. `method="trace"` forces the exact per-ray
  closed form (`trace`), for comparison.
- **disk**: only the rays that can come within `r_out` are followed through the
  disk plane (`trace_disk`); with concrete camera values they are gathered into a
  compact batch first, so the per-ray cost is paid for those rays alone.
- A scene with no effects on the table path is rendered by `render_array` itself:
  the identical program.

Stages are chosen by Python `if`s on the plan (never on traced values), so a stage
the scene does not name is not in the compiled program; each stage runs inside a
`jax.named_scope("jaxlens.<stage>")`, visible in the lowered program's locations.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _disk, _effects
from ._camera import Camera, sky_direction
from ._effects import AbstractMotion, CircularOrbit, RadialInfall, Redshift
from ._exact import B_CRIT
from ._raymap import RayMap
from ._render import render, render_array
from ._sky import AbstractSky
from ._trace import trace
from ._util import concrete as _concrete
from ._util import is_concrete as _is_concrete

# ------------------------------------------------------------------ weak field

# Coefficients c_n of (1 - x)^(-1/2) = sum c_n x^n.
_C = (1.0, 0.5, 0.375, 0.3125, 0.2734375)
# I_n(pi/2) = int_0^{pi/2} h(sin t)^n dt, h(s) = s + 1/(1 + s).
_I_HALF = (0.5 * math.pi, 2.0, 1.25 * math.pi - 4.0 / 3.0, 122.0 / 15.0 - 1.5 * math.pi)
WEAK_ORDER = 3
# The series costs ~50 ns (CPU) a ray more than a table look-up (three transcendentals
# against one log) but needs no table (~8 ms CPU to build on the 2-core benchmark
# machine): it is the cheaper path up to ~1.3e5 rays a view there
# (benchmarks/results/effects.md). Larger views of a far field take the table, whose
# build is then amortised.
WEAK_MAX_SAMPLES = 1 << 17


def _periapsis_u(b):
    """$u_2 = 1/r_0$: the smallest positive root of $u^2 - u^3 = 1/b^2$, by Newton from
    $1/b$ (four steps reach round-off for $u_2 < 0.1$, where the series is used)."""
    c = 1.0 / (b * b)
    u = 1.0 / b
    for _ in range(4):
        u = u - (u * u * (1.0 - u) - c) / (u * (2.0 - 3.0 * u))
    return u


def weak_field_terms(y0, c0=None):
    """$I_n(t_0) = \\int_0^{t_0} h(\\sin t)^n dt$, $n = 0..3$, $h(s) = s + 1/(1+s)$, at
    $\\sin t_0 = y_0 \\in [0, 1]$ (and $\\cos t_0$ = `c0`, if known more accurately than
    from $y_0$), in closed form (through $w = \\tan(t_0/2)$)."""
    if c0 is None:
        c0 = jnp.sqrt((1.0 - y0) * (1.0 + y0))
    t0 = jnp.arctan2(y0, c0)
    w = y0 / (1.0 + c0)
    v = 1.0 + w
    iv = 1.0 / v
    j1 = 2.0 * w * iv
    j2 = 2.0 * (((-2.0 / 3.0 * iv + 1.0) * iv - 1.0) * iv + 2.0 / 3.0)
    j3 = 2.0 * (((((-0.8 * iv + 2.0) * iv - 8.0 / 3.0) * iv + 2.0) * iv - 1.0) * iv + 7.0 / 15.0)
    s1 = y0 * y0 / (1.0 + c0)  # 1 - cos t0
    s2 = 0.5 * (t0 - y0 * c0)
    s3 = s1 - (1.0 - c0**3) / 3.0  # 2/3 - cos t0 + cos^3 t0 / 3
    i1 = s1 + j1
    i2 = s2 + 2.0 * t0 - 2.0 * j1 + j2
    i3 = s3 + 3.0 * s1 - 3.0 * t0 + 6.0 * j1 - 3.0 * j2 + j3
    return t0, (t0, i1, i2, i3)


def weak_field_escape_angle(alpha: ArrayLike, distance: ArrayLike, *, order: int = WEAK_ORDER):
    """Escape angle of rays with a far periapsis, as a series in $u_2 = 1/r_0$, with a
    rigorous bound on the truncation error.

    With $u = u_2\\sin t$ the azimuth from the asymptote to $u$ is exactly
    $\\int_0^{t}[1 - u_2 h(\\sin t')]^{-1/2} dt'$, $h(s) = s + 1/(1+s) \\in [1, 3/2]$;
    expanding the root gives $\\sum_n c_n u_2^n I_n(t)$ with $c_n = \\binom{2n}{n}4^{-n}$
    and closed-form $I_n$ (`weak_field_terms`). $\\Phi = \\phi(t_0)$ for outward rays,
    $2\\phi(\\pi/2) - \\phi(t_0)$ for inward ones ($\\sin t_0 = u_0/u_2$). For a camera at
    infinity this is the deflection $2/b + (15\\pi/16)/b^2 + \\dots$ (PHYSICS.md). The
    remainder after order $N$ is at most $L\\,c_{N+1}(1.5u_2)^{N+1}/(1 - 1.5u_2)$,
    $L = \\pi - t_0$ (inward) or $t_0$ (outward).

    **Arguments:** `alpha` (local angle from the hole, radians), `distance` (camera
    radius, units of R_S; $D > 1.5$); `order` $N \\in \\{1, 2, 3\\}$ (static).

    **Returns:** `(phi, bound)`, radians; `bound` is `inf` where $1.5u_2 \\ge 1/2$
    (the series is not used there).
    """
    if order not in (1, 2, 3):
        raise ValueError(f"order={order!r} must be 1, 2 or 3")
    alpha = jnp.asarray(alpha, jnp.result_type(float, alpha))
    d = jnp.asarray(distance, alpha.dtype)
    sa = jnp.abs(jnp.sin(alpha))
    ca = jnp.cos(alpha)
    inward = ca > 0
    b = d * sa * jnp.sqrt(d / (d - 1.0))
    ok = b > 2.0 * B_CRIT
    b_ = jnp.where(ok, b, 10.0 * B_CRIT)
    u2 = _periapsis_u(b_)
    u0 = 1.0 / d
    y0 = jnp.clip(u0 / u2, 0.0, 1.0)
    # cos t0 from u2 - u0 = G(u0) / [(u2 + u0) - (u2^2 + u2 u0 + u0^2)], G(u0) =
    # u0^2 (1 - u0) cot^2(alpha): no cancellation for a camera near the periapsis.
    cot = ca / jnp.where(ok, sa, 1.0)
    g0 = u0 * u0 * ((d - 1.0) / d) * cot * cot
    du = g0 / ((u2 + u0) - (u2 * u2 + u2 * u0 + u0 * u0))
    c0 = jnp.sqrt(jnp.clip(du * (u2 + u0), 0.0, None)) / u2
    t0, terms = weak_field_terms(y0, jnp.minimum(c0, 1.0))
    phi_t = sum(_C[n] * u2**n * terms[n] for n in range(order + 1))
    phi_h = sum(_C[n] * u2**n * _I_HALF[n] for n in range(order + 1))
    phi = jnp.where(inward, 2.0 * phi_h - phi_t, phi_t)
    x = 1.5 * u2
    length = jnp.where(inward, jnp.pi - t0, t0)
    # truncation, plus the round-off of the sums (measured: < 20 eps over random rays)
    eps = jnp.finfo(alpha.dtype).eps
    bound = length * _C[order + 1] * x ** (order + 1) / (1.0 - x) + 64.0 * eps
    ok = ok & (x < 0.5)
    return jnp.where(ok, phi, jnp.pi - alpha), jnp.where(ok, bound, jnp.inf)


# ------------------------------------------------------------------ scenes


class EffectScene(eqx.Module):
    """A camera, a sky and the effects a scene calls for.

    **Fields:**
    - `camera`: a `Camera` (one camera; its pixels are in the moving frame when
      `motion` is set).
    - `sky`: an `AbstractSky` (sums with `+`; `BlackbodyStars` carry temperatures).
    - `motion`: `None` (static camera), `CircularOrbit` or `RadialInfall`.
    - `redshift`: `None` (no frequency shift) or `Redshift(mode)`.
    - `disk`: `None` or a `Disk`.
    - `accuracy` (static): the error allowed in the escape angle (radians).
    - `method` (static): `"auto"` (the plan chooses), or force `"table"`,
      `"weak_field"` or `"trace"` for the sky rays.
    """

    camera: Camera
    sky: AbstractSky
    motion: AbstractMotion | None = None
    redshift: Redshift | None = None
    disk: _disk.Disk | None = None
    accuracy: float = eqx.field(static=True, default=1e-8)
    method: str = eqx.field(static=True, default="auto")

    def __check_init__(self):
        if not (0.0 < self.accuracy < 0.1):
            raise ValueError(f"accuracy={self.accuracy!r} must be in (0, 0.1) radians")
        if self.method not in ("auto", "table", "weak_field", "trace"):
            raise ValueError(
                f"method={self.method!r} must be 'auto', 'table', 'weak_field' or 'trace'"
            )
        if self.camera.batch_shape != ():
            raise ValueError(f"EffectScene takes one camera, got batch {self.camera.batch_shape}")
        if self.motion is not None and not isinstance(self.motion, AbstractMotion):
            raise ValueError(f"motion={self.motion!r} must be CircularOrbit, RadialInfall or None")
        if self.motion is not None:
            d = _concrete(self.camera.distance)
            if d is not None:
                self.motion.check_distance(d)

    def plan(self) -> "Plan":
        """The stages and paths `render_scene` takes for this scene, and why."""
        return plan(self)


def as_scene(scene_like, **effects) -> EffectScene:
    """An `EffectScene` from an `EffectScene` (effects given here replace its own), or
    from anything with `camera` and `sky` (and optionally `accuracy`) attributes,
    such as a `Scene` read from a TOML file."""
    if isinstance(scene_like, EffectScene):
        return dataclasses.replace(scene_like, **effects) if effects else scene_like
    if not (hasattr(scene_like, "camera") and hasattr(scene_like, "sky")):
        raise ValueError(f"{type(scene_like).__name__} has no camera and sky; not a scene")
    kw = {"accuracy": getattr(scene_like, "accuracy", 1e-8)}
    kw.update(effects)
    return EffectScene(scene_like.camera, scene_like.sky, **kw)


# ------------------------------------------------------------------ the plan


@dataclasses.dataclass(frozen=True)
class Plan:
    """What `render_scene` does for a scene (hashable: it keys the compiled program).

    **Fields:** `geometry` (`"table"`, `"weak_field"` or `"trace"`: how sky rays get
    their escape angle), `aberration` (`None`, `"radial"` or `"boost"`), `redshift`
    (`None`, `"bolometric"`, `"spectral"`), `disk` (whether disk rays are traced),
    `disk_rays` (rays followed through the disk plane; `None`: all, by mask),
    `samples` (area samples in the image), `weak_bound` (largest truncation bound of
    the weak-field series over the view, radians, where computed), `bare` (no
    effect: `render_array` itself), `reasons` (one line per decision).
    """

    geometry: str
    aberration: str | None
    redshift: str | None
    disk: bool
    disk_rays: int | None
    samples: int
    weak_bound: float | None
    bare: bool
    reasons: tuple[str, ...]

    def structure(self) -> "Plan":
        """The plan with its value-dependent fields blanked: what fixes the program."""
        return dataclasses.replace(
            self, disk_rays=None if self.disk_rays is None else 0, samples=0, weak_bound=None,
            reasons=(),
        )  # fmt: skip

    def __str__(self):
        head = (
            f"geometry={self.geometry}, aberration={self.aberration}, redshift="
            f"{self.redshift}, disk={'traced' if self.disk else 'none'}"
        )
        return "\n".join([head] + [f"  - {r}" for r in self.reasons])


@eqx.filter_jit
def _static_rays(camera: Camera, motion):
    alpha, cb, sb = camera.rays()
    return _to_static(camera, motion, alpha, cb, sb)[:3]


def _to_static(camera, motion, alpha, cb, sb):
    """Moving-frame pixel angles -> static-frame angles, and $\\cos a'$ (the angle
    from the velocity, moving frame) and the speed, for the Doppler factor."""
    if motion is None:
        return alpha, cb, sb, None, None
    dt = alpha.dtype
    v = motion.speed(camera.distance).astype(dt)
    if motion.radial:
        ca, sa = jnp.cos(alpha), jnp.sin(alpha)
        inv = 1.0 / (1.0 - v * ca)
        cs = (ca - v) * inv
        ss = sa * jnp.sqrt((1.0 - v) * (1.0 + v)) * inv
        return jnp.arctan2(ss, cs), cb, sb, ca, v
    e = motion.direction(dt)
    sa = jnp.sin(alpha)
    n = jnp.stack([sa * cb, sa * sb, jnp.cos(alpha)], axis=-1)
    cos_a = n[..., 0] * e[0] + n[..., 1] * e[1] + n[..., 2] * e[2]
    ns = _effects.aberrate(n, v, e)
    rho = jnp.sqrt(ns[..., 0] ** 2 + ns[..., 1] ** 2)
    safe = rho > 0
    rho_ = jnp.where(safe, rho, 1.0)
    cb_s = jnp.where(safe, ns[..., 0] / rho_, 1.0)
    sb_s = jnp.where(safe, ns[..., 1] / rho_, 0.0)
    return jnp.arctan2(rho, ns[..., 2]), cb_s, sb_s, cos_a, v


_BUCKETS = 16


def _bucket(count: int, total: int) -> int:
    """Padded size of a gathered batch: the next of 16 steps of `total` (so a moving
    scene recompiles at most 16 times)."""
    step = max(1, -(-total // _BUCKETS))
    return min(total, max(step, -(-count // step) * step))


def _disk_indices(scene: EffectScene, alpha_s):
    mask = _disk.can_reach(alpha_s, scene.camera.distance, scene.disk.r_out)
    idx = np.flatnonzero(np.asarray(mask).reshape(-1)).astype(np.int32)
    return idx


def plan(scene_like, **effects) -> Plan:
    """Decide how `render_scene` renders a scene (see the module docstring).

    Python-level decisions on the scene's structure; where the camera's values are
    concrete, also on them (the view's smallest impact parameter for the weak-field
    bound, the rays that can reach the disk). Under `jit`/`grad` of the scene the
    plan stays on the safe side: the table, and all rays masked for the disk.

    **Returns:** a `Plan`; `str(plan)` lists each decision and its reason.
    """
    scene = as_scene(scene_like, **effects)
    return _plan(scene)[0]


def _plan(scene: EffectScene):
    # Host-side decisions on concrete values: evaluate them now even inside a trace.
    with jax.ensure_compile_time_eval():
        return _plan_now(scene)


def _plan_now(scene: EffectScene):
    cam = scene.camera
    reasons = []
    concrete = _is_concrete((cam, scene.motion)) and (
        scene.disk is None or _concrete(scene.disk.r_out) is not None
    )
    samples = cam.width * cam.height * cam.supersample**2
    if scene.motion is None:
        aberration = None
        reasons.append("static camera: no aberration, the pixel angles are the static ones")
    elif scene.motion.radial:
        aberration = "radial"
        reasons.append(
            f"{type(scene.motion).__name__}: motion along the line to the hole, so the "
            "aberration only rescales alpha (the map stays 1-D)"
        )
    else:
        aberration = "boost"
        reasons.append(
            f"{type(scene.motion).__name__}: tangential motion, pixel directions are "
            "boosted to the static frame as 3-vectors; the static map stays 1-D"
        )
    redshift = None if scene.redshift is None else scene.redshift.mode
    if redshift is None:
        reasons.append("no Redshift: colours as emitted, no frequency shift computed")
    else:
        reasons.append(
            f"Redshift({redshift!r}): g = 1/sqrt(1 - 1/D)"
            + (" x Doppler factor" if scene.motion is not None else "")
        )
    alpha_s = _static_rays(cam, scene.motion)[0] if concrete else None

    weak_bound = None
    if scene.method != "auto":
        geometry = scene.method
        reasons.append(f"method={scene.method!r} forced by the scene")
    elif not concrete:
        geometry = "table"
        reasons.append("camera values are traced: the view cannot be bounded, use the table")
    else:
        _, bound = jax.jit(weak_field_escape_angle)(alpha_s, cam.distance)
        weak_bound = float(jnp.max(bound))
        if weak_bound < scene.accuracy and samples > WEAK_MAX_SAMPLES:
            geometry = "table"
            reasons.append(
                f"weak-field bound {weak_bound:.2e} rad < accuracy, but {samples} rays > "
                f"{WEAK_MAX_SAMPLES}: the table's build is amortised, its look-up is cheaper"
            )
        elif weak_bound < scene.accuracy:
            geometry = "weak_field"
            reasons.append(
                f"every ray in view has a far periapsis: weak-field series bound "
                f"{weak_bound:.2e} rad < accuracy {scene.accuracy:.1e}, no table needed"
            )
        else:
            geometry = "table"
            what = "inf (rays near the hole)" if not math.isfinite(weak_bound) else (
                f"{weak_bound:.2e} rad")  # fmt: skip
            reasons.append(
                f"weak-field bound {what} >= accuracy {scene.accuracy:.1e}: alpha table "
                "(RayMap) built once, interpolated per ray"
            )
    disk_rays = None
    idx = None
    if scene.disk is not None:
        if concrete:
            idx = _disk_indices(scene, alpha_s)
            disk_rays = int(idx.size)
            reasons.append(
                f"Disk: {disk_rays} of {samples} rays can come within r_out = "
                f"{float(scene.disk.r_out):g}; only they are traced through the disk plane "
                f"({scene.disk.crossings} crossings x {scene.disk.steps} RK4 steps)"
            )
        else:
            reasons.append("Disk: traced values, all rays traced through the plane (masked)")
    else:
        reasons.append("no Disk: no per-ray tracing")
    bare = aberration is None and redshift is None and scene.disk is None and geometry == "table"
    if bare:
        reasons.append("no effects: the plain renderer's program (render_array)")
    p = Plan(geometry, aberration, redshift, scene.disk is not None, disk_rays, samples,
             weak_bound, bare, tuple(reasons))  # fmt: skip
    return p, idx


# ------------------------------------------------------------------ rendering


def _render(scene: EffectScene, plan: Plan, idx, ray_map: RayMap | None = None):
    """The compiled body: the stages `plan` names, nothing else. `ray_map`: the table
    of the camera's distance if built already (else built here, differentiably)."""
    cam = scene.camera
    dt = cam.dtype
    d = cam.distance
    alpha, cb, sb = cam.rays()
    if plan.aberration is not None:
        with jax.named_scope("jaxlens.aberration"):
            alpha_s, cb_s, sb_s, cos_a, v = _to_static(cam, scene.motion, alpha, cb, sb)
    else:
        alpha_s, cb_s, sb_s, cos_a, v = alpha, cb, sb, None, None
    g_cam = None
    if plan.redshift is not None:
        with jax.named_scope("jaxlens.redshift"):
            g_cam = _effects.static_blueshift(d).astype(dt)
            if cos_a is not None:
                g_cam = g_cam * _effects.doppler_factor(cos_a, v)
    with jax.named_scope(f"jaxlens.{plan.geometry}"):
        if plan.geometry == "table":
            if ray_map is None:
                ray_map = RayMap.build(d, accuracy=scene.accuracy)
            phi = ray_map.escape_angle(alpha_s)
            escaped = alpha_s > ray_map.alpha_sh
        elif plan.geometry == "weak_field":
            phi, _ = weak_field_escape_angle(alpha_s, d)
            escaped = None
        else:
            res = trace(alpha_s, d, accuracy=scene.accuracy, method="exact")
            phi, escaped = res.phi, res.escaped
    n = sky_direction(phi, cb_s, sb_s)
    if not cam.at_origin():
        n = cam.to_world(n)
    if plan.redshift is not None:
        with jax.named_scope("jaxlens.redshift"):
            rad = _effects.shifted_sky(scene.sky, n, g_cam, plan.redshift)
    else:
        rad = scene.sky(n)
    if escaped is not None:
        rad = jnp.where(escaped[..., None], rad, 0.0)
    if plan.disk:
        with jax.named_scope("jaxlens.disk"):
            rad = _apply_disk(scene, plan, idx, rad, alpha_s, cb_s, sb_s, g_cam)
    h, w, k = cam.height, cam.width, cam.supersample
    return rad.reshape(h, w, k * k, 3).mean(axis=2)


def _apply_disk(scene, plan, idx, rad, alpha_s, cb_s, sb_s, g_cam):
    shape = alpha_s.shape
    flat = rad.reshape(-1, 3)

    def take(x):
        x = jnp.broadcast_to(x, shape).reshape(-1)
        return x if idx is None else x.at[idx].get(mode="clip")

    hits = _disk.trace_disk(take(alpha_s), take(cb_s), take(sb_s), scene.camera.distance,
                            scene.disk)  # fmt: skip
    if idx is None:
        hits = eqx.tree_at(
            lambda h: h.hit, hits,
            hits.hit & _disk.can_reach(take(alpha_s), scene.camera.distance, scene.disk.r_out),
        )  # fmt: skip
    col = _disk.disk_radiance(scene.disk, hits, None if g_cam is None else take(g_cam),
                              plan.redshift)  # fmt: skip
    if idx is None:
        return jnp.where(hits.hit[:, None], col, flat).reshape(rad.shape)
    old = flat.at[idx].get(mode="clip")
    return flat.at[idx].set(jnp.where(hits.hit[:, None], col, old), mode="drop").reshape(rad.shape)


@eqx.filter_jit
def _compiled(scene, key, idx, ray_map):
    return _render(scene, key, idx, ray_map)


def _program(scene, plan, idx, ray_map):
    """The compiled program of `plan`, keyed by its structure alone (a new camera,
    disk-ray count or bound reuses it; a new gather size among 16 recompiles)."""
    return _compiled(scene, plan.structure(), idx, ray_map)


@eqx.filter_jit
def _build_map(distance, accuracy):
    # One compiled table builder for every scene of an accuracy (any distance).
    return RayMap.build(distance, accuracy=accuracy)


def _host_map(scene, plan):
    if plan.geometry != "table":
        return None
    return _build_map(scene.camera.distance, float(scene.accuracy))


def _padded(idx, plan):
    if idx is None:
        return None
    size = _bucket(idx.size, plan.samples)
    out = np.full(size, plan.samples, np.int32)  # out of range: dropped on scatter
    out[: idx.size] = idx
    return jnp.asarray(out)


def render_scene_array(
    scene_like, *, plan: Plan | None = None, ray_map: RayMap | None = None, **effects
) -> Float[Array, "H W 3"]:
    """The image of a scene with its effects, as one traceable function (`jit`,
    `grad` with respect to any array field of camera, sky, motion and disk).

    **Arguments:** `scene_like` (`EffectScene`, or an object with `camera`, `sky`);
    `plan`: a `Plan` to follow (default: `plan(scene)`; under tracing the safe one);
    `ray_map`: a `RayMap` of the camera's distance built already (default: built
    inside, so gradients with respect to the distance flow through the table);
    `**effects`: `motion=`, `redshift=`, `disk=` overriding the scene's.

    **Returns:** linear radiance `(H, W, 3)` in the camera's dtype; captured rays 0
    (or the disk in front of them).
    """
    scene = as_scene(scene_like, **effects)
    if plan is None:
        plan, idx = _plan(scene)
    else:
        idx = None
        if plan.disk and plan.disk_rays is not None:
            with jax.ensure_compile_time_eval():
                idx = _disk_indices(scene, _static_rays(scene.camera, scene.motion)[0])
    if plan.bare and ray_map is None:
        return render_array(scene.camera, scene.sky, accuracy=scene.accuracy)
    return _render(scene, plan, _padded(idx, plan), ray_map)


def render_scene(scene_like, **effects) -> np.ndarray:
    """Render a scene with the effects it calls for, on the path `plan` chooses.

    **Arguments:** `scene_like`: an `EffectScene`, or an object with `camera`, `sky`
    (and `accuracy`), e.g. a `Scene` from a TOML file; `**effects`: `motion=`,
    `redshift=`, `disk=` to add or replace effects.

    **Returns:** linear float32 RGB `(H, W, 3)`. A scene without effects is handed to
    `render` (chunked, the plain renderer); with effects, one compiled program for
    the plan.
    """
    scene = as_scene(scene_like, **effects)
    p, idx = _plan(scene)
    if p.bare:
        return render(scene.camera, scene.sky, accuracy=scene.accuracy)
    out = _program(scene, p, _padded(idx, p), _host_map(scene, p))
    return np.asarray(out, np.float32)


def lowered_text(scene_like, **effects) -> str:
    """The lowered (StableHLO) text of the program `render_scene` compiles for a scene,
    with debug locations (the `jaxlens.<stage>` scopes): for checking which stages a
    program contains."""
    scene = as_scene(scene_like, **effects)
    p, idx = _plan(scene)
    if p.bare:
        fn = eqx.filter_jit(lambda s: render_array(s.camera, s.sky, accuracy=s.accuracy))
        return fn.lower(scene).lowered.as_text(debug_info=True)
    low = _compiled.lower(scene, p.structure(), _padded(idx, p), _host_map(scene, p))
    return low.lowered.as_text(debug_info=True)


# ------------------------------------------------------------------ scene files

_MOTIONS = {"orbit": CircularOrbit, "infall": RadialInfall}
_DISK_KEYS = {
    "r_in": (float, "a number > 1.5 (units of R_S)"),
    "r_out": (float, "a number > r_in (units of R_S)"),
    "inclination_deg": (float, "a number in [0, 180] (degrees)"),
    "position_angle_deg": (float, "a finite number (degrees)"),
    "temperature": (float, "a number > 0 (K)"),
    "brightness": (float, "a number >= 0"),
    "crossings": (int, "a whole number >= 1"),
    "steps": (int, "a whole number >= 2"),
}


def _number(where, key, value, kind, valid):
    ok = not isinstance(value, bool) and isinstance(value, int | float)
    if kind is int:
        ok = ok and isinstance(value, int)
    if not ok or not math.isfinite(float(value)):
        raise ValueError(f"{where} {key} = {value!r} is not valid: expected {valid}")
    return kind(value)


def effects_from_dict(table: dict, *, where: str = "[effects]") -> dict:
    """Effects from the `[effects]` table of a scene file (TOML schema below), checked
    with errors that name the key, its value and what is valid.

    ```toml
    [effects]
    method = "auto"              # auto | table | weak_field | trace
    [effects.motion]
    type = "orbit"               # orbit (circular geodesic at the camera's D) | infall
    angle_deg = 0.0              # orbit: direction of motion in the image, degrees
    [effects.redshift]
    mode = "spectral"            # spectral | bolometric
    [effects.disk]
    r_in = 3.0                   # units of R_S
    r_out = 12.0
    inclination_deg = 80.0
    position_angle_deg = 0.0
    temperature = 8000.0         # peak temperature, K
    brightness = 1.0
    crossings = 3                # 1 direct image, 2 + secondary, ...
    steps = 48                   # RK4 steps per half turn
    ```

    **Returns:** keyword arguments for `EffectScene` (`motion`, `redshift`, `disk`,
    `method`), only those present.
    """
    if not isinstance(table, dict):
        raise ValueError(f"{where} must be a table, got {table!r}")
    known = {"method", "motion", "redshift", "disk"}
    for key in table:
        if key not in known:
            raise ValueError(f"{where} has an unknown key {key!r}; valid keys: {sorted(known)}")
    out = {}
    if "method" in table:
        m = table["method"]
        if m not in ("auto", "table", "weak_field", "trace"):
            raise ValueError(
                f"{where} method = {m!r} is not valid: auto | table | weak_field | trace"
            )
        out["method"] = m
    if "motion" in table:
        t = dict(table["motion"])
        kind = t.pop("type", None)
        if kind not in _MOTIONS:
            raise ValueError(f"{where}.motion type = {kind!r} is not valid: orbit | infall")
        if kind == "orbit":
            angle = _number(f"{where}.motion", "angle_deg", t.pop("angle_deg", 0.0), float,
                            "a finite number (degrees)")  # fmt: skip
            out["motion"] = CircularOrbit(math.radians(angle))
        else:
            out["motion"] = RadialInfall()
        if t:
            raise ValueError(f"{where}.motion has unknown keys {sorted(t)}")
    if "redshift" in table:
        t = dict(table["redshift"])
        mode = t.pop("mode", "spectral")
        if mode not in ("spectral", "bolometric"):
            raise ValueError(
                f"{where}.redshift mode = {mode!r} is not valid: spectral | bolometric"
            )
        if t:
            raise ValueError(f"{where}.redshift has unknown keys {sorted(t)}")
        out["redshift"] = Redshift(mode)
    if "disk" in table:
        t = table["disk"]
        kw = {}
        for key, value in t.items():
            if key not in _DISK_KEYS:
                raise ValueError(
                    f"{where}.disk has an unknown key {key!r}; valid keys: {', '.join(_DISK_KEYS)}"
                )
            kind, valid = _DISK_KEYS[key]
            v = _number(f"{where}.disk", key, value, kind, valid)
            if key.endswith("_deg"):
                if key == "inclination_deg" and not 0.0 <= v <= 180.0:
                    raise ValueError(f"{where}.disk {key} = {v!r} is not valid: expected {valid}")
                kw[key[:-4]] = math.radians(v)
            else:
                kw[key] = v
        out["disk"] = _disk.Disk(**kw)
    return out


def load_effect_scene(path, *, dtype=None) -> EffectScene:
    """Read a TOML scene file: the plain scene (`load_scene`'s schema) plus an optional
    `[effects]` table (`effects_from_dict`)."""
    from . import _scene

    data = _scene.read_scene_file(path)
    effects = effects_from_dict(data.pop("effects", {}))
    base = _scene.Scene.from_dict(data, source=str(path), dtype=dtype)
    return as_scene(base, **effects)
