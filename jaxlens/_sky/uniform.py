"""A uniform sky level."""

from pathlib import Path

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _schema
from .._schema import Key, anything
from .._util import as_float as _farray
from ._base import AbstractRGBSky, finite


class Uniform(AbstractRGBSky):
    """A uniform sky level (the "floor"): linear radiance, a scalar or one per
    channel (RGB).

    **Fields:** `level`: linear radiance, shape `()`, `(1,)` or `(3,)`.
    """

    level: Float[Array, "*c"]

    def __init__(self, level: ArrayLike = 0.0):
        self.level = _farray(level)

    def __check_init__(self):
        finite("level", self.level, "linear radiance")
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
