"""A uniform sky level."""

from pathlib import Path
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _limits, _schema
from .._limits import real
from .._schema import Key, anything
from ._base import AbstractRGBSky


class Uniform(AbstractRGBSky):
    """A uniform sky level (the "floor"): linear radiance, a scalar or one per
    channel (RGB).

    **Fields:** `level`: linear radiance, shape `()`, `(1,)` or `(3,)`; finite and at
    most 1e30 in magnitude (a fitted floor may be slightly negative).
    """

    level: Float[Array, "*c"]
    limits: ClassVar = {"level": _limits.radiance()}

    def __init__(self, level: ArrayLike = 0.0):
        self.level = real("level", level)

    def __check_init__(self):
        if self.level.shape not in ((), (1,), (3,)):
            raise ValueError(f"level has shape {self.level.shape}; expected a scalar or RGB (3,)")

    def __call__(self, n):
        level = self.level.astype(n.dtype)
        return jnp.broadcast_to(level, n.shape[:-1] + (3,))


@_schema.register(
    "sky",
    "uniform",
    {"level": Key("color", 0.0, anything, "a number or a list of 3 numbers (radiance)")},
)
def _uniform(fields: dict, base: Path) -> Uniform:
    return Uniform(fields["level"])
