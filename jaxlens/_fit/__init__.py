"""Fit the black hole to an observed Einstein ring: autodiff of a forward model, optimistix.

The observation model: a static pinhole camera at distance $D$ (units of R_S) looks
straight at the hole with horizontal field of view FOV; one star sits exactly behind
the hole at infinity, Gaussian in angular distance $d$ on the sky,
$I = A e^{-d^2 / 2\\sigma^2}$; a uniform sky level `floor` lies behind everything;
captured rays are 0; pixels are area-averaged; the noise is additive.

The model image is the renderer's, with area-exact sampling (`Camera(...,
sampling="gauss")`, the kernel's `cells`): the escape angle comes from the ray map of
the distance (`escape_table`, a `RayMap`, differentiable with respect to $D$),
Gauss-Legendre cells that straddle the shadow edge are weighted by the exact fraction
of their footprint outside the (locally straight) edge, so the edge contributes
gradient with respect to $D$ and FOV, and the relativistic rings enter by their
integrated flux. `optimistix.least_squares`
with Levenberg-Marquardt then solves for $\\log(D - 1.5)$,
$\\operatorname{logit}(\\mathrm{FOV}/\\pi)$, $\\log\\sigma$, $A$, the floor and the
relativistic rings' flux factor; standard errors come from the Gauss-Newton curvature
$J^T J$ and the residual variance.
"""

from .arcs import (
    ArcGuess as ArcGuess,
    find_arcs as find_arcs,
    offset_from_radii as offset_from_radii,
    source_offset_from_arcs as source_offset_from_arcs,
)
from .fit_result import Fit as Fit
from .fits import FitsImage as FitsImage, read_fits as read_fits
from .general import DEFAULT_FREE as DEFAULT_FREE, fit as fit
from .model import ring_image as ring_image
from .noise import (
    AbstractNoise as AbstractNoise,
    Gaussian as Gaussian,
    Poisson as Poisson,
    clipped_mean as clipped_mean,
)
from .observation import (
    Observation as Observation,
    observe as observe,
    read_observation as read_observation,
)
from .params import PARAMETERS as PARAMETERS
from .ring import fit_ring as fit_ring
from .source import SourceDistance as SourceDistance
from .table import einstein_ring_angle as einstein_ring_angle, escape_table as escape_table
from .units import (
    C_LIGHT as C_LIGHT,
    GM_SUN as GM_SUN,
    RS_SUN_M as RS_SUN_M,
    distance_in_metres as distance_in_metres,
    mass_from_distance as mass_from_distance,
    parse_length as parse_length,
    schwarzschild_radius_m as schwarzschild_radius_m,
)
