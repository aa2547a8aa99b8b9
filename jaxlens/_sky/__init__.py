"""Skies: what lies at infinity in each direction, one sky a module.

`_base` holds the abstract bases (`AbstractSky`, `AbstractRGBSky`,
`AbstractCompactSky`), `SkySum` and the
direction and image helpers; each other module holds one sky and registers its
scene-file table (`_schema.register("sky", ...)`), so importing this package
registers every sky type.
"""

# The import order is the order in which scene-file errors list the sky types.
# isort: off
from ._base import (
    AbstractCompactSky as AbstractCompactSky,
    AbstractRGBSky as AbstractRGBSky,
    AbstractSky as AbstractSky,
    SkySum as SkySum,
    angles_from_direction as angles_from_direction,
    angular_distance as angular_distance,
    direction_from_angles as direction_from_angles,
    to_rgb as to_rgb,
)
from .star import GaussianStar as GaussianStar
from .starfield import StarField as StarField
from .panorama import Panorama as Panorama
from .plane import PlaneImage as PlaneImage
from .checker import Checker as Checker
from .default import DefaultSky as DefaultSky
from .uniform import Uniform as Uniform
from .blackbody import BlackbodyStars as BlackbodyStars
from .rotated import Rotated as Rotated
from .equirect import equirectangular as equirectangular
from ._table import sky_from_table as sky_from_table

# isort: on
