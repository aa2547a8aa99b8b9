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

from .._sky import GaussianStar, SkySum, Uniform
from .._sky._base import angles_from_direction, direction_from_angles


@dataclasses.dataclass(frozen=True)
class Transform:
    """Internal (unbounded) value <-> physical value; `slope` is d physical / d internal."""

    kind: str
    lo: float = -math.inf
    hi: float = math.inf

    def forward(self, t):
        if self.kind == "above":
            return self.lo + jnp.exp(t)
        if self.kind == "between":
            return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(t)
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


def _part(sky, cls, hint: str):
    parts = sky.parts if isinstance(sky, SkySum) else (sky,)
    for p in parts:
        if isinstance(p, cls):
            return p
    raise ValueError(f"the scene's sky has no {cls.__name__} to fit (add {hint})")


def star_of(sky) -> GaussianStar:
    """The first `GaussianStar` of a sky (the source a fit moves)."""
    return _part(sky, GaussianStar, "jl.GaussianStar(...)")


def floor_of(sky) -> Uniform:
    """The first `Uniform` level of a sky (the floor a fit adjusts)."""
    return _part(sky, Uniform, "jl.Uniform(0.0)")


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


def values_of(scene) -> dict:
    """The current value of every scene parameter (host floats)."""
    out = {}
    for name, p in PARAMETERS.items():
        if p.where is not None:
            try:
                out[name] = float(jnp.mean(jnp.asarray(p.where(scene))))
            except ValueError:
                continue
    try:
        lon, lat = angles_from_direction(star_of(scene.sky).direction)
        out["source_lon"], out["source_lat"] = float(lon), float(lat)
    except ValueError:
        pass
    return out


def apply(scene, values: dict):
    """`scene` with the parameters in `values` (arrays, possibly traced) set."""
    dt = scene.camera.dtype
    for name, v in values.items():
        p = PARAMETERS[name]
        if p.where is None:
            continue
        old = p.where(scene)
        new = jnp.broadcast_to(jnp.asarray(v, dt), jnp.shape(old)).astype(jnp.asarray(old).dtype)
        scene = eqx.tree_at(p.where, scene, new)
    if "source_lon" in values or "source_lat" in values:
        cur = values_of_source(scene)
        lon = values.get("source_lon", cur[0])
        lat = values.get("source_lat", cur[1])
        d = direction_from_angles(lon, lat).astype(star_of(scene.sky).direction.dtype)
        scene = eqx.tree_at(lambda s: star_of(s.sky).direction, scene, d)
    return scene


def values_of_source(scene):
    return angles_from_direction(star_of(scene.sky).direction)
