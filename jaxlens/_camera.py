"""A static pinhole camera at radius D looking at the hole (PHYSICS.md conventions).

Two frames:

- the **camera frame**: the hole at the origin, the camera on the $-z$ axis, so $+z$
  points from the camera through the hole; $x$ to the right and $y$ up in the image
  when yaw = pitch = roll = 0. The ray map works here: a ray's local angle alpha is
  measured from $+z$ and its orbital plane contains the $z$ axis.
- the **world frame** (the sky's): the camera frame turned by the camera's position
  around the hole (`azimuth`, `elevation`). With both zero the frames coincide and
  $+z$ is "behind the hole".

Moving a static camera around the hole at fixed distance only turns the sky (spherical
symmetry), so an orbit costs nothing more than a rotation of the sky directions.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._fastmath import arctan2, sin_cos
from ._messages import shown
from ._ray_inputs import check_distance, check_dtype, check_real
from ._units import angle, length
from ._util import as_float as _float, concrete as _concrete, is_zero as _is_zero


def rotation_matrix(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> Float[Array, "3 3"]:
    """Rotation $R = R_y(\\mathrm{yaw})\\,R_x(-\\mathrm{pitch})\\,R_z(\\mathrm{roll})$ (radians).

    It maps $+z$ to the direction at longitude yaw, latitude pitch (the convention of
    `direction_from_angles`), and turns $+x$ toward $+y$ by roll first.

    **Arguments:** `yaw`, `pitch`, `roll`: radians, or astropy angle Quantities.

    **Returns:** a `(3, 3)` array in the dtype of the angles.
    """
    yaw, pitch, roll = angle(yaw, "yaw"), angle(pitch, "pitch"), angle(roll, "roll")
    yaw, pitch, roll = jnp.broadcast_arrays(
        *(jnp.asarray(a, jnp.result_type(float, yaw, pitch, roll)) for a in (yaw, pitch, roll))
    )
    cy, sy = jnp.cos(yaw), jnp.sin(yaw)
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    one, zero = jnp.ones_like(cy), jnp.zeros_like(cy)
    r_yaw = jnp.stack(
        [jnp.stack([cy, zero, sy]), jnp.stack([zero, one, zero]), jnp.stack([-sy, zero, cy])]
    )
    r_pitch = jnp.stack(
        [jnp.stack([one, zero, zero]), jnp.stack([zero, cp, sp]), jnp.stack([zero, -sp, cp])]
    )
    r_roll = jnp.stack(
        [jnp.stack([cr, -sr, zero]), jnp.stack([sr, cr, zero]), jnp.stack([zero, zero, one])]
    )
    return r_yaw @ r_pitch @ r_roll


def rotate(m: Float[Array, "3 3"], n: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """`m @ n` for a stack of 3-vectors `n (..., 3)`, written as three FMAs a component."""
    m = m.astype(n.dtype)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    return jnp.stack([m[i, 0] * x + m[i, 1] * y + m[i, 2] * z for i in range(3)], axis=-1)


SAMPLINGS = ("uniform", "gauss")

# The largest image side (pixels) and area-sampling factor a camera takes: those of the
# CLI and scene files. 2^20 - 1 pixels a side keeps pixel indices and image-plane
# coordinates exact in float32 (24-bit significand, with a sub-sample's 1/k).
MAX_SIDE = (1 << 20) - 1
MAX_SUPERSAMPLE = 64


class Camera(eqx.Module):
    """Pinhole camera of a static observer at radius `distance` (PHYSICS.md, "Pixels").

    **Fields:**
    - `distance`: camera radius $1 < D \\le 10^{30}$ (units of R_S; the bound is
      `trace`'s, `MAX_DISTANCE`), also > 1 once rounded to the camera's dtype. A
      dimensionless astropy Quantity is read as R_S; a length in metres, km, ... is
      refused (R_S depends on the mass: `jaxlens.schwarzschild_radii` converts it).
    - `fov`: horizontal field of view (radians, $0 < \\mathrm{fov} < \\pi$). Every angle
      field also takes an astropy angle Quantity (`2 * u.deg`), converted to radians.
    - `width`, `height`: image size in pixels (static), whole numbers from 1 to
      `MAX_SIDE` = 1,048,575.
    - `yaw`, `pitch`, `roll`: orientation of the view (radians, finite); yaw turns the
      view to the right (+x), pitch up (+y), roll turns the view about the line of
      sight from +x toward +y, so the scene turns clockwise on the image (a star at
      the right of the image moves to the bottom at roll = +90 degrees). All zero:
      the hole sits at the image centre.
    - `azimuth`, `elevation`: the camera's position on its sphere of radius $D$
      (radians): the camera sits opposite the sky direction at longitude `azimuth`,
      latitude `elevation`, and (with zero yaw/pitch) looks at the hole and that sky
      direction behind it. Sweeping `azimuth` orbits the camera around the hole.
    - `supersample`: area sampling with $k \\times k$ samples a pixel (static), $k$
      from 1 to `MAX_SUPERSAMPLE` = 64.
    - `sampling` (static): `"uniform"` ($k \\times k$ point samples a pixel on a regular
      grid, the shadow edge as a linear ramp over one sample) or `"gauss"` (area-exact:
      the $k \\times k$ nodes of a Gauss-Legendre rule, the exact fraction of each cell
      outside the shadow edge, and the relativistic rings of compact sources, images of
      order $\\ge 1$ a small fraction of a pixel wide, integrated across each cell
      instead of point-sampled). `"gauss"` is what a fit differentiates: every pixel
      is continuous in the distance, the field of view and the source position.

    Every array field may carry one leading batch axis (all of the same length, see
    `stack_cameras`) to describe a batch of cameras for `render_frames` or
    `jax.vmap`.
    """

    distance: Float[Array, "*batch"]
    fov: Float[Array, "*batch"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    yaw: Float[Array, "*batch"]
    pitch: Float[Array, "*batch"]
    roll: Float[Array, "*batch"]
    azimuth: Float[Array, "*batch"]
    elevation: Float[Array, "*batch"]
    supersample: int = eqx.field(static=True)
    sampling: str = eqx.field(static=True)

    def __init__(
        self,
        distance: ArrayLike,
        fov: ArrayLike,
        width: int,
        height: int,
        *,
        yaw: ArrayLike = 0.0,
        pitch: ArrayLike = 0.0,
        roll: ArrayLike = 0.0,
        azimuth: ArrayLike = 0.0,
        elevation: ArrayLike = 0.0,
        supersample: int = 1,
        sampling: str = "uniform",
        dtype=None,
    ):
        """**Arguments:** as the fields; `dtype`: float dtype of the array fields,
        float32 or float64 (default: that of `distance` and `fov`, float64 for Python
        floats when `jax_enable_x64` is on).

        A complex, boolean or text value of an array field, or another `dtype`, is a
        `TypeError`; a value out of range a `ValueError` naming it."""
        angles = {"fov": fov, "yaw": yaw, "pitch": pitch, "roll": roll,
                  "azimuth": azimuth, "elevation": elevation}  # fmt: skip
        for name, value in angles.items():
            angles[name] = check_real(name, angle(value, name))
        distance = check_real("distance", length(distance, "distance"))
        fov, yaw, pitch, roll, azimuth, elevation = angles.values()
        dtype = check_dtype(jnp.result_type(float, distance, fov) if dtype is None else dtype)
        for name, value in angles.items():  # before the cast, which would give inf
            a = _concrete(value)
            with np.errstate(over="ignore"):
                finite = a is None or np.all(np.isfinite(np.asarray(a, dtype)))
            if not finite:
                raise ValueError(f"{name}={_cut(a)} must be finite in {dtype.name} (radians)")
        if _concrete(distance) is not None:
            # Before the cast: 1e300 in float32 is inf, 1 + 1e-9 is the horizon.
            check_distance(_concrete(distance), dtype)
        self.distance = _float(distance, dtype)
        self.fov = _float(fov, dtype)
        for name, top in (("width", MAX_SIDE), ("height", MAX_SIDE),
                          ("supersample", MAX_SUPERSAMPLE)):  # fmt: skip
            v = locals()[name]
            whole = isinstance(v, int | np.integer) and not isinstance(v, bool)
            if isinstance(v, float | np.floating):
                whole = math.isfinite(v) and float(v).is_integer()
            if not (whole and 1 <= v <= top):
                raise ValueError(f"{name}={_cut(v)} must be a whole number from 1 to {top:,}")
        self.width = int(width)
        self.height = int(height)
        self.yaw = _float(yaw, dtype)
        self.pitch = _float(pitch, dtype)
        self.roll = _float(roll, dtype)
        self.azimuth = _float(azimuth, dtype)
        self.elevation = _float(elevation, dtype)
        self.supersample = int(supersample)
        self.sampling = sampling

    def __check_init__(self):
        if self.sampling not in SAMPLINGS:
            raise ValueError(
                f"sampling={self.sampling!r} must be one of {', '.join(map(repr, SAMPLINGS))}"
            )
        for name, top in (("width", MAX_SIDE), ("height", MAX_SIDE),
                          ("supersample", MAX_SUPERSAMPLE)):  # fmt: skip
            v = getattr(self, name)
            if not 1 <= v <= top:
                raise ValueError(f"{name}={v} must be a whole number from 1 to {top:,}")
        d = _concrete(self.distance)
        if d is not None:  # (after `eqx.tree_at`, `approach`: values set without __init__)
            check_distance(d)
        f = _concrete(self.fov)
        if f is not None and (not np.all(np.isfinite(f)) or not np.all((f > 0) & (f < math.pi))):
            bad = f[~(np.isfinite(f) & (f > 0) & (f < math.pi))] if f.ndim else f
            raise ValueError(
                f"fov={float(np.degrees(bad.flat[0]))!r} degrees is not a valid field of view: it "
                "must be in (0, 180) degrees"
            )
        for name in ("yaw", "pitch", "roll", "azimuth", "elevation"):
            a = _concrete(getattr(self, name))
            if a is not None and not np.all(np.isfinite(a)):
                raise ValueError(f"{name}={_cut(a)} must be finite (radians)")

    # ------------------------------------------------------------------ geometry

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Shape of the batch of cameras (`()` for one camera)."""
        return jnp.shape(self.distance)

    @property
    def focal(self) -> Float[Array, "*batch"]:
        """Focal length in pixels: $(W/2) / \\tan(\\mathrm{FOV}/2)$."""
        return (0.5 * self.width) / jnp.tan(0.5 * self.fov)

    @property
    def dtype(self):
        """Float dtype of the camera's arrays (the render computes in it)."""
        return self.fov.dtype

    def is_centred(self) -> bool:
        """True when yaw, pitch and roll are concretely zero (host-side; False for
        tracers): the hole sits at the image centre and the image has the mirror
        symmetries the fast render path uses."""
        return all(_is_zero(a) for a in (self.yaw, self.pitch, self.roll))

    def at_origin(self) -> bool:
        """True when azimuth and elevation are concretely zero (host-side): the
        camera frame is the world frame."""
        return _is_zero(self.azimuth) and _is_zero(self.elevation)

    def sample_x(self) -> Float[Array, " Wk"]:
        """Image-plane $x$ of the sample columns, left to right (pixels):
        column $i$, sub-sample $m$ at $x = i + (m + 1/2)/k - W/2$."""
        k = self.supersample
        sub = (jnp.arange(k, dtype=self.dtype) + 0.5) / k
        col = jnp.arange(self.width, dtype=self.dtype)[:, None] + sub[None, :]
        return (col - 0.5 * self.width).reshape(-1)

    def sample_y(self, row0: ArrayLike = 0, rows: int | None = None) -> Float[Array, " Rk"]:
        """Image-plane $y$ of the sample rows of pixel rows `row0 .. row0+rows`, top to
        bottom (pixels): row $j$, sub-sample $n$ at $y = H/2 - j - (n + 1/2)/k$."""
        rows = self.height if rows is None else rows
        k = self.supersample
        sub = (jnp.arange(k, dtype=self.dtype) + 0.5) / k
        row = (jnp.asarray(row0, self.dtype) + jnp.arange(rows, dtype=self.dtype))[:, None] + sub
        return (0.5 * self.height - row).reshape(-1)

    def sample_xy(self, row0: ArrayLike = 0, rows: int | None = None):
        """Image-plane coordinates of the area samples of rows `row0 .. row0+rows`.

        Pixel (i, j) has its centre at $x = i + 0.5 - W/2$, $y = H/2 - (j + 0.5)$;
        sample (m, n) of $k \\times k$ sits at column $i + (m + 0.5)/k$, row
        $j + (n + 0.5)/k$.

        **Returns:** `x, y` of shape `(rows, W, k*k)` (pixels), sample index
        $n k + m$.
        """
        rows = self.height if rows is None else rows
        k = self.supersample
        x = self.sample_x().reshape(self.width, k)
        y = self.sample_y(row0, rows).reshape(rows, k)
        xs = jnp.broadcast_to(x[None, :, None, :], (rows, self.width, k, k))
        ys = jnp.broadcast_to(y[:, None, :, None], (rows, self.width, k, k))
        return xs.reshape(rows, self.width, k * k), ys.reshape(rows, self.width, k * k)

    def rotation(self) -> Float[Array, "3 3"]:
        """View rotation (camera-frame directions of the image axes): roll about the
        view axis, then pitch, then yaw (`rotation_matrix`)."""
        return rotation_matrix(self.yaw, self.pitch, self.roll)

    def position_rotation(self) -> Float[Array, "3 3"]:
        """Camera frame to world frame: maps $+z$ to the sky direction behind the hole
        at longitude `azimuth`, latitude `elevation`."""
        return rotation_matrix(self.azimuth, self.elevation, jnp.zeros_like(self.azimuth))

    def rays(self, row0: ArrayLike = 0, rows: int | None = None):
        """Local angles of the samples of rows `row0 .. row0+rows`.

        **Returns:** `alpha` (angle from the direction of the hole, radians),
        `cos_beta`, `sin_beta` (the orbital plane: the ray's direction across the
        line of sight, camera frame), each of shape `(rows, W, k*k)`.
        """
        x, y = self.sample_xy(row0, rows)
        return self._angles(x, y, oriented=not self.is_centred())

    def _view(self, x, y, *, oriented: bool):
        """Camera-frame direction (not normalised, $z$ toward the hole) of image-plane
        points `x, y` (pixels): `(dx, dy, dz)`; `oriented`: apply the view rotation."""
        f = self.focal
        if not oriented:
            return x, y, jnp.broadcast_to(f, jnp.shape(x))
        rot = self.rotation()
        return tuple(rot[i, 0] * x + rot[i, 1] * y + rot[i, 2] * f for i in range(3))

    def _angles(self, x, y, *, oriented: bool):
        return view_angles(*self._view(x, y, oriented=oriented))[:3]

    def to_world(self, n: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Camera-frame directions to world (sky) directions."""
        return rotate(self.position_rotation(), n)


def _cut(value, limit: int = 80) -> str:
    """`value` as a message shows it, cut to `limit` characters."""
    return shown(value.tolist() if isinstance(value, np.ndarray) else value, limit)


def view_angles(dx, dy, dz):
    """Local angle from the hole `alpha`, the orbital plane `(cos_beta, sin_beta)`
    (`(1, 0)` on the axis) and `rho` $= \\sqrt{dx^2 + dy^2}$ of camera-frame directions."""
    rho = jnp.hypot(dx, dy)
    alpha = arctan2(rho, dz)
    safe = rho > 0
    rho_ = jnp.where(safe, rho, 1.0)
    return alpha, jnp.where(safe, dx / rho_, 1.0), jnp.where(safe, dy / rho_, 0.0), rho


def sky_direction(phi, cos_beta, sin_beta):
    """Camera-frame direction of the escaping asymptote: angle `phi` from the
    hole-to-camera axis ($-z$) in the plane picked by beta.

    **Returns:** unit vectors `(..., 3)`; $+z$ (behind the hole) where $\\phi = \\pi$.
    """
    s, c = sin_cos(phi)
    return jnp.stack([s * cos_beta, s * sin_beta, -c], axis=-1)


# ---------------------------------------------------------------------- batches


def stack_cameras(cameras) -> Camera:
    """One batched `Camera` from a sequence of cameras of the same size and
    supersampling: every array field gets a leading axis.

    **Returns:** a `Camera` whose `batch_shape` is `(len(cameras),)`.
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("stack_cameras needs at least one camera")
    first = cameras[0]
    for c in cameras[1:]:
        if _static(c) != _static(first):
            raise ValueError(
                "cameras of one batch must share width, height, supersample and sampling, got "
                f"{_static(c)} and {_static(first)}"
            )
    return jax.tree.map(lambda *a: jnp.stack(a), *cameras)


def _static(c: Camera) -> tuple:
    return (c.width, c.height, c.supersample, c.sampling)


def _sweep(camera: Camera, name: str, values) -> Camera:
    values = length(values, name) if name == "distance" else angle(values, name)
    known = _concrete(check_real(name, values))
    if known is not None:  # before the cast: 1e300 is inf in float32
        if name == "distance":
            check_distance(known, camera.dtype)
        elif not np.all(np.isfinite(known)) or np.any(np.abs(known) > np.finfo(camera.dtype).max):
            bad = known[~(np.abs(known) <= np.finfo(camera.dtype).max)]
            raise ValueError(
                f"{name}={_cut(bad.flat[0])} must be finite in {camera.dtype.name} (radians)"
            )
    values = jnp.asarray(values, camera.dtype)
    if values.ndim != 1 or values.shape[0] < 1:
        raise ValueError(
            f"{name} values must be a non-empty 1-D sequence, got shape {values.shape}"
        )
    n = values.shape[0]
    batched = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,)), camera)
    out = eqx.tree_at(lambda c: getattr(c, name), batched, values)
    out.__check_init__()
    return out


def approach(camera: Camera, distances) -> Camera:
    """A batch of `camera` at each of `distances` (units of R_S, or a dimensionless
    astropy Quantity): a fall toward the hole, e.g. `np.geomspace(1e5, 3, 48)`."""
    return _sweep(camera, "distance", distances)


def orbit(camera: Camera, azimuths) -> Camera:
    """A batch of `camera` at each of the positions `azimuths` (radians, or an astropy
    angle Quantity) around the
    hole at fixed distance, looking at the hole: e.g. `np.linspace(0, 2 pi, 36)`."""
    return _sweep(camera, "azimuth", azimuths)


def pan(camera: Camera, yaws) -> Camera:
    """A batch of `camera` turned by each of `yaws` (radians, or an astropy angle
    Quantity) in place: the hole sweeps across the view."""
    return _sweep(camera, "yaw", yaws)


def zoom(camera: Camera, fovs) -> Camera:
    """A batch of `camera` with each horizontal field of view of `fovs` (radians, or an
    astropy angle Quantity)."""
    return _sweep(camera, "fov", fovs)
