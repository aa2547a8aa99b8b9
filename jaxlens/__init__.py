"""jaxlens: gravitational lensing by a Schwarzschild black hole, in JAX.

Units: the Schwarzschild radius R_S = 2GM/c^2 is 1; angles are radians.

The public names load on first use (`jaxlens.trace` imports JAX and the tracer then),
so `import jaxlens` and `jaxlens --help` do not pay for JAX, the fit's optimizer or
the notebook widgets until a name that needs them is used.
"""

import importlib

# Each public name and the private module that defines it.
_MODULES = {
    "_exact": (
        "B_CRIT",
        "CAPTURED",
        "Crossings",
        "ESCAPED",
        "PlaneCrossings",
        "R_PHOTON",
        "UNRESOLVED",
        "carlson_rf",
        "darwin_deflection",
        "impact_parameter",
        "periapsis",
        "plane_crossings",
        "radius_crossings",
        "shadow_angle",
        "strong_field_deflection",
        "weak_field_deflection",
    ),
    "_compile": ("keep_programs",),
    "_trace": (
        "RK4",
        "AbstractIntegrator",
        "AbstractMethod",
        "ButcherTableau",
        "DormandPrince",
        "Euler",
        "Exact",
        "Table",
        "trace",
    ),
    "_status": ("RayStatus", "TraceResult"),
    "_camera": (
        "Camera",
        "approach",
        "orbit",
        "pan",
        "rotation_matrix",
        "sky_direction",
        "stack_cameras",
        "zoom",
    ),
    "_color": (
        "XYZ_TO_SRGB",
        "blackbody_color",
        "blackbody_luminance",
        "blackbody_xyz_quadrature",
        "cie_cmf",
        "planck",
        "shifted_blackbody",
    ),
    "_disk": (
        "Disk",
        "DiskHits",
        "can_reach",
        "disk_angle_bound",
        "disk_redshift",
        "trace_disk",
    ),
    "_effects": (
        "AbstractMotion",
        "CircularOrbit",
        "RadialInfall",
        "Redshift",
        "aberrate",
        "aberrate_cos",
        "blackbody_rgb",
        "doppler_factor",
        "frequency_ratio",
        "infall_speed",
        "lorentz_factor",
        "orbital_speed",
        "static_blueshift",
    ),
    "_fit": (
        "DEFAULT_FREE",
        "RS_SUN_M",
        "AbstractNoise",
        "ArcGuess",
        "Fit",
        "FitsImage",
        "Gaussian",
        "Observation",
        "Poisson",
        "SourceDistance",
        "clipped_mean",
        "distance_in_metres",
        "einstein_ring_angle",
        "find_arcs",
        "fit",
        "fit_ring",
        "mass_from_distance",
        "observe",
        "offset_from_radii",
        "parse_length",
        "read_fits",
        "read_observation",
        "ring_image",
        "schwarzschild_radius_m",
        "source_offset_from_arcs",
    ),
    "_psf": (
        "AbstractPSF",
        "GaussianPSF",
        "ImagePSF",
        "convolve_psf",
        "gaussian_otf",
        "image_otf",
        "psf_margin",
    ),
    "_io": (
        "MissingExtraError",
        "read_image",
        "srgb_decode",
        "srgb_encode",
        "to_display",
        "write_gif",
        "write_image",
        "write_video",
    ),
    "_lensmap": (
        "LensedImages",
        "magnification",
        "point_lens_magnification",
        "point_source_images",
        "point_source_images_at",
    ),
    "_plan": (
        "Plan",
        "plan",
    ),
    "_raymap": ("RayMap",),
    "_render": (
        "block_memory",
        "render",
        "render_array",
        "render_frames",
        "sky_directions",
    ),
    "_scene": (
        "Scene",
        "load_scene",
        "scene_table_keys",
        "scene_table_types",
    ),
    "_schema": ("SceneKey",),
    "_shard": (
        "ray_mesh",
        "shard_map_rays",
        "trace_sharded",
    ),
    "_sky": (
        "AbstractCompactSky",
        "AbstractRGBSky",
        "AbstractSky",
        "BlackbodyStars",
        "Checker",
        "DefaultSky",
        "GaussianStar",
        "Panorama",
        "PlaneImage",
        "Rotated",
        "SkySum",
        "StarField",
        "Uniform",
        "angles_from_direction",
        "angular_distance",
        "direction_from_angles",
        "equirectangular",
        "sky_from_table",
        "to_rgb",
    ),
    "_units": ("schwarzschild_radii",),
    "_weak": ("weak_field_escape_angle",),
    "_explorer": ("Explorer",),  # needs ipywidgets (the `notebooks` extra)
}
_WHERE = {name: module for module, names in _MODULES.items() for name in names}
__all__ = sorted(_WHERE)


def _version() -> str:
    # On first use: `importlib.metadata` alone takes ~70 ms to import, a third of
    # `jaxlens --help`, and is the window in which a signal meets no handler.
    import importlib.metadata

    try:
        return importlib.metadata.version("jaxlens-bh")  # the distribution's name
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        return "0.0.0"


def __getattr__(name):
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'jaxlens' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"jaxlens.{module}"), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__) | {"__version__"})
