"""The result of a ring fit (`RingFit`) and the diagnosis of a degenerate or failed
fit."""

import math

import equinox as eqx
import numpy as np
import optimistix as optx

from .units import mass_from_distance, schwarzschild_radius_m


class RingFit(eqx.Module):
    """Result of `fit_ring`.

    **Fields:**
    - `distance`, `distance_err`: camera distance and its standard error (units of R_S).
    - `fov`, `fov_err`: horizontal field of view (radians); `fov_deg`, `fov_deg_err`
      are the same in degrees.
    - `brightness`, `floor` (+ `_err`): peak star radiance $A$ and sky level, in the
      image's units (linear, [0, 1] for integer formats).
    - `sigma`, `sigma_err`: star width (radians; `sigma_err` is 0 when it was given).
    - `ring_flux`, `ring_flux_err`: the flux of the relativistic rings (orders 1 and 2)
      relative to the exact area average, a nuisance factor with a prior N(1, 1): the
      rings are a few thousandths of a pixel wide and renderers that point-sample
      pixels alias them; ~1 for an exactly area-averaged image.
    - `covariance`: of (D, fov, [sigma,] A, floor) in those units; `correlation`.
    - `names`: the parameter names in that order.
    - `noise`: residual standard deviation per pixel of the fitted (binned) image.
    - `n_pixels`, `block`, `supersample`: pixels fitted, binning, k.
    - `result`: the optimistix `RESULTS` of the solve (`result_name`: its name);
      `num_steps`: its steps.
    - `converged`: optimistix succeeded and the curvature is finite and invertible.
    - `degenerate`: the data do not fix D and FOV separately, or the solve did not
      converge (see `message`); `variance_inflation`: the largest of
      $1/(1 - R^2)$ over D, FOV (and sigma), $R$ the multiple correlation of one with
      the others (above 1e9: degenerate).
    - `message`: human-readable diagnosis ("" when all is well).
    - `valid` (property): converged, not degenerate and no message: the values and
      errors are a measurement; anything else is flagged, not one to report.
    - `seconds`: wall time of the fit, compile included.
    - `transfer`: how a file's values were read (`read_observation`): `"srgb"` decoded
      to linear, `"linear"` as stored; `None` for an array.
    """

    distance: float
    distance_err: float
    fov: float
    fov_err: float
    brightness: float
    brightness_err: float
    floor: float
    floor_err: float
    sigma: float
    sigma_err: float
    ring_flux: float
    ring_flux_err: float
    covariance: np.ndarray
    correlation: np.ndarray
    names: tuple
    noise: float
    n_pixels: int
    block: int
    supersample: int
    result: optx.RESULTS
    result_name: str
    num_steps: int
    converged: bool
    degenerate: bool
    variance_inflation: float
    message: str
    seconds: float
    start: tuple
    transfer: str | None = None

    @property
    def valid(self) -> bool:
        """Converged, not degenerate, and every check passed (`message` is empty)."""
        return bool(self.converged and not self.degenerate and not self.message)

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view, degrees."""
        return math.degrees(self.fov)

    @property
    def fov_deg_err(self) -> float:
        """Standard error of the field of view, degrees."""
        return math.degrees(self.fov_err)

    @property
    def sigma_deg(self) -> float:
        """Star width, degrees."""
        return math.degrees(self.sigma)

    def distance_m(self, mass_msun: float) -> tuple[float, float]:
        """Camera distance in metres and its standard error, for a hole of `mass_msun`
        solar masses (taken as exact)."""
        rs = float(schwarzschild_radius_m(mass_msun))
        return self.distance * rs, self.distance_err * rs

    def mass_msun(self, distance_m: float) -> tuple[float, float]:
        """Mass of the hole in solar masses and its standard error, for a camera
        distance of `distance_m` metres (taken as exact)."""
        m = float(mass_from_distance(self.distance, distance_m))
        return m, m * self.distance_err / self.distance

    def to_dict(self) -> dict:
        """Plain-Python summary (JSON-serialisable)."""
        return {
            "distance": self.distance,
            "distance_err": self.distance_err,
            "fov": self.fov,
            "fov_err": self.fov_err,
            "fov_deg": self.fov_deg,
            "fov_deg_err": self.fov_deg_err,
            "brightness": self.brightness,
            "brightness_err": self.brightness_err,
            "floor": self.floor,
            "floor_err": self.floor_err,
            "sigma": self.sigma,
            "sigma_err": self.sigma_err,
            "sigma_deg": self.sigma_deg,
            "sigma_deg_err": math.degrees(self.sigma_err),
            "ring_flux": self.ring_flux,
            "ring_flux_err": self.ring_flux_err,
            "noise": self.noise,
            "n_pixels": self.n_pixels,
            "block": self.block,
            "supersample": self.supersample,
            "num_steps": self.num_steps,
            "result": self.result_name,
            "valid": self.valid,
            "converged": self.converged,
            "degenerate": self.degenerate,
            "variance_inflation": self.variance_inflation,
            "message": self.message,
            "seconds": self.seconds,
        }

    def summary(self) -> str:
        """A readable report."""
        lines = [
            f"distance  D   = {self.distance:.6g} +- {self.distance_err:.2g} R_S",
            f"field of view = {self.fov_deg:.6g} +- {self.fov_deg_err:.2g} deg",
            f"star sigma    = {self.sigma_deg:.4g}"
            + (f" +- {math.degrees(self.sigma_err):.2g} deg" if self.sigma_err else " deg (given)"),
            f"brightness A  = {self.brightness:.4g} +- {self.brightness_err:.2g}",
            f"floor         = {self.floor:.4g} +- {self.floor_err:.2g}",
            f"ring flux     = {self.ring_flux:.3g} +- {self.ring_flux_err:.2g} "
            "(relativistic rings / exact)",
            f"noise         = {self.noise:.3g} per pixel ({self.n_pixels} pixels, "
            f"bin {self.block}, {self.supersample}x{self.supersample} samples)",
            f"solver        = {self.num_steps} steps, "
            + ("converged" if self.converged else "NOT converged")
            + f", {self.seconds:.1f} s"
            + ("; file read as sRGB, decoded to linear" if self.transfer == "srgb" else ""),
        ]
        if self.degenerate:
            lines.append(f"DEGENERATE: {self.message}")
        elif self.message:
            lines.append(f"FLAGGED (not a valid measurement): {self.message}")
        return "\n".join(lines)


# Degeneracy thresholds: a relative standard error of D or FOV above 10 % means the
# image does not pin them down (the goal is 1 %); a variance inflation above 1e9
# (multiple correlation of D, FOV or sigma with the others above 1 - 1e-9) means the
# curvature is numerically singular along a valley where D trades off against FOV and
# sigma. Rings without a visible shadow edge and sigma fitted sit at 1e6-1e8 with D
# still fixed to 2-3 % by the ring's profile (320 x 240, noise 0.01): not degenerate.
_REL_ERR_DEGENERATE = 0.10
_VIF_DEGENERATE = 1e9
# With sigma fitted and no floor, what separates D from FOV and sigma is the relativistic
# ring (the primary ring alone fixed D to 5 % at D = 17, 320 x 240, noise 0.005). Where
# that ring's flux is measured to worse than 1/_RING_SIGNIFICANCE, fits from different
# noise realisations and starts scattered up to 4 times their reported errors (local minima
# along the valley): degenerate. A floor counts as seen above _EDGE_SIGNIFICANCE errors.
_RING_SIGNIFICANCE = 10.0
_EDGE_SIGNIFICANCE = 5.0


def _result_name(result) -> str:
    for name in (
        "successful",
        "nonlinear_max_steps_reached",
        "max_steps_reached",
        "nonlinear_divergence",
        "nonfinite",
        "singular",
        "breakdown",
        "stagnation",
    ):
        if bool(result == getattr(optx.RESULTS, name)):
            return name
    return "failed"


def _ring_verdict(names, values, errors, corr, shadow_seen: bool):
    """Whether a fit of D and FOV (`names` holding both) is degenerate, as a ring fixes
    them: D and FOV loose (relative errors above 10 %) or their curvature singular
    (variance inflation of D, FOV and sigma above 1e9); or, with sigma free, neither
    the shadow's edge (`shadow_seen`, or a floor seen above its errors) nor the
    relativistic ring (its flux above 10 errors) separating D from FOV and sigma.

    **Returns:** `(degenerate, note, vif)`: the note ("" when not degenerate) and the
    largest variance inflation.
    """
    fit_sigma = "sigma" in names
    idx = [names.index(n) for n in ("distance", "fov", "sigma") if n in names]
    d, fov = values["distance"], values["fov"]
    rel_d = errors["distance"] / d if d > 0 else np.inf
    rel_f = errors["fov"] / fov if fov > 0 else np.inf
    try:
        vif = float(np.max(np.diag(np.linalg.inv(corr[np.ix_(idx, idx)]))))
    except np.linalg.LinAlgError:
        vif = np.inf
    if not np.isfinite(vif):
        vif = np.inf
    if not (rel_d < _REL_ERR_DEGENERATE and rel_f < _REL_ERR_DEGENERATE) or vif > _VIF_DEGENERATE:
        why = (
            f"D and FOV are not fixed separately by this image (relative errors "
            f"{rel_d:.2g} and {rel_f:.2g}, variance inflation {vif:.3g})"
        )
        if fit_sigma and not shadow_seen:
            why += (
                "; sigma is unknown and no shadow edge is visible against a floor, so "
                "the ring's radius and width trade D against FOV and sigma: pass "
                "star_sigma (fix sigma), or use an image with a visible shadow edge"
            )
        return True, why, vif
    edge_seen = shadow_seen or (
        "floor" in names and values["floor"] > _EDGE_SIGNIFICANCE * errors["floor"]
    )
    ring_seen = "ring_flux" not in names or (
        values["ring_flux"] > _RING_SIGNIFICANCE * errors["ring_flux"]
    )
    if fit_sigma and not edge_seen and not ring_seen:
        return (
            True,
            (
                f"sigma is unknown, no shadow edge is visible against a floor, and the "
                f"relativistic ring is seen at {values['ring_flux'] / errors['ring_flux']:.2g} "
                f"standard errors (below {_RING_SIGNIFICANCE:g}): only it separates D from FOV "
                f"and sigma, so D = {d:.4g} +- {errors['distance']:.2g} rests on a faint, "
                "sub-pixel feature: pass star_sigma (fix sigma), or use an image with a "
                "visible shadow edge or less noise"
            ),
            vif,
        )
    return False, "", vif
