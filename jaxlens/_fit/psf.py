"""The fit's point-spread functions, from `jaxlens._psf` (which the renderer shares)."""

from .._psf import (
    _gaussian_otf as _gaussian_otf,
    convolve_psf as convolve_psf,
    gaussian_otf as gaussian_otf,
    image_otf as image_otf,
    psf_margin as psf_margin,
)
