"""Skies: what lies at infinity in each direction. Each maps unit vectors to RGB radiance.

Directions are world unit vectors (`_camera` frame: $+z$ is behind the hole, $x$ to the
right, $y$ up). Sky coordinates: longitude `lon` grows from $+z$ toward $+x$, latitude
`lat` toward $+y$ (`direction_from_angles`). Every sky is an `equinox.Module`, so its
array fields (star positions, brightness, the pixels of a panorama) can be
differentiated; skies add with `+`.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._camera import rotate, rotation_matrix
from ._fastmath import arctan2
from ._util import as_float as _farray, concrete as _concrete


class AbstractSky(eqx.Module):
    """A sky: `sky(directions)` gives linear RGB radiance of shape `(..., 3)` for unit
    vectors `directions (..., 3)`, in their dtype."""

    def __call__(self, n: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        raise NotImplementedError

    def __add__(self, other: "AbstractSky") -> "SkySum":
        if not isinstance(other, AbstractSky):
            return NotImplemented
        return SkySum((self, other))


class SkySum(AbstractSky):
    """The sum of several skies (a star field over a panorama, a floor level, ...)."""

    parts: tuple

    def __call__(self, n):
        return sum(p(n) for p in self.parts)

    def __add__(self, other):
        if not isinstance(other, AbstractSky):
            return NotImplemented
        return SkySum((*self.parts, other))


# ------------------------------------------------------------------ coordinates


def angular_distance(n, s):
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


def direction_from_angles(lon, lat):
    """Unit vector at longitude `lon`, latitude `lat` (radians); (0, 0) is $+z$,
    behind the hole; longitude grows toward $+x$, latitude toward $+y$."""
    lon, lat = jnp.broadcast_arrays(
        *(jnp.asarray(a, jnp.result_type(float, lon, lat)) for a in (lon, lat))
    )
    return jnp.stack([jnp.cos(lat) * jnp.sin(lon), jnp.sin(lat), jnp.cos(lat) * jnp.cos(lon)], -1)


def angles_from_direction(n):
    """Longitude in $(-\\pi, \\pi]$ and latitude in $[-\\pi/2, \\pi/2]$ (radians) of
    directions `n (..., 3)` (inverse of `direction_from_angles`)."""
    lon = arctan2(n[..., 0], n[..., 2])
    lat = arctan2(n[..., 1], jnp.sqrt(n[..., 0] ** 2 + n[..., 2] ** 2))
    return lon, lat


def _positive(name, value, unit):
    v = _concrete(value)
    if v is not None and not np.all(np.isfinite(v) & (v > 0)):
        raise ValueError(f"{name}={v.tolist()!r} must be finite and > 0 ({unit})")


def _finite(name, value, unit):
    v = _concrete(value)
    if v is not None and not np.all(np.isfinite(v)):
        raise ValueError(f"{name}={v.tolist()!r} must be finite ({unit})")


# ------------------------------------------------------------------ simple skies


class Uniform(AbstractSky):
    """A uniform sky level (the "floor"): linear radiance, a scalar or one per
    channel (RGB)."""

    level: Float[Array, "*c"]

    def __init__(self, level: ArrayLike = 0.0):
        self.level = _farray(level)

    def __check_init__(self):
        _finite("level", self.level, "linear radiance")
        if self.level.shape not in ((), (1,), (3,)):
            raise ValueError(f"level has shape {self.level.shape}; expected a scalar or RGB (3,)")

    def __call__(self, n):
        level = self.level.astype(n.dtype)
        return jnp.broadcast_to(level, n.shape[:-1] + (3,))


class GaussianStar(AbstractSky):
    """A star of Gaussian profile in angular distance $d$: $I = A e^{-d^2 / 2\\sigma^2}$.

    **Fields:** `sigma` (radians, standard deviation in great-circle angle),
    `brightness` $A$ (peak radiance), `direction` (3-vector, need not be unit
    length; default $+z$, exactly behind the hole), `color` (RGB weights).

    Give the position either as `direction` or as `lon`, `lat` (radians; see
    `direction_from_angles`).
    """

    sigma: Float[Array, ""]
    brightness: Float[Array, ""]
    direction: Float[Array, "3"]
    color: Float[Array, "3"]

    def __init__(
        self,
        sigma: ArrayLike,
        brightness: ArrayLike = 1.0,
        direction: ArrayLike | None = None,
        color: ArrayLike = (1.0, 1.0, 1.0),
        *,
        lon: ArrayLike | None = None,
        lat: ArrayLike | None = None,
    ):
        _positive("sigma", sigma, "radians")
        self.sigma = _farray(sigma)
        self.brightness = _farray(brightness)
        if lon is not None or lat is not None:
            if direction is not None:
                raise ValueError("give the star position as direction or as lon/lat, not both")
            d = direction_from_angles(0.0 if lon is None else lon, 0.0 if lat is None else lat)
        else:
            d = _farray((0.0, 0.0, 1.0) if direction is None else direction)
            c = _concrete(d)
            if c is not None and (c.shape != (3,) or not np.all(np.isfinite(c)) or not c.any()):
                raise ValueError(f"direction={c.tolist()!r} must be a finite non-zero 3-vector")
            d = d / jnp.linalg.norm(d)
        self.direction = d
        self.color = _farray(color)

    def __check_init__(self):
        _finite("brightness", self.brightness, "linear radiance")

    def __call__(self, n):
        dt = n.dtype
        d = angular_distance(n, self.direction.astype(dt))
        i = self.brightness.astype(dt) * jnp.exp(-0.5 * (d / self.sigma.astype(dt)) ** 2)
        return i[..., None] * self.color.astype(dt)


class StarField(AbstractSky):
    """Many Gaussian stars, summed; vectorised over stars and directions.

    Each direction is compared with every star (blocks of `block` stars at a time,
    through `lax.scan`, so memory is `block` x the number of directions): use it for
    up to a few hundred stars. The procedural `DefaultSky` holds millions.

    **Fields:** `directions (N, 3)` (unit vectors), `sigma (N,)` (radians),
    `brightness (N,)` (peak radiance), `color (N, 3)`; `block` (static).
    """

    directions: Float[Array, "N 3"]
    sigma: Float[Array, " N"]
    brightness: Float[Array, " N"]
    color: Float[Array, "N 3"]
    block: int = eqx.field(static=True)

    def __init__(
        self,
        directions: ArrayLike,
        sigma: ArrayLike,
        brightness: ArrayLike = 1.0,
        color: ArrayLike = (1.0, 1.0, 1.0),
        *,
        block: int = 16,
    ):
        d = _farray(directions)
        if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
            raise ValueError(f"directions has shape {d.shape}; expected (N, 3) with N >= 1")
        n = d.shape[0]
        _positive("sigma", sigma, "radians")
        self.directions = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        self.sigma = jnp.broadcast_to(_farray(sigma), (n,))
        self.brightness = jnp.broadcast_to(_farray(brightness), (n,))
        self.color = jnp.broadcast_to(_farray(color), (n, 3))
        self.block = int(block)

    @classmethod
    def from_angles(cls, lon, lat, sigma, brightness=1.0, color=(1.0, 1.0, 1.0)) -> "StarField":
        """Stars at longitudes `lon`, latitudes `lat` (radians, 1-D arrays)."""
        d = direction_from_angles(jnp.atleast_1d(lon), jnp.atleast_1d(lat))
        return cls(d, sigma, brightness, color)

    @classmethod
    def random(cls, count: int, *, seed: int = 0, sigma=0.003, brightness=(0.05, 2.0)):
        """`count` stars uniform on the sphere, brightness log-uniform in the range
        `brightness`, colours from blue-white to orange; `sigma` in radians."""
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(count, 3))
        lo, hi = brightness
        b = np.exp(rng.uniform(np.log(lo), np.log(hi), count))
        t = rng.uniform(0, 1, count)[:, None]
        color = np.concatenate([0.8 + 0.4 * t, 0.9 + 0.1 * t, 1.2 - 0.5 * t], axis=1)
        return cls(d, sigma, b, color)

    def __call__(self, n):
        dt = n.dtype
        shape = n.shape[:-1]
        flat = n.reshape(-1, 3)
        k = self.directions.shape[0]
        nb = -(-k // self.block)
        pad = nb * self.block - k

        def padded(a, value):
            return jnp.concatenate([a.astype(dt), jnp.full((pad,) + a.shape[1:], value, dt)])

        s = padded(self.directions, 0.0)
        s = s.at[k:, 2].set(1.0)
        # Tangent basis (e1, e2, s) of each star: d = atan2(|(n.e1, n.e2)|, n.s) exactly.
        helper = jnp.where(
            jnp.abs(s[:, :1]) < 0.9, jnp.array([1.0, 0, 0], dt), jnp.array([0, 1.0, 0], dt)
        )
        e1 = jnp.cross(s, helper)
        e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
        e2 = jnp.cross(s, e1)
        basis = jnp.stack([e1, e2, s], axis=1).reshape(nb, self.block * 3, 3)
        inv2s2 = (0.5 / padded(self.sigma, 1.0) ** 2).reshape(nb, self.block)
        amp = padded(self.brightness, 0.0).reshape(nb, self.block)
        col = padded(self.color, 0.0).reshape(nb, self.block, 3)

        def step(acc, blk):
            b, w, a, c = blk
            p = (flat @ b.T).reshape(-1, self.block, 3)
            d = arctan2(jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2), p[..., 2])
            i = a * jnp.exp(-(d * d) * w)
            return acc + i @ c, None

        acc, _ = jax.lax.scan(step, jnp.zeros((flat.shape[0], 3), dt), (basis, inv2s2, amp, col))
        return acc.reshape(shape + (3,))


class Rotated(AbstractSky):
    """Another sky turned by yaw, pitch, roll (radians; `rotation_matrix`): what was
    at direction $m$ appears at $R m$; with only yaw, the sky turns toward $+x$."""

    sky: AbstractSky
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]

    def __init__(self, sky: AbstractSky, yaw=0.0, pitch=0.0, roll=0.0):
        self.sky = sky
        self.yaw, self.pitch, self.roll = _farray(yaw), _farray(pitch), _farray(roll)

    def __call__(self, n):
        r = rotation_matrix(self.yaw, self.pitch, self.roll)
        return self.sky(rotate(r.T, n))


def _unrotate(n, yaw, pitch, roll):
    """Directions in the frame of a sky turned by yaw, pitch, roll; identity (and no
    work) when the angles are concretely zero."""
    if all((c := _concrete(a)) is not None and np.all(c == 0) for a in (yaw, pitch, roll)):
        return n
    return rotate(rotation_matrix(yaw, pitch, roll).T, n)


# ------------------------------------------------------------------ images


def to_rgb(image: ArrayLike, *, name: str = "image") -> np.ndarray:
    """An `(H, W)` or `(H, W, C)` image as float32 RGB `(H, W, 3)`.

    Channels: 1 (grey) is repeated; 2 is grey and alpha (the grey is kept: integer
    files come with the colour already multiplied by alpha); 3 is RGB; 4 is RGBA (the
    alpha is dropped, likewise). Larger counts are refused.
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


