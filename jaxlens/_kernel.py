"""The one traceable kernel: a block of pixel rows of a scene -> linear radiance.

Every image jaxlens makes (a render, an animation frame, the explorer, `render_array`
under `grad`) is this function on a block of rows, with the stages its `Plan` names:

1. **samples**: the $k \\times k$ area samples of the block's pixels, camera frame
   (`Camera.sample_x`, `sample_y`); local angle $\\alpha$ from the hole, orbital plane
   $\\beta$, and one sample's size in $\\alpha$.
2. **aberration** (a moving camera): the pixel directions boosted to the static
   observer's frame; the static ray map stays one-dimensional.
3. **redshift**: the camera's frequency ratio $g$ for light from infinity.
4. **geometry**: the escape angle $\\Phi(\\alpha)$ from the plan's source: the ray map
   (`RayMap`, built once per distance), the weak-field series, or the exact closed
   form per ray (`trace`). For a sky on a sphere $r = R$ (`Scene.source_distance`):
   the azimuth of its crossing from the ray map of $(D, R)$ ($R > D$), or each ray's
   exact crossings (`"crossings"`, up to two, their radiance added; `"crossing"`,
   the one of a sphere beyond the camera). Samples that straddle the shadow edge are
   weighted by the fraction of their footprint outside it (a linear ramp over one
   sample in $\\alpha$), so the edge carries gradient with respect to distance and
   field of view.
5. **sky**: the sky's radiance in the escaping directions (frequency-shifted if asked).
6. **disk**: rays that can reach the disk are followed through its plane.
7. the mean over each pixel's samples.

With `Camera(..., sampling="gauss")` the pixels are area-exact instead (`cells`): the
$k \\times k$ nodes of a Gauss-Legendre rule, the exact share of each cell outside the
shadow edge, and the thin rings of compact sources (`AbstractCompactSky.crossing`)
integrated across the cells; a fit differentiates this path.

Stages are Python `if`s on the plan, never on traced values: a stage the scene does
not name is not in the compiled program. Each runs in `jax.named_scope("jaxlens.<stage>")`.

For a centred camera whose rays depend on $|x|$ and $|y|$ alone (static or radially
moving, no disk), the per-ray work is done for one half of the columns and mirrored,
and with `pair` a block of rows also yields its mirror rows in the bottom half: a
quarter of the samples go through the map; the sky is looked up at every sample.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _area, _disk, _effects, _limits
from ._camera import view_angles
from ._exact import finite_crossings, plane_crossings, shadow_angle
from ._fastmath import sin_cos
from ._messages import cut
from ._ray_inputs import _MAX_COMPARED, MAX_DISTANCE
from ._sky import AbstractCompactSky, SkySum
from ._sky._base import rgb_shift_power
from ._trace import trace
from ._util import fusion_barrier
from ._weak import weak_field_series

# The camera's orientation and position angles, as the kernel uses them.
_CAMERA_ANGLES = ("yaw", "pitch", "roll", "azimuth", "elevation")


# The dtypes pixels are computed in: float16's 3 significant digits cannot resolve
# the sky directions of even a small image, and its range (6.5e4) ends below many
# radiances (an all-NaN image).
PIXEL_DTYPES = ("float32", "float64")


def pixel_dtype(dtype):
    """`dtype` as a NumPy dtype, checked: one of `PIXEL_DTYPES` (a `ValueError`
    naming it otherwise, a `TypeError` for what is not a dtype)."""
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise TypeError(f"dtype={cut(repr(dtype))} is not a dtype: pixels are "
                        "computed in float32 or float64") from None  # fmt: skip
    if dt.name not in PIXEL_DTYPES:
        raise ValueError(f"dtype={dt.name} is not supported: pixels are computed in float32 "
                         "or float64")  # fmt: skip
    return dt


def _checks(scene, xp, dtype=None):
    """Each check of a scene's values: `(where, bad, message)`, `where` the value's
    path in the scene and `bad` where it fails (`xp`: `jnp` traced, `np` on the host;
    `dtype`: the pixel dtype, default the camera's; another is a `ValueError`).

    The camera's distance, field of view and angles are checked here; the sky, the
    motion and the disk declare their fields' ranges (`limits`, see `_limits`), checked
    in the pixel dtype: a value it rounds to inf (or a width to 0) is refused too."""
    cam = scene.camera
    d, fov = xp.asarray(cam.distance), xp.asarray(cam.fov)
    out = [
        (lambda s: s.camera.distance, ~xp.isfinite(d) | ~(d > 1.0),
         "camera distance must be finite and > 1 (units of R_S; the horizon is at 1)"),
        (lambda s: s.camera.fov, ~xp.isfinite(fov) | ~(fov > 0.0) | ~(fov < xp.pi),
         "field of view must be in (0, pi) radians, i.e. (0, 180) degrees"),
    ]  # fmt: skip
    # Sky directions are rounded to about one ulp of the dtype (absolute). Samples
    # closer than 4 ulps are no longer told apart: a float32 checkerboard at 480
    # samples across differed from float64 on 20 % of its edge pixels at 0.03 degrees
    # (8 ulps apart), 4.5 % at 0.1 degrees, 0.3 % at 2 degrees.
    dt = pixel_dtype(cam.dtype if dtype is None else dtype)
    across = cam.width * cam.supersample
    fov_min = 4.0 * float(jnp.finfo(dt).eps) * across
    f64 = 4.0 * float(np.finfo(np.float64).eps) * across
    hint = f" (float64 reaches {math.degrees(f64):.2g} degrees)" if dt != jnp.float64 else ""
    out.append((lambda s: s.camera.fov, (fov > 0.0) & (fov < fov_min),
                f"field of view must be at least {math.degrees(fov_min):.3g} degrees for "
                f"{across} samples across in {dt.name}: narrower fields are below the "
                f"resolution of its sky directions{hint}"))  # fmt: skip
    angle = _limits.finite("radians")
    for name in _CAMERA_ANGLES:
        out.append((_limits._getter(lambda s: s.camera, name),
                    angle.bad(getattr(cam, name), xp, dt),
                    f"camera {name} must be {angle.describe()}"))  # fmt: skip
    out += _limits.checks(scene.sky, lambda s: s.sky, "sky", xp, dt)
    for part in ("motion", "disk"):
        if getattr(scene, part) is not None:
            where = _limits._getter(lambda s: s, part)
            out += _limits.checks(getattr(scene, part), where, part, xp, dt)
    if scene.motion is not None and not scene.motion.radial:
        out.append((lambda s: s.camera.distance, ~(d > 1.5),
                    "a circular orbit needs distance > 1.5 (units of R_S)"))  # fmt: skip
    if scene.disk is not None:
        r_in, r_out = (xp.asarray(r).astype(dt) for r in (scene.disk.r_in, scene.disk.r_out))
        out.append((lambda s: s.disk.r_in, ~(r_in > 1.5) | ~(r_in < r_out) | ~xp.isfinite(r_out),
                    "disk radii must satisfy 1.5 < r_in < r_out < inf (units of R_S)"))  # fmt: skip
    if scene.source_plane is not None:
        plane = xp.asarray(scene.source_plane).astype(dt)
        out.append((lambda s: s.source_plane,
                    ~xp.isfinite(plane) | ~(plane > 0.0) | (plane > _MAX_COMPARED),
                    f"source plane must be > 0 and at most {MAX_DISTANCE:g} (units of "
                    "R_S)"))  # fmt: skip
    if scene.source_distance is not None:
        r = xp.asarray(scene.source_distance).astype(dt)
        out.append((lambda s: s.source_distance,
                    ~xp.isfinite(r) | ~(r > 1.0) | (r > _MAX_COMPARED),
                    f"source distance must be > 1 and at most {MAX_DISTANCE:g} (units of R_S; "
                    "None for a sky at infinity)"))  # fmt: skip
        if scene.disk is not None:
            out.append((lambda s: s.source_distance, ~(r >= d) | ~(r >= r_out),
                        "a Disk needs the source sphere outside the camera and the disk: "
                        "source_distance >= distance and >= r_out (units of R_S)"))  # fmt: skip
    return out


def checked(scene):
    """`scene` with its values checked where they are used: `eqx.error_if` on the
    camera distance ($D > 1$, finite), the field of view ($0 <$ FOV $< \\pi$), the
    camera's angles (finite), a circular orbit's distance ($D > 1.5$), the disk radii
    ($1.5 < r_{in} < r_{out}$, finite) and every field of the sky, motion and disk
    against its declared range (`limits`); a bad traced value raises at run time
    under `jit`, never a NaN image."""
    for where, bad, message in _checks(scene, jnp):
        scene = eqx.tree_at(where, scene, eqx.error_if(where(scene), bad, message))
    return scene


def verify(scene, dtype=None):
    """The checks of `checked` on the host, for concrete values: `ValueError` with the
    same message and the bad value (`dtype`: the pixel dtype, default the camera's). A
    host driver (`render`) checks this way, so that its compiled blocks
    carry no error callback, which would keep them out of JAX's persistent
    compilation cache."""
    for where, bad, message in _checks(scene, np, dtype):
        if np.any(bad):
            raise ValueError(f"{message}; got {_limits.shown(where(scene), bad)}")


def coverage(alpha, alpha_sh, width):
    """Fraction of a sample's footprint outside the shadow (a linear ramp over one
    sample width `width` in alpha, radians), and the alpha of the escaping part's
    centre, where the sample takes its radiance."""
    cover = jnp.clip((alpha - alpha_sh) / width + 0.5, 0.0, 1.0)
    edge = jnp.maximum(alpha, alpha_sh + 0.5 * width * (1.0 - cover))
    return cover, edge


def _to_static(scene, alpha, cb, sb):
    """Moving-frame sample angles -> static-frame angles, the Doppler factor
    $\\delta = \\sqrt{1-v^2}/(1 - v\\cos a')$ (also the local linear scale of the
    aberration map, which is conformal) and nothing else."""
    cam, motion = scene.camera, scene.motion
    dt = alpha.dtype
    v = motion.speed(cam.distance).astype(dt)
    if motion.radial:
        ca, sa = jnp.cos(alpha), jnp.sin(alpha)
        inv = 1.0 / (1.0 - v * ca)
        cs = (ca - v) * inv
        ss = sa * jnp.sqrt((1.0 - v) * (1.0 + v)) * inv
        return jnp.arctan2(ss, cs), cb, sb, _effects.doppler_factor(ca, v)
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
    return jnp.arctan2(rho, ns[..., 2]), cb_s, sb_s, _effects.doppler_factor(cos_a, v)


def _frequency_ratio(scene, doppler, like):
    """The camera's frequency ratio $g$ for light from the sky, `like`'s shape: the
    static observer's blueshift for light from infinity, times $\\sqrt{1 - 1/R}$ for a
    sky on the sphere $r = R$ (`source_distance`), times the Doppler factor of a moving
    camera (`doppler`, `None` for a static one)."""
    g = _effects.static_blueshift(scene.camera.distance).astype(like.dtype)
    if scene.source_distance is not None:  # a static emitter at R: sqrt(1 - 1/R) of it
        r = jnp.asarray(scene.source_distance).astype(like.dtype)
        g = g * jnp.sqrt((r - 1.0) / r)
    return jnp.broadcast_to(g if doppler is None else g * doppler, like.shape)


def _escape_angle(scene, plan, ray_map, alpha):
    d = scene.camera.distance
    if plan.geometry == "table":
        return ray_map.escape_angle(alpha)
    if plan.geometry == "weak_field":
        return weak_field_series(alpha, d)[0]  # the scene's values are checked
    if plan.geometry == "crossing":  # the one crossing of a sphere beyond the camera
        dt = alpha.dtype
        r = jnp.asarray(scene.source_distance).astype(dt)
        return finite_crossings(alpha, d.astype(dt), r).first
    return trace(alpha, d, accuracy=scene.accuracy, method="exact").phi


def _geometry(scene, plan, ray_map, x, y):
    """Per-sample geometry at image-plane points `x, y` (pixels, one shape).

    **Returns:** `(sin_phi, cos_phi, cb, sb, cover, g, alpha_s)`: the escape angle's
    sine and cosine, the static-frame orbital plane, the shadow coverage, the camera's
    frequency ratio (`None` without redshift) and the static-frame alpha.
    """
    cam = scene.camera
    dt = x.dtype
    f = cam.focal
    alpha, cb, sb = cam._angles(x, y, oriented=not plan.centred)
    # One sample's size in alpha: cos^2(angle off the image axis) / (f k); for an
    # off-centre view the same to first order.
    width = f / ((x * x + y * y + f * f) * cam.supersample)
    g = doppler = None
    if plan.aberration is not None:
        with jax.named_scope("jaxlens.aberration"):
            alpha, cb, sb, doppler = _to_static(scene, alpha, cb, sb)
            width = width * doppler
    if plan.redshift is not None:
        with jax.named_scope("jaxlens.redshift"):
            g = _frequency_ratio(scene, doppler, alpha)
    with jax.named_scope(f"jaxlens.{plan.geometry}"):
        if ray_map is not None:
            alpha_sh = ray_map.alpha_sh.astype(dt)
        else:
            alpha_sh = shadow_angle(cam.distance).astype(dt)
        cover, edge = coverage(alpha, alpha_sh, width)
        if _on_shell(plan):
            phi, cover = _shell_crossings(scene, alpha, cover, edge)
            if g is not None:
                g = jnp.broadcast_to(g, phi.shape)
        elif plan.geometry == "plane":
            hits = plane_crossings(edge, cam.distance.astype(dt),
                                   jnp.asarray(scene.source_plane).astype(dt))  # fmt: skip
            phi, cover = hits.phi, cover * hits.hit
            if g is not None:  # a static emitter at the crossing's radius
                r = jnp.where(hits.hit, hits.radius, 2.0)
                g = g * jnp.sqrt((r - 1.0) / r)
        else:
            phi = _escape_angle(scene, plan, ray_map, edge)
    sin_phi, cos_phi = sin_cos(phi)
    return sin_phi, cos_phi, cb, sb, cover, g, alpha


def _on_shell(plan) -> bool:
    """Whether the block's rays take the exact crossings of the sky's sphere (up to two
    a ray, a leading axis of 2 on their arrays). A sphere beyond the camera read from
    its ray map (`RayMap.build(..., radius=R)`, the `"table"` geometry) takes the sky
    at infinity's path: one crossing a ray, where it escapes."""
    return plan.geometry == "crossings"


def _shell_crossings(scene, alpha, cover, edge):
    """The crossings of the sky's sphere $r = R$ (`scene.source_distance`) by the rays
    of static-frame angles `alpha`, and the weight of each in its sample.

    A sample wholly outside or inside the shadow (`cover` 1 or 0) takes the crossings
    of its own ray, each with weight 1 (the sphere is transparent: every crossing adds
    its radiance). A sample on the shadow's edge (`cover` in (0, 1)) takes those of
    its escaping part's centre (`edge`): a crossing on the way in ($R < D$, before the
    periapsis) is shared by the captured part of its footprint, weight 1; one after the
    periapsis (the second for $R < D$, the only one for $R \\ge D$) is seen by the
    escaping part alone, weight `cover`.

    **Returns:** `(phi, weight)`, each of shape `(2,) + alpha.shape`: the azimuths swept
    from the camera to the first and second crossing (radians) and their weights (0
    where the ray has no such crossing, or winds past the budget).
    """
    dt = alpha.dtype
    d = scene.camera.distance.astype(dt)
    r = jnp.asarray(scene.source_distance).astype(dt)
    ramp = cover > 0.0
    first, second, count = finite_crossings(jnp.where(ramp, edge, alpha), d, r)
    w1 = jnp.where(ramp & ~(r < d), cover, 1.0) * (count >= 1)
    w2 = jnp.where(ramp, cover, 1.0) * (count >= 2)
    return jnp.stack([first, second]), jnp.stack([w1, w2]).astype(dt)


def _symmetric(scene, plan, ray_map, row0, rows: int, pair: bool):
    """Camera-frame directions, coverage and $g$ of the block through the mirror
    symmetries of a centred camera: the per-ray work on one half of the columns. With
    `pair`, the mirror rows follow the block's rows in one batch (so what consumes them,
    the sky, is traced and compiled once)."""
    cam = scene.camera
    xs = cam.sample_x()
    ys = cam.sample_y(row0, rows)
    half, odd = xs.shape[0] // 2, xs.shape[0] % 2
    xh = jnp.abs(xs[half:])
    x = jnp.broadcast_to(xh[None, :], (ys.shape[0], xh.shape[0]))
    y = jnp.broadcast_to(ys[:, None], x.shape)
    sin_phi, c, _, _, cover, g, _ = _geometry(scene, plan, ray_map, x, y)
    rho = jnp.sqrt(x * x + y * y)
    safe = rho > 0
    s = jnp.where(safe, sin_phi / jnp.where(safe, rho, 1.0), 0.0)
    per_ray = (s, c, cover) if g is None else (s, c, cover, g)
    # Materialise the half before mirroring: XLA would otherwise fuse the map look-up
    # into every consumer of the mirrored arrays and repeat it.
    per_ray = jax.lax.optimization_barrier(per_ray)
    # (The arrays of a sky on a sphere lead with an axis of its two crossings.)
    per_ray = [jnp.concatenate([a[..., odd:][..., ::-1], a], axis=-1) for a in per_ray]

    if pair:  # the mirror rows: the same rays, y negated
        per_ray = [jnp.concatenate([a, a[..., ::-1, :]], axis=-2) for a in per_ray]
        ys = jnp.concatenate([ys, -ys[::-1]])
    s, c, cover = per_ray[:3]
    g = per_ray[3] if g is not None else None
    n = jnp.stack([s * xs[None, :], s * ys[:, None], -c], axis=-1)
    return n, cover, g


def _sample_grid(cam, row0, rows: int):
    """Sample columns `xs (W k,)`, rows `ys (rows k,)` and their grid `x, y` (pixels)."""
    xs = cam.sample_x()
    ys = cam.sample_y(row0, rows)
    x = jnp.broadcast_to(xs[None, :], (ys.shape[0], xs.shape[0]))
    return xs, ys, x, jnp.broadcast_to(ys[:, None], x.shape)


def _general(scene, plan, ray_map, row0, rows: int):
    """Camera-frame directions, coverage, $g$ and static-frame rays of every sample."""
    cam = scene.camera
    xs, ys, x, y = _sample_grid(cam, row0, rows)
    sp, cp, cb, sb, cover, g, alpha_s = _geometry(scene, plan, ray_map, x, y)
    n = jnp.stack([sp * cb, sp * sb, -cp], axis=-1)
    return n, cover, g, (alpha_s, cb, sb)


def directions(scene, plan, ray_map, row0, rows: int):
    """World sky directions `(rows k, W k, 3)` and shadow coverage `(rows k, W k)` of
    the block's samples, by the path `shade` takes (for checks and benchmarks)."""
    if plan.symmetric:
        n, cover, _ = _symmetric(scene, plan, ray_map, row0, rows, False)
    else:
        n, cover, _, _ = _general(scene, plan, ray_map, row0, rows)
    if not plan.at_origin:
        n = scene.camera.to_world(n)
    return n, cover


def _sky_radiance(sky, plan, n, g):
    """A sky's radiance at world directions `n`, frequency-shifted if the plan says."""
    if plan.redshift is None:
        return sky(n)
    with jax.named_scope("jaxlens.redshift"):
        return sky.shifted(n, g, plan.redshift)


def _radiance(scene, plan, n, g):
    if not plan.at_origin:
        n = scene.camera.to_world(n)
    return _sky_radiance(scene.sky, plan, n, g)


def _average(radiance, rows: int, width: int, k: int):
    """Mean over each pixel's k x k samples: `(rows k, W k, 3)` -> `(rows, W, 3)`."""
    if k == 1:
        return radiance
    return radiance.reshape(rows, k, width, k, 3).mean(axis=(1, 3))


def static_alpha(scene, plan, row0, rows: int):
    """Static-frame local angle (radians) of every sample of the block, `(rows k, W k)`:
    what the weak-field bound and the disk's reach are decided on."""
    cam = scene.camera
    xs, ys, x, y = _sample_grid(cam, row0, rows)
    alpha, cb, sb = cam._angles(x, y, oriented=not plan.centred)
    if plan.aberration is not None:
        alpha = _to_static(scene, alpha, cb, sb)[0]
    return alpha


def reach(scene, plan, row0, rows: int):
    """Which samples of the block can come within the disk's outer radius (bool,
    `(rows k, W k)`): the rays the disk stage follows."""
    alpha = static_alpha(scene, plan, row0, rows)
    return _disk.can_reach(alpha, scene.camera.distance, scene.disk.r_out)


def _apply_disk(scene, plan, rad, rays, g):
    alpha_s, cb, sb = rays
    shape = alpha_s.shape
    flat = rad.reshape(-1, 3)
    d = scene.camera.distance
    mask = _disk.can_reach(alpha_s, d, scene.disk.r_out)
    if plan.disk_rays is None:  # traced values: every ray, masked
        take = lambda a: jnp.broadcast_to(a, shape).reshape(-1)  # noqa: E731
    else:  # only the rays that can reach it, gathered into a batch of static size
        idx = jnp.nonzero(mask.reshape(-1), size=plan.disk_rays, fill_value=mask.size)[0]
        take = lambda a: jnp.broadcast_to(a, shape).reshape(-1).at[idx].get(mode="clip")  # noqa: E731
    hits = _disk.trace_disk(take(alpha_s), take(cb), take(sb), d, scene.disk)
    hit = hits.hit & take(mask)
    col = _disk.disk_radiance(scene.disk, hits, None if g is None else take(g), plan.redshift)
    col = col.astype(flat.dtype)
    if plan.disk_rays is None:
        return jnp.where(hit[:, None], col, flat).reshape(rad.shape)
    old = flat.at[idx].get(mode="clip")
    new = jnp.where(hit[:, None], col, old)
    return flat.at[idx].set(new, mode="drop").reshape(rad.shape)


# ------------------------------------------------------------------ area-exact cells

# Relativistic images of order 1 and 2 of a compact source (Phi = Phi_0 + 2 pi, + 4 pi)
# are integrated across the cells; higher orders are e^{-2 pi} fainter again.
THIN_ORDERS = (1, 2)


def split_sky(sky):
    """`(compact, rest)`: the compact sources of a sky (a tuple of
    `AbstractCompactSky`) and the sum of its other parts (`None` when there are none)."""
    parts = sky.parts if isinstance(sky, SkySum) else (sky,)
    compact = tuple(p for p in parts if isinstance(p, AbstractCompactSky))
    rest = [p for p in parts if not isinstance(p, AbstractCompactSky)]
    if not rest:
        return compact, None
    return compact, rest[0] if len(rest) == 1 else SkySum(tuple(rest))


def _static_rays(scene, plan, x, y):
    """Static-frame local angle, orbital plane and Doppler factor (`None` for a static
    camera) at image-plane points `x, y` (pixels), and $|\\nabla\\alpha_s|$ (radians a
    pixel) with the unit normal of the iso-alpha lines `(nx, ny)`."""
    cam = scene.camera
    f = cam.focal
    dx, dy, dz = cam._view(x, y, oriented=not plan.centred)
    # d(dx, dy, dz) / d(x, y): the view rotation's first two columns (dz = f unrotated).
    r = ((1, 0), (0, 1), (0, 0)) if plan.centred else cam.rotation()
    alpha, cb, sb, rho = view_angles(dx, dy, dz)
    # d alpha / d(x, y) of alpha = atan2(rho, dz): finite at the axis through the
    # guarded (cb, sb) that `view_angles` returns there.
    den = rho * rho + dz * dz
    gx = (dz * (cb * r[0][0] + sb * r[1][0]) - rho * r[2][0]) / den
    gy = (dz * (cb * r[0][1] + sb * r[1][1]) - rho * r[2][1]) / den
    doppler = None
    if plan.aberration == "radial":  # alpha_s depends on alpha alone, with slope delta
        alpha, cb, sb, doppler = _to_static(scene, alpha, cb, sb)
        gx, gy = gx * doppler, gy * doppler
    elif plan.aberration == "boost":

        def static_alpha(x_, y_):
            a, c, s = cam._angles(x_, y_, oriented=not plan.centred)
            return _to_static(scene, a, c, s)[0]

        one, zero = jnp.ones_like(x), jnp.zeros_like(x)
        gx = jax.jvp(static_alpha, (x, y), (one, zero))[1]
        gy = jax.jvp(static_alpha, (x, y), (zero, one))[1]
        alpha, cb, sb, doppler = _to_static(scene, alpha, cb, sb)
    grad = jnp.hypot(gx, gy)
    safe = grad > 0
    g_ = jnp.where(safe, grad, 1.0)
    nx, ny = jnp.where(safe, gx / g_, 1.0), jnp.where(safe, gy / g_, 0.0)
    return alpha, cb, sb, doppler, jnp.where(safe, grad, 1.0 / f), nx, ny


def ring_references(ray_map, dtype):
    """Where each thin order's escape angle is $(2m+1)\\pi$: `(tau, dphi_dtau)` of
    shape `(orders,)`, $\\tau = \\ln(\\alpha - \\alpha_{sh})$. Near the shadow edge
    $\\Phi$ is linear in $\\tau$ to $O(\\alpha - \\alpha_{sh})$, so a source off the
    axis shifts each ring by $\\Delta\\Phi / (d\\Phi/d\\tau)$ in $\\tau$."""
    targets = jnp.asarray([(2 * m + 1) * math.pi for m in THIN_ORDERS], dtype)
    # A loop over the orders, not a Python loop: the map enters once, materialised,
    # instead of XLA duplicating its producer into every gather.
    a, slope = jax.lax.map(lambda t: ray_map.solve(t, with_slope=True), targets)
    gap = a - ray_map.alpha_sh.astype(dtype)
    return jnp.log(gap), slope * gap


def cells(scene, plan, ray_map, x0, y0, side, k: int | None = None, *, references=None, rings=True):
    """Area-exact radiance of square pixel cells (the `"gauss"` sampling).

    Each cell of side `side` (pixels) with top-left corner `(x0, y0)` (image-plane
    pixels from the image centre, $x$ right, $y$ up) is split into the $k \\times k$
    sub-cells of a Gauss-Legendre rule. The sky is evaluated at the rule's nodes
    (the escaping direction of the static-frame $\\alpha$, as `shade`); the shadow
    edge enters through the exact fraction of each sub-cell outside it (the edge
    locally straight across a sub-cell), and the images of order 1 and 2 of compact
    sources (`AbstractCompactSky`) through the share of each sub-cell that their thin
    rings cross, times the source's integral across the ring. Every value is
    continuous in the camera's distance and field of view and in the source position:
    what a fit differentiates.

    **Arguments:** `scene` (one camera; `scene.camera.sampling` is not consulted),
    `plan` (its `Plan`; the `"table"` geometry for compact sources), `ray_map` (the
    `RayMap` of the distance in the camera's dtype), `x0`, `y0` (one shape), `side`
    (pixels: a scalar, or one a cell broadcasting to `x0`'s shape), `k` (the rule's
    order; default the camera's `supersample`);
    `references`: `ring_references(ray_map, dtype)` when the caller evaluates many
    batches of cells of one scene (computed here otherwise); `rings=False` leaves the
    thin rings out (`thin` is then 0: a coarse search that compares the primary
    image only). The scene's values are
    the caller's to check (`checked`), outside any loop over batches.

    **Returns:** `(main, thin)` of shape `x0.shape + (3,)`: the cells' mean radiance
    from the nodes and from the thin rings (their sum is the pixel value).
    """
    cam = scene.camera
    k = cam.supersample if k is None else int(k)
    dt = cam.dtype
    x0, y0 = jnp.asarray(x0, dt), jnp.asarray(y0, dt)
    node, weight, centre = (jnp.asarray(v, dt) for v in _area.rule(k))
    side = jnp.broadcast_to(jnp.asarray(side, dt), x0.shape)
    s4 = side[..., None, None]
    full = jnp.zeros(x0.shape + (k, k), dt)

    def grid(u):  # [..., i (x), j (y)]
        x = x0[..., None, None] + s4 * u[:, None] + full
        y = y0[..., None, None] - s4 * u[None, :] + full
        return x, y

    ext_x, ext_y = s4 * weight[:, None], s4 * weight[None, :]
    w2 = weight[:, None] * weight[None, :]
    if ray_map is not None:
        alpha_sh = ray_map.alpha_sh.astype(dt)
    else:
        alpha_sh = shadow_angle(cam.distance).astype(dt)
    compact, rest = split_sky(scene.sky)

    # Sub-cells: the static-frame angles at their centres, the edge's normal there.
    xc, yc = grid(centre)
    # Materialised: XLA would otherwise recompute the view's arctan2 and the edge's
    # normal (and, in a fit's Jacobian, their tangents) in every fusion that reads them.
    a_c, cb_c, sb_c, dop_c, grad, nx, ny = fusion_barrier(
        _static_rays(scene, plan, xc, yc), cam.focal
    )
    ax, ay = ext_x * jnp.abs(nx), ext_y * jnp.abs(ny)
    f = cam.focal
    if plan.centred and plan.aberration is None:
        # alpha = atan(rho / f): offsets measured exactly in rho, as on the image plane.
        t_edge = f * (jnp.tan(a_c) - jnp.tan(alpha_sh))
    else:
        t_edge = (a_c - alpha_sh) / grad
    with jax.named_scope("jaxlens.coverage"):
        cover = _area.edge_cover(t_edge, ax, ay)

    # Nodes: the sky in the escaping direction; a node inside the shadow takes the
    # radiance of the escaping part of its sub-cell.
    xn, yn = grid(node)
    a_n, cb_n, sb_n, dop_n = _static_rays(scene, plan, xn, yn)[:4]
    a_edge = alpha_sh + 0.5 * _area.half_extent(ax, ay) * grad
    g = None if plan.redshift is None else _frequency_ratio(scene, dop_n, a_n)
    with jax.named_scope(f"jaxlens.{plan.geometry}"):
        phi = _escape_angle(scene, plan, ray_map, jnp.maximum(a_n, a_edge))
    sp, cp = sin_cos(phi)
    n = jnp.stack([sp * cb_n, sp * sb_n, -cp], axis=-1)
    if not plan.at_origin:
        n = cam.to_world(n)
    with jax.named_scope("jaxlens.sky"):
        rad = jnp.zeros(n.shape, dt)
        if rest is not None:
            rad = rad + _sky_radiance(rest, plan, n, g)
        if compact:
            # Order 0 only (Phi < 2 pi): the higher orders come as thin rings below.
            prim = sum(_sky_radiance(c, plan, n, g) for c in compact)
            rad = rad + jnp.where((phi < 2.0 * jnp.pi)[..., None], prim, 0.0)
    main = jnp.sum((w2 * cover)[..., None] * rad, axis=(-3, -2))

    thin = jnp.zeros_like(main)
    if compact and rings:
        if ray_map is None:
            raise ValueError("thin rings of compact sources need the table geometry")
        with jax.named_scope("jaxlens.thin_rings"):
            if references is None:
                references = ring_references(ray_map, dt)
            tau_ref, dphi_dtau = references
            # The ring's radius and its integral vary across a pixel by O(offset /
            # radius) of the pixel's azimuth: both are taken at the pixel's centre, the
            # share of each sub-cell they cross per sub-cell.
            xp, yp = x0 + 0.5 * side, y0 - 0.5 * side
            _, cb_p, sb_p, dop_p, grad_p = _static_rays(scene, plan, xp, yp)[:5]
            zero = jnp.zeros_like(cb_p)
            e1 = jnp.stack([cb_p, sb_p, zero], axis=-1)
            e3 = jnp.stack([zero, zero, zero - 1.0], axis=-1)
            if not plan.at_origin:
                e1, e3 = cam.to_world(e1), cam.to_world(e3)
            scale = 1.0
            if plan.redshift is not None:  # compact skies are RGB: g^4 or g^3
                scale = _frequency_ratio(scene, dop_p, xp) ** rgb_shift_power(plan.redshift)
            exact = plan.centred and plan.aberration is None
            rho_c = f * jnp.tan(a_c) if exact else None
            for c in compact:
                phi0, integral = c.crossing(e1, e3)
                for i, m in enumerate(THIN_ORDERS):
                    shift = phi0 + 2.0 * math.pi * m - (2 * m + 1) * math.pi
                    gap = jnp.exp(tau_ref[i] + shift / dphi_dtau[i])
                    a_m = alpha_sh + gap
                    if exact:  # offsets of the sub-cells from the ring, pixels
                        t_m = (f * jnp.tan(a_m))[..., None, None] - rho_c
                        px_per_rad = f / jnp.cos(a_m) ** 2
                    else:
                        t_m = (a_m[..., None, None] - a_c) / grad
                        px_per_rad = 1.0 / grad_p
                    width = px_per_rad * gap / jnp.abs(dphi_dtau[i])  # d rho / d Phi
                    share = jnp.sum(w2 * _area.edge_density(t_m, ax, ay), axis=(-2, -1))
                    thin = thin + (share * width * scale)[..., None] * integral
    return main, thin


def _shade_cells(scene, plan, ray_map, row0, rows: int, check: bool):
    cam = scene.camera
    dt = cam.dtype
    x0 = jnp.arange(cam.width, dtype=dt) - 0.5 * cam.width
    y0 = 0.5 * cam.height - (jnp.asarray(row0, dt) + jnp.arange(rows, dtype=dt))
    x0, y0 = (
        jnp.broadcast_to(x0[None, :], (rows, cam.width)),
        jnp.broadcast_to(y0[:, None], (rows, cam.width)),
    )
    main, thin = cells(checked(scene) if check else scene, plan, ray_map, x0, y0, 1.0)
    return main + thin


def shade(scene, plan, ray_map, row0, rows: int, pair: bool = False, check: bool = True):
    """Linear radiance of pixel rows `row0 .. row0+rows` of one camera's image; with
    `pair` (symmetric plans only) also of their mirror rows `H-row0-rows .. H-row0`.

    **Arguments:** `scene` (one camera), `plan` (a `Plan`: the stages), `ray_map` (the
    `RayMap` of the camera's distance in the pixel dtype, for the table source; else
    `None`), `row0` (first pixel row, may be traced), `rows` (static), `check`
    (`checked` the scene's values in the program; `False` where the caller has
    `verify`ed them on the host).

    **Returns:** `(rows, W, 3)`, or `(2 rows, W, 3)` with `pair` (the block, then its
    mirror rows, each top to bottom), in the camera's dtype; captured rays are 0.
    """
    if scene.camera.sampling == "gauss":
        return _shade_cells(scene, plan, ray_map, row0, rows, check)
    if check:
        scene = checked(scene)
    cam = scene.camera
    k, w = cam.supersample, cam.width
    shell = _on_shell(plan)
    if plan.symmetric:
        n, cover, g = _symmetric(scene, plan, ray_map, row0, rows, pair)
        rad = _radiance(scene, plan, n, g) * cover[..., None]
        if shell:  # the radiance of every crossing of the sky's sphere adds
            rad = jnp.sum(rad, axis=0)
        return _average(rad, 2 * rows if pair else rows, w, k)
    n, cover, g, rays = _general(scene, plan, ray_map, row0, rows)
    rad = _radiance(scene, plan, n, g) * cover[..., None]
    if shell:
        rad = jnp.sum(rad, axis=0)
        g = None if g is None else g[0]
    if plan.disk:
        with jax.named_scope("jaxlens.disk"):
            rad = _apply_disk(scene, plan, rad, rays, g)
    return _average(rad, rows, w, k)
