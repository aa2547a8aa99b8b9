"""The result of a fit (`Fit`, of `fit` and `fit_ring`): values, standard errors,
correlations, the residual image and the verdict."""

import dataclasses
import math

import numpy as np

from .noise import GOODNESS_SIGMAS
from .params import is_angle, parameter
from .source import SourceDistance
from .units import mass_from_distance, schwarzschild_radius_m, to_metres, to_solar_masses


@dataclasses.dataclass(frozen=True)
class Fit:
    """Result of `fit` and of `fit_ring`.

    **Fields:**
    - `scene`: the fitted `Scene` (the model, its free parameters at their values).
    - `names`: the free parameters, in the order of `covariance`.
    - `values`, `errors`: dicts of every fitted parameter's value and standard error
      (units of `PARAMETERS`: R_S, radians, the image's linear units, pixels; a
      further star's under its index, `source_lon_2`, ...).
    - `covariance`, `correlation`: of the free parameters (physical units), from the
      Gauss-Newton curvature (the Laplace approximation) at the optimum.
    - `start`: the starting values, by parameter name (the units of `values`).
    - `noise`: `"gaussian"` or `"poisson"`; `noise_sigma`: the per-pixel noise of the
      image (data units; Gaussian), `gain` (counts per data unit; Poisson).
    - `chi2_dof`: the residuals' sum of squares per degree of freedom, in units of the
      noise (about 1 when the model describes the image to its noise).
    - `model`, `residuals`: the model image and data - model on the compared pixel grid
      (`block` x `block` bins of the image; NaN where masked).
    - `n_pixels`, `block`, `supersample`: pixels compared, their binning, k.
    - `result`: the optimistix `RESULTS` of the solve, `result_name` its name,
      `num_steps` its steps (over both passes where the noise of a clipped image is
      re-estimated between them).
    - `converged`: the solve succeeded, the curvature is finite and invertible, no
      parameter sits at a bound; `degenerate`: some parameters cannot be separated by
      the image (named in `message`; from `fit_ring` also when not converged, as a
      ring's D and FOV are then not fixed); `message`: "" when all is well, else every check
      that failed (solver, bounds, degeneracy, residuals against the noise, nuisances
      out of their physical range, no pixel noise found).
    - `valid` (property): converged, not degenerate and no message: the values and
      errors are a measurement. Anything else is a flagged result, not one to report.
    - `caveat`: what a valid measurement rests on where that is worth saying ("" when
      nothing): a D that only a faint feature fixes (the relativistic ring seen at 5
      to 10 standard errors), whose error allows for it; a star's brightness or the
      rings' flux fitted negative but within 3 standard errors of zero (beyond them
      the fit is flagged in `message`).
    - `variance_inflation`: the largest $1/(1 - R^2)$ over D, FOV (and sigma), $R$
      the multiple correlation of one with the other free parameters (NaN when D or
      FOV is held); above 1e9 the curvature is singular.
    - `seconds`: wall time, compile included.
    - `source_distance`: the `SourceDistance` the model placed the source at (None:
      at infinity). With it, `source_radius` (and `_err`: the source sphere's radius,
      R_S), `mass` and `mass_err` (solar masses; where the observer's distance was
      given), `observer_distance` and `observer_distance_err` (metres; where the
      mass was given), Quantities where the `SourceDistance` was given Quantities.
    - `transfer`: how a file's values were read: `"srgb"` (8/16-bit, decoded from sRGB
      to linear), `"linear"` (as stored; integer files normalised to [0, 1]); `None`
      for an array. `transfer_reason`: why that decoding ("tagged sRGB", "untagged:
      both decodings fitted, linear passed the residual test", ...; "" when none was
      given).
    - `pixels`: how the fit took the image's pixels to sample the light, `"area"` or
      `"point"` (`observe`'s `pixels`); `pixels_reason`: why.
    - `blur_variance`, `blur_z`: the score test of the model's blur: the extra
      Gaussian blur variance (pixels squared; negative: the image is sharper than the
      model) one step of the fit would add, with the free parameters' own share taken
      out, and its size in standard errors (about N(0, 1) where the model describes
      the image). Beyond 5 the fit is flagged naming the PSF: a blur that the fitted
      values take up (a ring blurred by 1 px without its PSF, fitted at D = 35 for 20)
      leaves residuals that pass `goodness`, but not this test. NaN where the image
      shows no pixel noise.
    - `goodness`: how far the residuals exceed the noise model, in standard deviations
      of their sum of squares (its own scatter and the estimated noise level's
      uncertainty: `AbstractNoise.excess`); above 5 the model does not describe the
      image and `message` says so with the likely cause; NaN where the image shows no
      pixel noise to judge by. `fits_noise` (property): at most 5.
    - `noise_trend`: how the residuals' scatter grows with the model's level, in standard
      deviations (the log ratio of their variance over the brightest and faintest thirds
      of the compared bins; about N(0, 1) where the noise model holds). A wrong decoding
      of a file's values makes it large; `fit` uses it to choose an untagged file's.
    - `residual_noise` (property): the residuals' standard deviation per compared pixel
      (data units), $\\sqrt{\\chi^2/\\mathrm{dof}}$ times `noise_sigma`; NaN under Poisson
      noise, whose level varies with the model. Where no pixel noise was found
      (`noise_seen` False) it is the misfit, not a noise, and `noise_sigma` the level
      of the image's fine structure, not its noise.
    - `noise_seen`: the noise level is a noise's: given, or estimated from an image
      that shows white pixel noise (False for a noiseless or smoothed image: its errors
      then measure the misfit, and `message` says so).

    Attribute shortcuts: `fit.<name>` and `fit.<name>_err` for every parameter in
    `values` (the error of one held fixed is 0), and `fit.<name>_deg`,
    `fit.<name>_deg_err` for an angle (degrees).
    """

    scene: object
    names: tuple
    values: dict
    errors: dict
    covariance: np.ndarray
    correlation: np.ndarray
    start: dict
    noise: str
    noise_sigma: float
    gain: float
    chi2_dof: float
    model: np.ndarray
    residuals: np.ndarray
    n_pixels: int
    block: int
    supersample: int
    result: object
    result_name: str
    num_steps: int
    variance_inflation: float
    converged: bool
    degenerate: bool
    message: str
    seconds: float
    transfer: str | None = None
    transfer_reason: str = ""
    goodness: float = math.nan
    noise_trend: float = math.nan
    pixels: str = "area"
    pixels_reason: str = ""
    blur_variance: float = math.nan
    blur_z: float = math.nan
    caveat: str = ""
    source_distance: SourceDistance | None = None
    noise_seen: bool = True

    @property
    def fits_noise(self) -> bool:
        """Whether the residuals are within the noise model's scatter: `goodness` at
        most `noise.GOODNESS_SIGMAS` (False where no noise was found to judge by)."""
        return bool(self.goodness <= GOODNESS_SIGMAS)

    def __getattr__(self, name):
        # fit.distance, fit.distance_err, fit.fov_deg, ...
        values, errors = self.__dict__["values"], self.__dict__["errors"]
        if name in values:
            return values[name]
        if name.endswith("_err") and name[:-4] in values:
            return errors.get(name[:-4], 0.0)  # held fixed: no error
        for suffix in ("_deg", "_deg_err"):
            base = name[: -len(suffix)] if name.endswith(suffix) else None
            if base in values and is_angle(base):
                v = values[base] if suffix == "_deg" else errors.get(base, 0.0)
                return math.degrees(v)
        raise AttributeError(name)

    @property
    def valid(self) -> bool:
        """Converged, not degenerate, and every check passed (`message` is empty)."""
        return bool(self.converged and not self.degenerate and not self.message)

    @property
    def residual_noise(self) -> float:
        """The residuals' standard deviation per compared pixel (data units): the noise
        the fit saw, $\\sqrt{\\chi^2/\\mathrm{dof}}$ times `noise_sigma`. NaN under
        Poisson noise (its level varies with the model: see `gain` and `chi2_dof`)."""
        if self.noise != "gaussian":
            return math.nan
        return math.sqrt(self.chi2_dof) * self.noise_sigma

    @property
    def source_radius(self) -> float:
        """The source sphere's radius (units of R_S): $R$ of `source_distance` at the
        fitted distance, `inf` for a source at infinity."""
        if self.source_distance is None:
            return math.inf
        return float(self.source_distance.radius_of(self.values["distance"]))

    @property
    def source_radius_err(self) -> float:
        """The standard error of `source_radius` (R_S): the distance's scaled where the
        radius follows it, else 0."""
        if self.source_distance is None:
            return 0.0
        return self.source_distance.linear()[0] * self.errors.get("distance", 0.0)

    def _scale(self, which: str):
        sd = self.source_distance
        d, e = self.values["distance"], self.errors.get("distance", 0.0)
        out = None
        if sd is not None:
            out = sd.mass_of(d, e) if which == "mass" else sd.observer_distance_of(d, e)
        if out is None:
            need = (
                "the observer's distance: fit with source_distance=SourceDistance("
                "behind=D_LS, observer=D_OL), or call mass_msun(distance_m)"
                if which == "mass"
                else "the mass: fit with source_distance=SourceDistance(behind=D_LS, "
                "mass=M), or call distance_m(mass_msun)"
            )
            raise ValueError(f"the fit does not measure the {which.replace('_', ' ')} "
                             f"without {need}")  # fmt: skip
        return out

    @property
    def mass(self):
        """The hole's mass (solar masses; a Quantity where the `SourceDistance` was
        given Quantities), from the fitted D and the given observer's distance:
        $M = D_{OL} / (D R_{S\\odot})$. `ValueError` where that distance was not
        given."""
        return self._scale("mass")[0]

    @property
    def mass_err(self):
        """The standard error of `mass` (its relative error is D's)."""
        return self._scale("mass")[1]

    @property
    def observer_distance(self):
        """The observer's (camera's) distance from the hole (metres; a Quantity where
        the `SourceDistance` was given Quantities): $D \\, R_S(M)$ from the given mass,
        or the given distance. `ValueError` where neither was given."""
        return self._scale("observer_distance")[0]

    @property
    def observer_distance_err(self):
        """The standard error of `observer_distance` (0 where it was given)."""
        return self._scale("observer_distance")[1]

    def distance_m(self, mass_msun: float) -> tuple[float, float]:
        """Camera distance in metres, and its standard error, for a hole of `mass_msun`
        (solar masses, or an astropy mass Quantity)."""
        rs = float(schwarzschild_radius_m(mass_msun))
        return self.values["distance"] * rs, self.errors.get("distance", 0.0) * rs

    def mass_msun(self, distance_m: float) -> tuple[float, float]:
        """Mass of the hole (solar masses) for a camera `distance_m` metres (or an
        astropy length Quantity) away."""
        m = float(mass_from_distance(self.values["distance"], distance_m))
        return m, m * self.errors.get("distance", 0.0) / self.values["distance"]

    def _given(self, mass_msun, distance_m) -> tuple[dict, list]:
        """The camera distance in metres for a given mass, the mass for a given camera
        distance: for `to_dict` and `summary` (nothing where the fit's `SourceDistance`
        measured one already: it is in both)."""
        sd = self.source_distance
        if sd is not None and sd.behind is not None:
            return {}, []
        out, lines = {}, []
        if mass_msun is not None:
            mass_msun = to_solar_masses(mass_msun, name="mass_msun")
            d_m, d_m_err = self.distance_m(mass_msun)
            out.update(mass_msun=mass_msun, distance_m=d_m, distance_m_err=d_m_err)
            lines.append(f"{'distance':<12} = {d_m:.6g} +- {d_m_err:.2g} m "
                         f"(mass {mass_msun:g} M_sun)")  # fmt: skip
        if distance_m is not None:
            distance_m = to_metres(distance_m, name="distance_m")
            m, m_err = self.mass_msun(distance_m)
            out.update(distance_m=distance_m, mass_msun=m, mass_msun_err=m_err)
            lines.append(f"{'mass':<12} = {m:.6g} +- {m_err:.2g} M_sun "
                         f"(distance {distance_m:g} m)")  # fmt: skip
        return out, lines

    def to_dict(self, *, mass_msun: float | None = None, distance_m: float | None = None) -> dict:
        """Plain values for JSON: every parameter and its `_err` (angles also in degrees
        as `<name>_deg`), and the verdict; with `mass_msun` (solar masses, or an astropy
        mass Quantity) also `distance_m` and its error (metres), with `distance_m` (the
        camera's distance: metres, or an astropy length Quantity) also `mass_msun` and
        its error, as `jaxlens fit --json` writes them."""
        out = {}
        for name, v in self.values.items():
            e = self.errors.get(name, 0.0)
            out[name], out[f"{name}_err"] = float(v), float(e)
            if is_angle(name):
                out[f"{name}_deg"], out[f"{name}_deg_err"] = math.degrees(v), math.degrees(e)
        out.update(
            valid=self.valid, converged=self.converged, degenerate=self.degenerate,
            message=self.message,
            noise=self.noise, noise_sigma=self.noise_sigma, gain=self.gain,
            chi2_dof=self.chi2_dof, residual_noise=self.residual_noise,
            n_pixels=self.n_pixels, block=self.block, supersample=self.supersample,
            result=self.result_name, num_steps=self.num_steps,
            variance_inflation=self.variance_inflation, seconds=self.seconds,
            transfer=self.transfer, transfer_reason=self.transfer_reason,
            goodness=self.goodness, noise_trend=self.noise_trend, pixels=self.pixels,
            pixels_reason=self.pixels_reason, blur_variance=self.blur_variance,
            blur_z=self.blur_z, caveat=self.caveat, noise_seen=self.noise_seen,
        )  # fmt: skip
        out.update(_scale_dict(self))
        out.update(self._given(mass_msun, distance_m)[0])
        return out

    def summary(self, *, mass_msun: float | None = None, distance_m: float | None = None) -> str:
        """A table of the parameters with their standard errors, the verdict, how a
        file's values were read (`transfer`, `transfer_reason`) and the message: the
        text report of `jaxlens fit` (which adds the file's name above it).

        **Arguments:** `mass_msun`: the hole's mass (solar masses, or an astropy mass
        Quantity), adding the camera distance in metres; `distance_m`: the camera's
        distance (metres, or an astropy length Quantity), adding the mass
        (`--mass-msun`, `--distance-m`; ignored where the fit's `SourceDistance`
        measured either)."""
        lines = []
        for name, v in self.values.items():
            unit = parameter(name).unit
            e = self.errors.get(name, 0.0)
            if is_angle(name):
                v, e, unit = math.degrees(v), math.degrees(e), "deg"
            tag = "" if name in self.names else "  (fixed)"
            lines.append(f"{name:<12} = {v:.6g} +- {e:.2g}{f' {unit}' if unit else ''}{tag}")
        verdict = "converged" if self.converged else "NOT converged"
        if self.degenerate:
            verdict += ", degenerate"
        if self.converged and not self.valid:
            verdict += ", FLAGGED (not a valid measurement)"
        noise = ""
        if self.noise == "gaussian":
            noise = f"residuals {self.residual_noise:.3g} per pixel"
        if math.isfinite(self.goodness):
            sep = ", " if noise else ""
            noise += f"{sep}{self.goodness:+.2g} standard deviations from the noise"
        noise = f"chi2/dof {self.chi2_dof:.3g}" + (f" ({noise})" if noise else "")
        if not self.noise_seen:
            # No noise level to print: chi2/dof and the residuals' scatter measure the
            # misfit (`message` says so).
            misfit = self.residual_noise if self.noise == "gaussian" else math.nan
            noise = "no pixel noise found" + (f", misfit {misfit:.3g} per pixel"
                                              if math.isfinite(misfit) else "")  # fmt: skip
        lines.append(
            f"{verdict}; {noise}; {self.n_pixels} pixels (bins "
            f"of {self.block}), k = {self.supersample}; {self.num_steps} steps; "
            f"{self.seconds:.1f} s"
        )
        if self.transfer is not None:
            how = "decoded from sRGB to linear" if self.transfer == "srgb" else "as stored"
            why = f"; {self.transfer_reason}" if self.transfer_reason else ""
            lines.append(f"transfer     = {self.transfer} ({how}{why})")
        if self.pixels != "area":
            lines.append(f"pixels       = {self.pixels} ({self.pixels_reason})")
        lines += _scale_lines(self)
        lines += self._given(mass_msun, distance_m)[1]
        if self.message:
            lines.append(self.message)
        if self.caveat:
            lines.append(f"caveat: {self.caveat}")
        return "\n".join(lines)


