"""The sky family's bases, its sum, and the helpers its members share.

Directions are world unit vectors (`_camera` frame: $+z$ is behind the hole, $x$ to the
right, $y$ up). Sky coordinates: longitude `lon` grows from $+z$ toward $+x$, latitude
`lat` toward $+y$ (`direction_from_angles`). Every sky is an `equinox.Module`, so its
array fields (star positions, brightness, the pixels of a panorama) can be
differentiated; skies add with `+`.

The extension points are the two abstract methods of `AbstractSky`: `__call__` (rest
radiance) and `shifted` (radiance seen with a frequency ratio). A sky without a
spectrum subclasses `AbstractRGBSky`, which implements `shifted` once for all of them.
A sky of one compact source subclasses `AbstractCompactSky` and also writes
`crossing`, which lets area-exact sampling integrate its relativistic rings.
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import _limits
from .._camera import rotate, rotation_matrix
from .._fastmath import arctan2
from .._units import angle
from .._util import concrete as _concrete, has_tracer


class AbstractSky(eqx.Module):
    """A sky: what lies at infinity in each direction.

    `sky(n)` gives the linear RGB radiance `(..., 3)` at unit vectors `n (..., 3)`, in
    their dtype; `sky.shifted(n, g, mode)` gives it as seen with the frequency ratio
    $g = \\nu_{obs}/\\nu_\\infty$. Skies add with `+` (a flat `SkySum`).

    Subclass `AbstractRGBSky` for a sky without a spectrum (only `__call__` to
    write), or this class to give the sky its own `shifted`.

    Each sky declares the valid range of its array fields in `limits` (`_limits`):
    a known value outside it is a `ValueError` when the sky is built, a traced one an
    error at run time in `render_array` (`_kernel.checked`).
    """

    limits: ClassVar[dict[str, _limits.Limit]] = {}

    def __check_init__(self):
        _limits.check_fields(self)

    @abc.abstractmethod
    def __call__(self, n: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Rest-frame linear RGB radiance `(..., 3)` at unit directions `n (..., 3)`."""

    @abc.abstractmethod
    def shifted(
        self, n: Float[Array, "... 3"], g: Float[ArrayLike, "..."], mode: str
    ) -> Float[Array, "... 3"]:
        """Radiance `(..., 3)` at unit directions `n (..., 3)` seen with frequency ratio
        `g` (dimensionless, broadcasting with `n[..., 0]`); `mode`: `"bolometric"` or
        `"spectral"`, as `Redshift`."""

    def __add__(self, other: "AbstractSky") -> "SkySum":
        if not isinstance(other, AbstractSky):
            return NotImplemented
        return SkySum((*_terms(self), *_terms(other)))


class AbstractRGBSky(AbstractSky):
    """A sky of plain RGB radiance, without a spectrum.

    Seen with frequency ratio $g$ it is scaled by $g^4$ (`"bolometric"`: colour kept)
    or by $g^3$ (`"spectral"`: a flat spectrum, $I_\\nu$ constant in each channel, and
    $I_\\nu/\\nu^3$ invariant). Subclasses write `__call__` only.
    """

    def shifted(self, n, g, mode):
        return (jnp.asarray(g, n.dtype) ** rgb_shift_power(mode))[..., None] * self(n)


def rgb_shift_power(mode: str) -> int:
    """The power of $g$ that scales a sky without a spectrum: 4 (`"bolometric"`) or 3
    (`"spectral"`, a flat spectrum)."""
    return 4 if mode == "bolometric" else 3


class AbstractCompactSky(AbstractRGBSky):
    """A sky of one compact source (angular size $\\ll$ 1 rad) of plain RGB radiance.

    Its images of order $\\ge 1$ (light that circles the hole once or more) are rings
    a small fraction of a pixel wide, hugging the shadow edge, which point samples
    alias. Area-exact sampling (`Camera(..., sampling="gauss")`) instead integrates the
    source across each such ring: for the great circle a ray family sweeps it needs the
    angle of closest approach and the integral of the radiance across it, which is
    what `crossing` gives.
    """

    @abc.abstractmethod
    def crossing(
        self, e1: Float[Array, "... 3"], e3: Float[Array, "... 3"]
    ) -> tuple[Float[Array, "..."], Float[Array, "... 3"]]:
        """The source seen along the great circles $n(\\Phi) = \\sin\\Phi\\,e_1 +
        \\cos\\Phi\\,e_3$ (`e1`, `e3` orthonormal world vectors `(..., 3)`).

        **Returns:** `(phi0, integral)`: the angle $\\Phi_0 \\in [0, 2\\pi)$ (radians)
        of the circle's closest approach to the source, and
        $\\int I(n(\\Phi))\\, d\\Phi$ across it (RGB radiance times radians,
        `(..., 3)`), in the dtype of `e1`."""


class SkySum(AbstractSky):
    """The sum of several skies (a star field over a panorama, a floor level, ...).

    **Fields:** `parts`: a non-empty tuple of skies (`a + b` flattens sums, so none of
    them is a `SkySum`).
    """

    parts: tuple[AbstractSky, ...] = eqx.field(converter=tuple)

    def __check_init__(self):
        if not self.parts or not all(isinstance(p, AbstractSky) for p in self.parts):
            raise ValueError(f"parts={self.parts!r} must be a non-empty tuple of skies")

    def __call__(self, n):
        return sum(p(n) for p in self.parts)

    def shifted(self, n, g, mode):
        return sum(p.shifted(n, g, mode) for p in self.parts)


