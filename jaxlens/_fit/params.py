"""The parameters a general fit can free: where each lives in a `Scene` (or beside it),
its unit, and the transform that keeps it in range.

A parameter is fitted as an unbounded internal value $\\theta$: `above(lo)` maps
$\\theta \\mapsto lo + e^\\theta$, `between(lo, hi)` maps it through a logistic curve,
`free` is the identity. The scene is updated with `eqx.tree_at`, so any array field
the renderer differentiates can be a parameter.
"""

import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._sky import GaussianStar, SkySum, Uniform
from .._sky._base import angles_from_direction, direction_from_angles
from .._units import angle, is_quantity, length, plain
from .._util import has_tracer, to_device


@dataclasses.dataclass(frozen=True)
class Transform:
    """Internal (unbounded) value <-> physical value; `slope` is d physical / d internal."""

    kind: str
    lo: float = -math.inf
    hi: float = math.inf

    def forward(self, t):
        """The physical value of internal `t` (on the host for host numbers)."""
        host = isinstance(t, (float, np.floating))
        if self.kind == "above":
            return self.lo + (math.exp(t) if host else jnp.exp(t))
        if self.kind == "between":
            sig = 0.5 * (1.0 + math.tanh(0.5 * t)) if host else jax.nn.sigmoid(t)
            return self.lo + (self.hi - self.lo) * sig
        return t

    def inverse(self, v: float) -> float:
        if self.kind == "above":
            return math.log(max(v - self.lo, 1e-300))
        if self.kind == "between":
            u = min(max((v - self.lo) / (self.hi - self.lo), 1e-12), 1.0 - 1e-12)
            return math.log(u / (1.0 - u))
        return float(v)

    def slope(self, v: float) -> float:
        if self.kind == "above":
            return v - self.lo
        if self.kind == "between":
            u = (v - self.lo) / (self.hi - self.lo)
            return (self.hi - self.lo) * u * (1.0 - u)
        return 1.0

    def at_bound(self, v: float, tol: float = 1e-6) -> bool:
        span = 1.0 if not math.isfinite(self.hi - self.lo) else self.hi - self.lo
        return (math.isfinite(self.lo) and v - self.lo < tol * span) or (
            math.isfinite(self.hi) and self.hi - v < tol * span
        )