def _bilinear(texels, j0, i0, fu, fv, dtype):
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


def _panorama_texels(image):
    """The texels a `Panorama` samples: the image with its first column repeated
    after the last (the seam) and a row of the first (last) row's mean above (below)
    it, which the look-up places at the north (south) pole."""
    north = jnp.broadcast_to(jnp.mean(image[:1], axis=1, keepdims=True), (1,) + image.shape[1:])
    south = jnp.broadcast_to(jnp.mean(image[-1:], axis=1, keepdims=True), (1,) + image.shape[1:])
    rows = jnp.concatenate([north, image, south], axis=0)
    return jnp.concatenate([rows, rows[:, :1]], axis=1)


class Panorama(AbstractSky):
    """An equirectangular (longitude-latitude) panorama covering the whole sky.

    Pixel (column $i$, row $j$) of a $w \\times h$ image is centred at longitude
    $2\\pi (i + 1/2)/w - \\pi$ and latitude $\\pi/2 - \\pi (j + 1/2)/h$: the image
    centre is $+z$ (behind the hole), the left and right edges meet at longitude
    $\\pm\\pi$ (in front of the camera), the top row is next to the north pole $+y$.
    Sampled bilinearly; the columns wrap, so the $\\pm\\pi$ seam is seamless; between
    the first (last) row's centre and the pole the value blends linearly in latitude
    into the mean of that row, so the pole has one value and no pinch.

    **Fields:** `texels (h + 2, w + 1, 3)`: the image in linear radiance, framed for
    the look-up (`image` gives it back); `brightness` (scale), `yaw`, `pitch`, `roll`
    (radians: the panorama's orientation, the old programs' "offset"; see `Rotated`).
    """

    texels: Float[Array, "h2 w1 3"]
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]

    def __init__(self, image: ArrayLike, *, brightness=1.0, yaw=0.0, pitch=0.0, roll=0.0):
        """**Arguments:** `image`: `(h, w)` or `(h, w, 1..4)` linear radiance (see
        `to_rgb`); the other fields as above."""
        if not isinstance(image, jax.core.Tracer):
            image = jnp.asarray(to_rgb(image, name="panorama image"))
        self.texels = _panorama_texels(image)
        self.brightness = _farray(brightness)
        self.yaw, self.pitch, self.roll = _farray(yaw), _farray(pitch), _farray(roll)

    def __check_init__(self):
        for name in ("brightness", "yaw", "pitch", "roll"):
            _finite(name, getattr(self, name), "radians" if name != "brightness" else "scale")

    @property
    def image(self) -> Float[Array, "h w 3"]:
        """The panorama image `(h, w, 3)`."""
        return self.texels[1:-1, :-1]

    @classmethod
    def from_file(cls, path, **kwargs) -> "Panorama":
        """Read an equirectangular image with OpenImageIO (PNG, JPEG, EXR, HDR, ...;
        8- and 16-bit files are converted from sRGB to linear)."""
        from ._io import read_image

        return cls(to_rgb(read_image(path), name=f"panorama {str(path)!r}"), **kwargs)

    def __call__(self, n):
        dt = n.dtype
        n = _unrotate(n, self.yaw, self.pitch, self.roll)
        h, w = self.texels.shape[0] - 2, self.texels.shape[1] - 1
        lon, lat = angles_from_direction(n)
        u = (lon * (0.5 / math.pi) + 0.5) * w - 0.5  # in [-0.5, w - 0.5]
        v = (0.5 - lat * (1.0 / math.pi)) * h - 0.5  # in [-0.5, h - 0.5]
        u0 = jnp.floor(u)
        i0 = u0.astype(jnp.int32)
        i0 = jnp.where(i0 < 0, w - 1, i0)  # the columns wrap: no seam at lon = +-pi
        fu = u - u0
        # Rows: texel row r + 1 holds image row r; rows 0 and h + 1 hold the poles,
        # half a row beyond the first and last row centres.
        interior = jnp.clip(jnp.floor(v).astype(jnp.int32) + 1, 1, max(h - 1, 1))
        j0 = jnp.where(v < 0, 0, jnp.where(v > h - 1, h, interior))
        fv = jnp.where(
            v < 0,
            2.0 * v + 1.0,
            jnp.where(v > h - 1, 2.0 * (v - (h - 1)), v - (interior - 1).astype(dt)),
        )
        val = _bilinear(self.texels, j0, i0, fu, jnp.clip(fv, 0.0, 1.0), dt)
        return self.brightness.astype(dt) * val


