"""jaxlens: gravitational lensing by a Schwarzschild black hole, in JAX.

Units: the Schwarzschild radius R_S = 2GM/c^2 is 1; angles are radians.
"""

import importlib.metadata

from ._exact import (
    B_CRIT as B_CRIT,
)
from ._exact import (
    CAPTURED as CAPTURED,
)
from ._exact import (
    ESCAPED as ESCAPED,
)
from ._exact import (
    R_PHOTON as R_PHOTON,
)
from ._exact import (
    UNRESOLVED as UNRESOLVED,
)
from ._exact import (
    carlson_rf as carlson_rf,
)
from ._exact import (
    darwin_deflection as darwin_deflection,
)
from ._exact import (
    impact_parameter as impact_parameter,
)
from ._exact import (
    periapsis as periapsis,
)
from ._exact import (
    shadow_angle as shadow_angle,
)
from ._exact import (
    strong_field_deflection as strong_field_deflection,
)
from ._exact import (
    weak_field_deflection as weak_field_deflection,
)
from ._trace import (
    RK4 as RK4,
)
from ._trace import (
    AbstractMethod as AbstractMethod,
)
from ._trace import (
    DormandPrince as DormandPrince,
)
from ._trace import (
    Euler as Euler,
)
from ._trace import (
    Exact as Exact,
)
from ._trace import (
    Table as Table,
)
from ._trace import (
    TraceResult as TraceResult,
)
from ._trace import (
    trace as trace,
)

try:
    __version__ = importlib.metadata.version("jaxlens")
except importlib.metadata.PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"

from ._camera import (
    Camera as Camera,
)
from ._camera import (
    approach as approach,
)
from ._camera import (
    orbit as orbit,
)
from ._camera import (
    pan as pan,
)
from ._camera import (
    rotation_matrix as rotation_matrix,
)
from ._camera import (
    sky_direction as sky_direction,
)
from ._camera import (
    stack_cameras as stack_cameras,
)
from ._camera import (
    zoom as zoom,
)
from ._compose import (
    EffectScene as EffectScene,
)
from ._compose import (
    Plan as Plan,
)
from ._compose import (
    load_effect_scene as load_effect_scene,
)
from ._compose import (
    plan as plan,
)
from ._compose import (
    render_scene as render_scene,
)
from ._compose import (
    render_scene_array as render_scene_array,
)
from ._disk import Disk as Disk
from ._disk import trace_disk as trace_disk
from ._effects import (
    BlackbodyStars as BlackbodyStars,
)
from ._effects import (
    CircularOrbit as CircularOrbit,
)
from ._effects import (
    RadialInfall as RadialInfall,
)
from ._effects import (
    Redshift as Redshift,
)
from ._effects import (
    aberrate as aberrate,
)
from ._effects import (
    blackbody_rgb as blackbody_rgb,
)
from ._effects import (
    doppler_factor as doppler_factor,
)
from ._effects import (
    frequency_ratio as frequency_ratio,
)
from ._effects import (
    static_blueshift as static_blueshift,
)
from ._fit import RS_SUN_M as RS_SUN_M
from ._fit import EscapeTable as EscapeTable
from ._fit import RingFit as RingFit
from ._fit import distance_in_metres as distance_in_metres
from ._fit import einstein_ring_angle as einstein_ring_angle
from ._fit import fit_ring as fit_ring
from ._fit import mass_from_distance as mass_from_distance
from ._fit import read_observation as read_observation
from ._fit import ring_image as ring_image
from ._fit import schwarzschild_radius_m as schwarzschild_radius_m
from ._io import (
    read_image as read_image,
)
from ._io import (
    to_display as to_display,
)
from ._io import (
    write_gif as write_gif,
)
from ._io import (
    write_image as write_image,
)
from ._io import (
    write_video as write_video,
)
from ._lensmap import (
    magnification as magnification,
)
from ._lensmap import (
    point_lens_magnification as point_lens_magnification,
)
from ._lensmap import (
    point_source_images as point_source_images,
)
from ._raymap import RayMap as RayMap
from ._render import (
    block_memory as block_memory,
)
from ._render import (
    plan_blocks as plan_blocks,
)
from ._render import (
    render as render,
)
from ._render import (
    render_array as render_array,
)
from ._render import (
    render_frames as render_frames,
)
from ._render import (
    shade as shade,
)
from ._render import (
    sky_directions as sky_directions,
)
from ._scene import Scene as Scene
from ._scene import load_scene as load_scene
from ._shard import ray_mesh as ray_mesh
from ._shard import shard_map_rays as shard_map_rays
from ._shard import trace_sharded as trace_sharded
from ._sky import (
    AbstractSky as AbstractSky,
)
from ._sky import (
    Checker as Checker,
)
from ._sky import (
    DefaultSky as DefaultSky,
)
from ._sky import (
    GaussianStar as GaussianStar,
)
from ._sky import (
    Panorama as Panorama,
)
from ._sky import (
    PlaneImage as PlaneImage,
)
from ._sky import (
    Rotated as Rotated,
)
from ._sky import (
    SkySum as SkySum,
)
from ._sky import (
    StarField as StarField,
)
from ._sky import (
    Uniform as Uniform,
)
from ._sky import (
    angles_from_direction as angles_from_direction,
)
from ._sky import (
    angular_distance as angular_distance,
)
from ._sky import (
    direction_from_angles as direction_from_angles,
)
from ._sky import (
    equirectangular as equirectangular,
)


def __getattr__(name):
    # The notebook explorer needs ipywidgets (the `notebooks` extra): imported lazily.
    if name == "Explorer":
        from ._explorer import Explorer

        return Explorer
    raise AttributeError(f"module 'jaxlens' has no attribute {name!r}")
