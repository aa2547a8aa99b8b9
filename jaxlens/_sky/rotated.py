"""Another sky, turned."""

from typing import ClassVar

from jaxtyping import Array, Float

from .. import _limits
from .._camera import rotate, rotation_matrix
from .._limits import radians
from ._base import AbstractSky


class Rotated(AbstractSky):
    """Another sky turned by yaw, pitch, roll (radians; `rotation_matrix`): what was
    at direction $m$ appears at $R m$; with only yaw, the sky turns toward $+x$.

    **Fields:** `sky` (any `AbstractSky`; its spectrum, if any, is kept: `shifted`
    turns the directions and asks it), `yaw`, `pitch`, `roll` (radians or astropy angles,
    finite).
    """

    sky: AbstractSky
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]
    limits: ClassVar = dict(_limits.ORIENTATION)

    def __init__(self, sky: AbstractSky, yaw=0.0, pitch=0.0, roll=0.0):
        self.sky = sky
        self.yaw, self.pitch = radians("yaw", yaw), radians("pitch", pitch)
        self.roll = radians("roll", roll)

    def __check_init__(self):
        if not isinstance(self.sky, AbstractSky):
            raise ValueError(f"sky={self.sky!r} must be a sky (an AbstractSky)")

    def _turned(self, n):
        return rotate(rotation_matrix(self.yaw, self.pitch, self.roll).T, n)

    def __call__(self, n):
        return self.sky(self._turned(n))

    def shifted(self, n, g, mode):
        return self.sky.shifted(self._turned(n), g, mode)