class PlaneImage(AbstractSky):
    """A flat picture behind the hole: an image of angular width `width` centred on
    $+z$, in gnomonic (pinhole) projection, zero outside it.

    A picture of physical width $S$ on a plane at distance $L$ behind the hole (the
    original C++ program's background) is `PlaneImage.at_distance(image, S, L)`:
    width $= 2\\arctan(S / 2L)$; this takes each ray's asymptote through the hole's
    centre, exact when $L$ is large against the rays' impact parameters.

    **Fields:** `image (h, w, 3)` linear radiance, `width` (radians, full horizontal
    angle, in $(0, \\pi)$), `brightness`, `yaw`, `pitch`, `roll` (radians, as
    `Rotated`).
    """

    image: Float[Array, "h w 3"]
    width: Float[Array, ""]
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]

    def __init__(self, image, width, *, brightness=1.0, yaw=0.0, pitch=0.0, roll=0.0):
        if isinstance(image, jax.core.Tracer):
            self.image = image
        else:
            self.image = jnp.asarray(to_rgb(image, name="plane image"))
        self.width = _farray(width)
        self.brightness = _farray(brightness)
        self.yaw, self.pitch, self.roll = _farray(yaw), _farray(pitch), _farray(roll)

    def __check_init__(self):
        wv = _concrete(self.width)
        if wv is not None and not np.all(np.isfinite(wv) & (wv > 0) & (wv < math.pi)):
            raise ValueError(
                f"width={np.degrees(wv).tolist()!r} degrees must be in (0, 180) degrees"
            )

    @classmethod
    def at_distance(cls, image, size, distance, **kwargs) -> "PlaneImage":
        """A picture `size` wide (units of R_S) on a plane `distance` behind the hole
        (units of R_S)."""
        if not (size > 0 and distance > 0):
            raise ValueError(f"size={size!r} and distance={distance!r} must be > 0 (R_S)")
        return cls(image, 2.0 * math.atan(0.5 * size / distance), **kwargs)

    @classmethod
    def from_file(cls, path, width, **kwargs) -> "PlaneImage":
        """Read the picture with OpenImageIO; `width` in radians."""
        from ._io import read_image

        return cls(to_rgb(read_image(path), name=f"plane image {str(path)!r}"), width, **kwargs)

    def __call__(self, n):
        dt = n.dtype
        n = _unrotate(n, self.yaw, self.pitch, self.roll)
        h, w = self.image.shape[:2]
        front = n[..., 2] > 0
        nz = jnp.where(front, n[..., 2], 1.0)
        scale = (0.5 * w) / jnp.tan(0.5 * self.width.astype(dt))  # pixels per unit tangent
        u = n[..., 0] / nz * scale + (0.5 * w - 0.5)
        v = (0.5 * h - 0.5) - n[..., 1] / nz * scale
        # Bilinear with zero texels outside: a one-texel fade at the border. The
        # image is sampled with a one-texel zero frame, so every index is in range.
        framed = jnp.pad(self.image, ((1, 1), (1, 1), (0, 0)))
        u = jnp.clip(u + 1.0, 0.0, w + 1.0)
        v = jnp.clip(v + 1.0, 0.0, h + 1.0)
        u0 = jnp.minimum(jnp.floor(u), w)
        v0 = jnp.minimum(jnp.floor(v), h)
        i0, j0 = u0.astype(jnp.int32), v0.astype(jnp.int32)
        val = _bilinear(framed, j0, i0, u - u0, v - v0, dt)
        return self.brightness.astype(dt) * jnp.where(front[..., None], val, 0.0)


