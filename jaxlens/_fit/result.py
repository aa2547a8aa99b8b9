"""The verdict of a fit: the solver's result by name, and whether an image fixes a
ring's D and FOV (`ring_verdict`)."""

import numpy as np
import optimistix as optx

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


def result_name(result) -> str:
    """The name of an optimistix `RESULTS` value ("successful", "max_steps_reached",
    ...; "failed" for one not listed)."""
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


def ring_verdict(names, values, errors, corr, shadow_seen: bool):
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
