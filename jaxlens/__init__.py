"""jaxlens: gravitational lensing by a Schwarzschild black hole, in JAX.

Units: the Schwarzschild radius R_S = 2GM/c^2 is 1; angles are radians.
"""

import importlib.metadata

from ._exact import (
    B_CRIT as B_CRIT,
    CAPTURED as CAPTURED,
    ESCAPED as ESCAPED,
    R_PHOTON as R_PHOTON,
    UNRESOLVED as UNRESOLVED,
    carlson_rf as carlson_rf,
    darwin_deflection as darwin_deflection,
    impact_parameter as impact_parameter,
    periapsis as periapsis,
    shadow_angle as shadow_angle,
    strong_field_deflection as strong_field_deflection,
    weak_field_deflection as weak_field_deflection,
)
from ._trace import (
    RK4 as RK4,
    AbstractIntegrator as AbstractIntegrator,
    AbstractMethod as AbstractMethod,
    ButcherTableau as ButcherTableau,
    DormandPrince as DormandPrince,
    Euler as Euler,
    Exact as Exact,
    RayStatus as RayStatus,
    Table as Table,
    TraceResult as TraceResult,
    trace as trace,
)

try:
    __version__ = importlib.metadata.version("jaxlens")
except importlib.metadata.PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"

from ._camera import (
    Camera as Camera,
    approach as approach,
    orbit as orbit,
    pan as pan,
    rotation_matrix as rotation_matrix,
    sky_direction as sky_direction,
    stack_cameras as stack_cameras,
    zoom as zoom,
)
from ._color import (
    XYZ_TO_SRGB as XYZ_TO_SRGB,
    blackbody_color as blackbody_color,
    blackbody_luminance as blackbody_luminance,
    blackbody_xyz_quadrature as blackbody_xyz_quadrature,
    cie_cmf as cie_cmf,
    planck as planck,
    shifted_blackbody as shifted_blackbody,
)
from ._disk import (
    Disk as Disk,
    DiskHits as DiskHits,
    can_reach as can_reach,
    disk_angle_bound as disk_angle_bound,
    disk_redshift as disk_redshift,
    trace_disk as trace_disk,
)
from ._effects import (
    AbstractMotion as AbstractMotion,
    CircularOrbit as CircularOrbit,
    RadialInfall as RadialInfall,
    Redshift as Redshift,
    aberrate as aberrate,
    aberrate_cos as aberrate_cos,
    blackbody_rgb as blackbody_rgb,
    doppler_factor as doppler_factor,
    frequency_ratio as frequency_ratio,
    infall_speed as infall_speed,
    lorentz_factor as lorentz_factor,
    orbital_speed as orbital_speed,
    static_blueshift as static_blueshift,
)
from ._fit import (
    DEFAULT_FREE as DEFAULT_FREE,
    RS_SUN_M as RS_SUN_M,
    ArcGuess as ArcGuess,
    Fit as Fit,
    FitsImage as FitsImage,
    RingFit as RingFit,
    clipped_mean as clipped_mean,
    convolve_psf as convolve_psf,
    distance_in_metres as distance_in_metres,
    einstein_ring_angle as einstein_ring_angle,
    find_arcs as find_arcs,
    fit as fit,
    fit_ring as fit_ring,
    gaussian_otf as gaussian_otf,
    image_otf as image_otf,
    mass_from_distance as mass_from_distance,
    offset_from_radii as offset_from_radii,
    psf_margin as psf_margin,
    read_fits as read_fits,
    read_observation as read_observation,
    ring_image as ring_image,
    schwarzschild_radius_m as schwarzschild_radius_m,
    source_offset_from_arcs as source_offset_from_arcs,
)
from ._io import (
    MissingExtraError as MissingExtraError,
    read_image as read_image,
    srgb_decode as srgb_decode,
    srgb_encode as srgb_encode,
    to_display as to_display,
    write_gif as write_gif,
    write_image as write_image,
    write_video as write_video,
)
from ._lensmap import (
    magnification as magnification,
    point_lens_magnification as point_lens_magnification,
    point_source_images as point_source_images,
)
from ._plan import Plan as Plan, plan as plan
from ._raymap import RayMap as RayMap
from ._render import (
    block_memory as block_memory,
    render as render,
    render_array as render_array,
    render_frames as render_frames,
    sky_directions as sky_directions,
)
from ._scene import Scene as Scene, load_scene as load_scene
from ._schema import (
    SceneKey as SceneKey,
    scene_table_keys as scene_table_keys,
    scene_table_types as scene_table_types,
)
from ._shard import (
    ray_mesh as ray_mesh,
    shard_map_rays as shard_map_rays,
    trace_sharded as trace_sharded,
)
from ._sky import (
    AbstractCompactSky as AbstractCompactSky,
    AbstractRGBSky as AbstractRGBSky,
    AbstractSky as AbstractSky,
    BlackbodyStars as BlackbodyStars,
    Checker as Checker,
    DefaultSky as DefaultSky,
    GaussianStar as GaussianStar,
    Panorama as Panorama,
    PlaneImage as PlaneImage,
    Rotated as Rotated,
    SkySum as SkySum,
    StarField as StarField,
    Uniform as Uniform,
    angles_from_direction as angles_from_direction,
    angular_distance as angular_distance,
    direction_from_angles as direction_from_angles,
    equirectangular as equirectangular,
    sky_from_table as sky_from_table,
    to_rgb as to_rgb,
)
from ._weak import weak_field_escape_angle as weak_field_escape_angle


def __getattr__(name):
    # The notebook explorer needs ipywidgets (the `notebooks` extra): imported lazily.
    if name == "Explorer":
        from ._explorer import Explorer

        return Explorer
    raise AttributeError(f"module 'jaxlens' has no attribute {name!r}")