class Checker(AbstractSky):
    """A diagnostic checkerboard sphere: `n_lon` x `n_lat` squares in longitude and
    latitude, tinted by quadrant of longitude (red around $+z$ behind the hole, then
    green toward $+x$, blue in front, yellow toward $-x$), dark and light squares
    alternating, with thin white lines on the equator and the prime meridian.

    **Fields:** `n_lon`, `n_lat` (static, squares around and pole to pole),
    `brightness`, `yaw`, `pitch`, `roll` (radians, as `Rotated`).
    """

    n_lon: int = eqx.field(static=True)
    n_lat: int = eqx.field(static=True)
    brightness: Float[Array, ""]
    yaw: Float[Array, ""]
    pitch: Float[Array, ""]
    roll: Float[Array, ""]

    def __init__(self, n_lon: int = 24, n_lat: int = 12, *, brightness=1.0, yaw=0.0, pitch=0.0,
                 roll=0.0):  # fmt: skip
        self.n_lon, self.n_lat = int(n_lon), int(n_lat)
        self.brightness = _farray(brightness)
        self.yaw, self.pitch, self.roll = _farray(yaw), _farray(pitch), _farray(roll)

    def __check_init__(self):
        if self.n_lon < 1 or self.n_lat < 1:
            raise ValueError(f"n_lon={self.n_lon}, n_lat={self.n_lat} must be >= 1")

    def __call__(self, n):
        dt = n.dtype
        n = _unrotate(n, self.yaw, self.pitch, self.roll)
        lon, lat = angles_from_direction(n)
        a = (lon + math.pi) * (self.n_lon / (2.0 * math.pi))
        b = (lat + 0.5 * math.pi) * (self.n_lat / math.pi)
        parity = (jnp.floor(a) + jnp.floor(b)) % 2.0
        # Quadrant of longitude: 0 around +z (behind the hole), 1 around +x, 2 in front
        # (lon = +-pi), 3 around -x.
        quadrant = jnp.floor((lon + 0.25 * math.pi) / (0.5 * math.pi)).astype(jnp.int32) % 4
        palette = jnp.asarray(
            [[1.0, 0.25, 0.2], [0.3, 1.0, 0.3], [0.25, 0.35, 1.0], [1.0, 0.9, 0.25]], dt
        )
        tint = palette[quadrant]
        level = (0.25 + 0.75 * parity)[..., None]
        line = (jnp.abs(lat) < 0.004) | (jnp.abs(lon) < 0.004)
        out = jnp.where(line[..., None], jnp.ones(3, dt), level * tint)
        return self.brightness.astype(dt) * out


