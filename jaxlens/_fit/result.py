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
# that ring's flux is seen at fewer than _RING_SEEN standard errors the fit is
# degenerate: on the fit benchmark's D = 17 ring (0.7-3.1 errors over eight noise
# draws) D's pulls reached 3.7, and on its D = 40, FOV 90 deg ring (3.8-4.5, four
# draws) 2.2. Between _RING_SEEN and _RING_SIGNIFICANCE the values and errors
# stand, with a caveat that names the feature: on the D = 40 ring at 5.6-6.1 errors,
# four noise draws, the pulls were 0.04, -1.2, -1.4 and 0.58. A floor counts as seen
# above _EDGE_SIGNIFICANCE errors.
_RING_SEEN = 5.0
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
    relativistic ring (its flux above 5 errors) separating D from FOV and sigma.

    **Returns:** `(degenerate, note, vif, caveat)`: the note ("" when not degenerate),
    the largest variance inflation, and a caveat on a fit that is not degenerate but
    whose D rests on the relativistic ring seen at 5 to 10 errors ("" otherwise).
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
        return True, why, vif, ""
    edge_seen = shadow_seen or (
        "floor" in names and values["floor"] > _EDGE_SIGNIFICANCE * errors["floor"]
    )
    if not fit_sigma or edge_seen or "ring_flux" not in names:
        return False, "", vif, ""
    seen = values["ring_flux"] / errors["ring_flux"] if errors["ring_flux"] > 0 else np.inf
    if seen >= _RING_SIGNIFICANCE:
        return False, "", vif, ""
    what = (f"sigma is unknown, no shadow edge is visible against a floor, and the relativistic "
            f"ring is seen at {seen:.2g} standard errors: only it separates D from FOV and "
            f"sigma, so D = {d:.4g} +- {errors['distance']:.2g} rests on a faint, sub-pixel "
            "feature")  # fmt: skip
    if seen >= _RING_SEEN:
        return False, "", vif, f"{what}; its error allows for that (seen at {_RING_SEEN:g} or more)"
    advice = ("pass star_sigma (fix sigma), or use an image with a visible shadow edge or less "
              "noise")  # fmt: skip
    return True, f"{what} (below {_RING_SEEN:g}): {advice}", vif, ""