FREE = Transform("free")


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One fittable quantity: `name`, `unit`, its `transform`, and (for scene fields)
    `where`, a function of the scene that returns the field (for `eqx.tree_at`)."""

    name: str
    unit: str
    transform: Transform
    where: Callable | None = None


def _parts(sky, cls):
    return [p for p in (sky.parts if isinstance(sky, SkySum) else (sky,)) if isinstance(p, cls)]


def star_of(sky, index: int = 1) -> GaussianStar:
    """The `index`-th `GaussianStar` of a sky, counting from 1 (the source a fit moves)."""
    stars = _parts(sky, GaussianStar)
    if len(stars) < index:
        have = f"only {len(stars)}" if stars else "no"
        raise ValueError(f"the scene's sky has {have} GaussianStar, so no star {index} to fit "
                         "(add jl.GaussianStar(...))")  # fmt: skip
    return stars[index - 1]


def floor_of(sky) -> Uniform:
    """The first `Uniform` level of a sky (the floor a fit adjusts)."""
    levels = _parts(sky, Uniform)
    if not levels:
        raise ValueError("the scene's sky has no Uniform to fit (add jl.Uniform(0.0))")
    return levels[0]


# The star's parameters: `NAME` is the sky's first GaussianStar, `NAME_i` its i-th (i >= 2).
STAR = ("source_lon", "source_lat", "sigma", "brightness")
PARAMETERS = {
    p.name: p
    for p in (
        Parameter("distance", "R_S", Transform("above", 1.0), lambda s: s.camera.distance),
        Parameter("fov", "rad", Transform("between", 0.0, math.pi), lambda s: s.camera.fov),
        Parameter("yaw", "rad", FREE, lambda s: s.camera.yaw),
        Parameter("pitch", "rad", FREE, lambda s: s.camera.pitch),
        Parameter("source_lon", "rad", FREE),
        Parameter("source_lat", "rad", FREE),
        Parameter("sigma", "rad", Transform("above", 0.0), lambda s: star_of(s.sky).sigma),
        Parameter("brightness", "radiance", FREE, lambda s: star_of(s.sky).brightness),
        Parameter("floor", "radiance", FREE, lambda s: floor_of(s.sky).level),
        Parameter("psf_sigma", "px", Transform("above", 0.0)),
        Parameter("ring_flux", "", FREE),
    )
}
ANGLES = ("fov", "yaw", "pitch", "source_lon", "source_lat", "sigma")


def split_name(name: str) -> tuple[str, int]:
    """`("sigma", 2)` for `"sigma_2"`; `(name, 1)` for a name without a star index.
    Raises `ValueError` for a name that is no parameter."""
    base, sep, tail = name.rpartition("_")
    if sep and base in STAR and tail.isdigit() and int(tail) >= 2:
        return base, int(tail)
    if name in PARAMETERS:
        return name, 1
    further = ", ".join(n + "_2" for n in STAR)
    raise ValueError(f"unknown parameter {name!r}; choose from {', '.join(PARAMETERS)} "
                     f"(and {further}, ... for further stars)")  # fmt: skip


def is_angle(name: str) -> bool:
    """Whether the parameter `name` is an angle (radians; reported in degrees too)."""
    return split_name(name)[0] in ANGLES


def init_value(name: str, value):
    """A starting value (`fit`'s `init`) in its parameter's unit: an astropy Quantity
    converted (`_units`: R_S for the distance, radians for an angle, degrees for
    `fov_deg`) or, for a parameter without an astropy unit, refused with a
    `ValueError`; anything else returned as it is."""
    if not is_quantity(value):
        return value
    where = f"init[{name!r}]"
    if name == "fov_deg":
        return math.degrees(angle(value, where))
    unit = parameter(name).unit
    if unit == "R_S":
        return length(value, where)
    if unit == "rad":
        return angle(value, where)
    return plain(value, where, f"in {unit or 'no unit'}")


def parameter(name: str) -> Parameter:
    """The `Parameter` called `name`: one of `PARAMETERS`, or a star's parameter with
    the index of its `GaussianStar` in the sky (`brightness_2`: the second star's)."""
    base, i = split_name(name)
    p = PARAMETERS[base]
    if i == 1 or base in ("source_lon", "source_lat"):
        return dataclasses.replace(p, name=name)
    where = {"sigma": lambda s: star_of(s.sky, i).sigma,
             "brightness": lambda s: star_of(s.sky, i).brightness}[base]  # fmt: skip
    return dataclasses.replace(p, name=name, where=where)


def in_scene(name: str) -> bool:
    """Whether `name` is a field of the scene (else a fit's own: PSF width, ring flux)."""
    return parameter(name).where is not None or split_name(name)[0] in STAR[:2]


def _suffix(i: int) -> str:
    return "" if i == 1 else f"_{i}"


def values_of(scene) -> dict:
    """The current value of every scene parameter (host floats), each star's under its
    own names (`sigma`, `sigma_2`, ...)."""
    out = {}
    for name in ("distance", "fov", "yaw", "pitch", "floor"):
        try:
            out[name] = float(np.mean(np.asarray(PARAMETERS[name].where(scene))))
        except ValueError:
            continue
    for i, star in enumerate(_parts(scene.sky, GaussianStar), start=1):
        lon, lat = angles_from_direction(np.asarray(star.direction))
        out[f"source_lon{_suffix(i)}"], out[f"source_lat{_suffix(i)}"] = float(lon), float(lat)
        out[f"sigma{_suffix(i)}"] = float(np.mean(np.asarray(star.sigma)))
        out[f"brightness{_suffix(i)}"] = float(np.mean(np.asarray(star.brightness)))
    return out


def apply(scene, values: dict):
    """`scene` with the parameters in `values` (arrays, possibly traced) set; names
    that are no field of the scene (`psf_sigma`, `ring_flux`) are passed over."""
    dt = scene.camera.dtype
    moved = {}
    for name, v in values.items():
        base, i = split_name(name)
        if base in ("source_lon", "source_lat"):
            moved.setdefault(i, {})[base] = v
            continue
        p = parameter(name)
        if p.where is None:
            continue
        old = p.where(scene)
        if isinstance(v, jax.core.Tracer | jax.Array):
            new = jnp.broadcast_to(jnp.asarray(v, dt), jnp.shape(old)).astype(jnp.result_type(old))
        else:  # a host value: placed, not computed by eager operations
            new = to_device(np.broadcast_to(np.asarray(v, dt), np.shape(old)), jnp.result_type(old))
        scene = eqx.tree_at(p.where, scene, new)
    for i, given in moved.items():
        star = star_of(scene.sky, i)
        n, dt = star.direction, jnp.result_type(star.direction)
        host = not has_tracer(n, *given.values())
        cur = angles_from_direction(np.asarray(n) if host else n)
        lon = given.get("source_lon", cur[0])
        lat = given.get("source_lat", cur[1])
        d = direction_from_angles(lon, lat)
        d = to_device(np.asarray(d), dt) if host else d.astype(dt)
        scene = eqx.tree_at(lambda s: star_of(s.sky, i).direction, scene, d)
    return scene