# ------------------------------------------------------------------ procedural sky


def _hash(i, j, k, salt):
    """A 32-bit integer hash (lowbias32) of lattice indices -> [0, 1): deterministic,
    the same on every backend."""
    h = (
        i.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)
        ^ j.astype(jnp.uint32) * jnp.uint32(0xD8163841)
        ^ k.astype(jnp.uint32) * jnp.uint32(0xCB1AB31F)
        ^ jnp.asarray(salt).astype(jnp.uint32)
    )
    h ^= h >> 16
    h *= jnp.uint32(0x7FEB352D)
    h ^= h >> 15
    h *= jnp.uint32(0x846CA68B)
    h ^= h >> 16
    return (h >> 8).astype(jnp.float32) * (1.0 / 16777216.0)


def _value_noise(p, salt):
    """Smooth 3-D value noise in [0, 1] at points `p (..., 3)` (lattice spacing 1)."""
    c = jnp.floor(p)
    f = p - c
    f = f * f * (3.0 - 2.0 * f)
    ci = c.astype(jnp.int32)
    x, y, z = ci[..., 0], ci[..., 1], ci[..., 2]
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]

    def lerp(a, b, t):
        return a + t * (b - a)

    def corner(dx, dy, dz):
        return _hash(x + dx, y + dy, z + dz, salt).astype(p.dtype)

    x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), fx)
    x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), fx)
    x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), fx)
    x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), fx)
    return lerp(lerp(x00, x10, fy), lerp(x01, x11, fy), fz)