def _plain(x) -> float:
    """A float of a float or a Quantity (in the unit it is in: metres or M_sun)."""
    return float(getattr(x, "value", x))


def _scale_dict(fit: Fit) -> dict:
    """The source's placement and what it measures, as plain numbers for JSON:
    `source_radius` (R_S, null at infinity), `source_behind_m`, and `mass_msun`,
    `distance_m` with their errors where measured or given."""
    sd = fit.source_distance
    if sd is None:
        return {}
    out = {"source_radius": fit.source_radius, "source_radius_err": fit.source_radius_err}
    if sd.behind is not None:
        out["source_behind_m"] = sd.behind_m
    if sd.observer is not None:
        m, e = fit.mass, fit.mass_err
        out |= {"mass_msun": _plain(m), "mass_msun_err": _plain(e), "distance_m": sd.observer_m}
    if sd.mass is not None:
        d, e = fit.observer_distance, fit.observer_distance_err
        out |= {"distance_m": _plain(d), "distance_m_err": _plain(e), "mass_msun": sd.mass_msun}
    return out


def _scale_lines(fit: Fit) -> list:
    """The summary's lines of the source's placement and the mass or distance it
    measures."""
    sd = fit.source_distance
    if sd is None:
        return []
    r, r_err = fit.source_radius, fit.source_radius_err
    if sd.follows_distance:
        how = f"D x D_LS / D_OL, D_LS = {sd.behind_m:.6g} m, D_OL = {sd.observer_m:.6g} m"
        lines = [f"{'source R':<12} = {r:.6g} +- {r_err:.2g} R_S ({how})"]
        m, e = (_plain(v) for v in (fit.mass, fit.mass_err))
        lines.append(f"{'mass':<12} = {m:.6g} +- {e:.2g} M_sun")
        return lines
    if sd.radius is not None:
        return [f"{'source R':<12} = {r:.6g} R_S (fixed)"]
    how = f"D_LS = {sd.behind_m:.6g} m / R_S of {sd.mass_msun:.6g} M_sun"
    d, e = (_plain(v) for v in (fit.observer_distance, fit.observer_distance_err))
    return [
        f"{'source R':<12} = {r:.6g} R_S (fixed: {how})",
        f"{'distance':<12} = {d:.6g} +- {e:.2g} m (observer, mass {sd.mass_msun:.6g} M_sun)",
    ]