def _terms(sky: AbstractSky) -> tuple[AbstractSky, ...]:
    return sky.parts if isinstance(sky, SkySum) else (sky,)


# ------------------------------------------------------------------ coordinates


def angular_distance(n: Float[Array, "... 3"], s: Float[ArrayLike, "3"]) -> Float[Array, "..."]:
    """Great-circle angle between unit vectors `n (..., 3)` and `s (3,)`, radians.

    `atan2(|n x s|, n . s)`: accurate at tiny and at near-antipodal separations, and
    independent of the length of `s`.
    """
    s = jnp.broadcast_to(s, n.shape)
    cx = n[..., 1] * s[..., 2] - n[..., 2] * s[..., 1]
    cy = n[..., 2] * s[..., 0] - n[..., 0] * s[..., 2]
    cz = n[..., 0] * s[..., 1] - n[..., 1] * s[..., 0]
    dot = n[..., 0] * s[..., 0] + n[..., 1] * s[..., 1] + n[..., 2] * s[..., 2]
    return arctan2(jnp.sqrt(cx * cx + cy * cy + cz * cz), dot)


def direction_from_angles(lon: ArrayLike, lat: ArrayLike) -> Float[Array, "... 3"]:
    """Unit vector at longitude `lon`, latitude `lat` (radians, or astropy angle
    Quantities); (0, 0) is $+z$, behind the hole; longitude grows toward $+x$,
    latitude toward $+y$."""
    lon, lat = angle(lon, "lon"), angle(lat, "lat")
    dtype = jnp.result_type(float, lon, lat)
    # Values known now are computed on the host: each eager jnp operation would compile.
    host = not has_tracer(lon, lat)
    xp = np if host else jnp
    lon, lat = xp.broadcast_arrays(*(xp.asarray(a, dtype) for a in (lon, lat)))
    n = xp.stack([xp.cos(lat) * xp.sin(lon), xp.sin(lat), xp.cos(lat) * xp.cos(lon)], -1)
    return jax.device_put(n) if host else n


def angles_from_direction(n: Float[Array, "... 3"]):
    """Longitude in $(-\\pi, \\pi]$ and latitude in $[-\\pi/2, \\pi/2]$ (radians) of
    directions `n (..., 3)` (inverse of `direction_from_angles`); NumPy in, NumPy out."""
    atan2, sqrt = (np.arctan2, np.sqrt) if isinstance(n, np.ndarray) else (arctan2, jnp.sqrt)
    lon = atan2(n[..., 0], n[..., 2])
    lat = atan2(n[..., 1], sqrt(n[..., 0] ** 2 + n[..., 2] ** 2))
    return lon, lat


def unrotate(n, yaw, pitch, roll):
    """Directions in the frame of a sky turned by yaw, pitch, roll (radians); identity
    (and no work) when the angles are concretely zero."""
    if all((c := _concrete(a)) is not None and np.all(c == 0) for a in (yaw, pitch, roll)):
        return n
    return rotate(rotation_matrix(yaw, pitch, roll).T, n)


# ------------------------------------------------------------------ images


def to_rgb(image: ArrayLike, *, name: str = "image") -> np.ndarray:
    """An `(H, W)` or `(H, W, C)` image as float32 RGB `(H, W, 3)`.

    Channels: 1 (grey) is repeated; 2 is grey and alpha (the grey is kept: integer
    files come with the colour already multiplied by alpha); 3 is RGB; 4 is RGBA (the
    alpha is dropped, likewise). Larger counts are refused.

    **Arguments:** `image` (linear radiance), `name` (for error messages).

    **Returns:** a C-contiguous float32 NumPy array `(H, W, 3)`.
    """
    a = np.asarray(image, np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"{name} has shape {a.shape}; expected (H, W) or (H, W, C)")
    c = a.shape[-1]
    if c in (1, 2):
        a = np.repeat(a[..., :1], 3, axis=-1)
    elif c in (3, 4):
        a = a[..., :3]
    else:
        raise ValueError(f"{name} has {c} channels; 1 (grey), 2 (grey, alpha), 3 (RGB) or 4 "
                         "(RGBA) are supported")  # fmt: skip
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite pixel values (NaN or inf)")
    return np.ascontiguousarray(a)


def bilinear(texels, j0, i0, fu, fv, dtype):
    """Bilinear blend of the texels (j0, i0), (j0, i0 + 1), (j0 + 1, i0), (j0 + 1,
    i0 + 1) of `texels (h, w, 3)` with weights `fu`, `fv` in [0, 1]; the caller
    guarantees every index is in range (padded borders)."""
    w = texels.shape[1]
    flat = texels.reshape(-1, 3)
    # Materialise the index and weights first: otherwise XLA fuses their arithmetic
    # (two arctangents) into the gather loop, once for each channel.
    base, fu, fv = jax.lax.optimization_barrier((j0 * w + i0, fu, fv))

    def tex(offset):
        return flat.at[base + offset].get(mode="promise_in_bounds").astype(dtype)

    fu, fv = fu[..., None], fv[..., None]
    top = tex(0) + fu * (tex(1) - tex(0))
    bot = tex(w) + fu * (tex(w + 1) - tex(w))
    return top + fv * (bot - top)