def _fbm(p, octaves, salt):
    """Fractal sum of value noise, normalised to [0, 1]. A `fori_loop` over the
    octaves keeps the compiled program small."""

    def octave(o, total):
        scale = (2.0 ** o.astype(p.dtype)).astype(p.dtype)
        amp = (0.5 ** o.astype(p.dtype)).astype(p.dtype)
        return total + amp * _value_noise(p * scale + 17.0 * o.astype(p.dtype), salt + 7919 * o)

    total = jax.lax.fori_loop(0, octaves, octave, jnp.zeros(p.shape[:-1], p.dtype))
    return total * (1.0 / (2.0 - 2.0 ** (1 - octaves)))


def _cube_cells(n, cells):
    """Cube-map cell of each direction: face (0..5), cell indices and the position
    inside the face in cell units."""
    a = jnp.abs(n)
    axis = jnp.argmax(a, axis=-1)
    major = jnp.take_along_axis(n, axis[..., None], -1)[..., 0]
    face = axis * 2 + (major < 0)
    ua = jnp.where(axis == 0, n[..., 1], n[..., 0])
    va = jnp.where(axis == 2, n[..., 1], n[..., 2])
    u = (ua / jnp.abs(major) + 1.0) * (0.5 * cells)
    v = (va / jnp.abs(major) + 1.0) * (0.5 * cells)
    return face, u, v


def _star_layer(n, cells, size, fraction, faint, bright, density, salt):
    """One layer of hashed stars: at most one a cube-map cell, at a hashed position
    inside it, Gaussian of sigma `size` (cell units), present with probability
    `fraction * density`, peak brightness a power law from `faint` up to `bright`."""
    face, u, v = _cube_cells(n, cells)
    iu, iv = jnp.floor(u), jnp.floor(v)
    ii, jj = iu.astype(jnp.int32), iv.astype(jnp.int32)
    h1, h2 = _hash(ii, jj, face, salt + 1), _hash(ii, jj, face, salt + 2)
    h3, h4 = _hash(ii, jj, face, salt + 3), _hash(ii, jj, face, salt + 4)
    temp = _hash(ii, jj, face, salt + 5).astype(n.dtype)
    du = u - (iu + 0.3 + 0.4 * h1)
    dv = v - (iv + 0.3 + 0.4 * h2)
    r2 = (du * du + dv * dv) * (1.0 / (size * size))
    present = h3 < fraction * density
    # Flux of a uniform population: N(> F) ~ F^-3/2, so F = F_min u^(-2/3), capped.
    mag = jnp.minimum(faint * jnp.maximum(h4, 1e-6) ** (-2.0 / 3.0), bright)
    # Fade to zero at the cell border, so no star is cut off by its cell.
    fu, fv = u - iu, v - iv
    edge = jnp.minimum(jnp.minimum(fu, 1.0 - fu), jnp.minimum(fv, 1.0 - fv))
    window = jnp.clip(edge * (1.0 / 0.2), 0.0, 1.0) ** 2
    i = jnp.where(present, mag * jnp.exp(-0.5 * r2) * window, 0.0)
    tint = jnp.stack([0.75 + 0.45 * temp, 0.85 + 0.15 * temp, 1.25 - 0.55 * temp], -1)
    return i[..., None] * tint


class DefaultSky(AbstractSky):
    """The procedural default sky: a Milky-Way-like band with a bulge, clumpy star
    clouds, dark dust lanes and two layers of stars. Made by code (no image file),
    deterministic, continuous across the whole sphere.

    The band is a great circle tilted 30 degrees across the view, its centre (the
    bulge) 40 degrees to the left of $+z$. Its brightness and dust are fractal value
    noise in 3-D (no seam, no pole); stars sit in cube-map cells, at most one a cell,
    at hashed positions, more of them near the band, so evaluating the sky costs the
    same for every direction.

    **Fields:** `brightness` (overall scale), `cells` (static: cells a cube face of
    the faint star layer), `star_size` (static: Gaussian sigma of a star, in units of
    its cell), `stars` (static: include the star layers).
    """

    brightness: Float[Array, ""]
    cells: int = eqx.field(static=True)
    star_size: float = eqx.field(static=True)
    stars: bool = eqx.field(static=True)

    def __init__(self, brightness: ArrayLike = 1.0, *, cells: int = 256, star_size: float = 0.08,
                 stars: bool = True):  # fmt: skip
        self.brightness = _farray(brightness)
        self.cells = int(cells)
        self.star_size = float(star_size)
        self.stars = bool(stars)

    def __check_init__(self):
        if self.cells < 1 or not self.star_size > 0:
            raise ValueError(f"cells={self.cells} must be >= 1, star_size={self.star_size} > 0")

    def galactic_frame(self):
        """Unit vectors (centre, east, pole) of the band's frame, world coordinates."""
        tilt, lon_c = math.radians(30.0), math.radians(-40.0)
        east = np.array([math.cos(tilt), math.sin(tilt), 0.0])  # along the band, +x-ward
        pole = np.array([-math.sin(tilt), math.cos(tilt), 0.0])
        # Centre: +z turned about the pole by lon_c (stays in the band).
        z = np.array([0.0, 0.0, 1.0])
        centre = math.cos(lon_c) * z + math.sin(lon_c) * np.cross(pole, z)
        east = np.cross(pole, centre)
        return centre, east, pole

    def __call__(self, n):
        dt = n.dtype
        centre, east, pole = (jnp.asarray(v, dt) for v in self.galactic_frame())
        nc, ne, npole = (jnp.sum(n * v, -1) for v in (centre, east, pole))
        b = arctan2(npole, jnp.sqrt(nc * nc + ne * ne))  # galactic latitude
        l = arctan2(ne, nc)  # noqa: E741  galactic longitude
        # Star clouds and dust: 3-D fractal noise on the sphere (no seams).
        clouds = _fbm(n * 5.0, 5, 11)
        grain = _fbm(n * 23.0 + 3.0, 3, 29)
        dustn = _fbm(n * 9.0 + 7.0, 4, 47)
        width = 0.11 + 0.05 * (clouds - 0.5) + 0.06 * jnp.exp(-((l / 0.7) ** 2))
        disk = jnp.exp(-((b / width) ** 2)) * (0.3 + 0.7 * jnp.exp(-((l / 1.6) ** 2)))
        disk = disk * (0.35 + 1.3 * clouds**2) * (0.75 + 0.5 * grain)
        halo = 0.12 * jnp.exp(-((b / 0.45) ** 2)) * (0.4 + 0.6 * jnp.exp(-((l / 1.2) ** 2)))
        bulge = jnp.exp(-((l / 0.2) ** 2) - (b / 0.15) ** 2) * (0.8 + 0.4 * clouds)
        # Dust: a rift along the plane, wavy and filamentary.
        ridge = 1.0 - jnp.abs(2.0 * dustn - 1.0)
        lane = jnp.exp(-(((b - 0.035 * (dustn - 0.5)) / (0.03 + 0.02 * grain)) ** 2))
        tau = 2.2 * lane * ridge**2 * (0.4 + 0.6 * jnp.exp(-((l / 1.5) ** 2)))
        redden = jnp.asarray([0.75, 1.0, 1.35], dt)
        trans = jnp.exp(-tau[..., None] * redden)
        glow = (
            0.16 * disk[..., None] * jnp.asarray([0.78, 0.84, 1.0], dt)
            + 0.5 * bulge[..., None] * jnp.asarray([1.0, 0.8, 0.55], dt)
            + 0.03 * halo[..., None] * jnp.asarray([0.8, 0.85, 1.0], dt)
        ) * trans
        out = glow
        if self.stars:
            density = 0.25 + 0.75 * jnp.exp(-((b / 0.25) ** 2)) + 0.5 * bulge
            faint = _star_layer(n, self.cells, self.star_size, 0.6, 0.02, 0.6, density, 100)
            bright = _star_layer(
                n, max(self.cells // 4, 1), 0.75 * self.star_size, 0.5, 0.1, 6.0, density, 200
            )
            out = out + (faint * trans + bright).astype(dt)
        return self.brightness.astype(dt) * out


@eqx.filter_jit
def _equirect_block(sky, j0, width, height, rows, k, dtype):
    sub = (jnp.arange(k, dtype=dtype) + 0.5) / k
    i = (jnp.arange(width, dtype=dtype)[:, None] + sub).reshape(-1)
    j = ((j0 + jnp.arange(rows)).astype(dtype)[:, None] + sub).reshape(-1)
    lon = 2.0 * math.pi * i / width - math.pi
    lat = 0.5 * math.pi - math.pi * j / height
    n = direction_from_angles(lon[None, :], lat[:, None]).astype(dtype)
    img = sky(n).reshape(rows, k, width, k, 3).mean(axis=(1, 3))
    return img.astype(jnp.float32)


def equirectangular(
    sky: AbstractSky, width: int, height: int, *, supersample: int = 1, dtype=jnp.float32
) -> np.ndarray:
    """Sample a sky onto an equirectangular grid (the `Panorama` pixel convention).

    **Arguments:** `sky`; `width`, `height` (pixels; 2:1 for square pixels in angle);
    `supersample`: $k \\times k$ samples a pixel (uniform in longitude and latitude);
    `dtype`: the dtype the sky is evaluated in.

    **Returns:** float32 `(height, width, 3)` linear radiance; `Panorama(result)`
    gives the sky back (bilinearly interpolated).
    """
    if width < 1 or height < 1 or supersample < 1:
        raise ValueError(f"width={width}, height={height}, supersample={supersample} must be >= 1")
    k = supersample
    rows = min(height, max(1, (1 << 20) // (width * k * k)))
    out = np.empty((height, width, 3), np.float32)
    for r0 in range(0, height, rows):
        s = min(r0, height - rows)  # the last block overlaps instead of padding
        block = _equirect_block(sky, jnp.asarray(s), width, height, rows, k, jnp.dtype(dtype))
        out[r0 : s + rows] = np.asarray(block)[r0 - s :]
    return out
