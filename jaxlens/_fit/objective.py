"""The fit's objective: the model image of the compared bins for every parameter's
value, its residuals under the noise model, and the compiled programs that solve for
them (`solve`), evaluate the loss (`loss`) and re-weigh a point under a new noise
level (`renoised`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _kernel, _plan, _psf
from .._compile import program
from .._util import to_device
from .model import chunk_layout
from .noise import Gaussian, clipped_slope
from .observation import BOX_VARIANCE
from .params import apply, in_scene, parameter
from .solve import dense_least_squares, newton_decrement
from .table import escape_table, source_table

# The flux of the relativistic rings (order 1 and 2, radially a few thousandths of a
# pixel wide) is a nuisance factor `ring_flux` (1: the exact area average), with a
# Gaussian prior of this standard deviation about 1. Renderers that point-sample pixels
# alias these rings (k = 12 samples a pixel gave 55 % of the exact flux at D = 17, in a
# moire pattern), and a fit that trusted their flux was pulled 5 % in D on such images
# when sigma was fitted and no floor was seen; their positions, which fix D
# against the primary ring's radius, are still used.
RING_FLUX_PRIOR = 1.0


class Problem(eqx.Module):
    """Static description of a family of fits: every parameter of the model (`names`:
    the scene's, as `values_of` lists them, then `psf_sigma` with a Gaussian PSF and
    `ring_flux`), the bins' side and the model's settings. Which parameters are free
    and the held values are arguments (`Select`), so fits of one image size and model
    share their compiled programs."""

    names: tuple = eqx.field(static=True)
    block: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    pad: int = eqx.field(static=True)
    psf: str | None = eqx.field(static=True)  # None, "gaussian" or "image"
    knots: int = eqx.field(static=True)
    # With a PSF, each bin is rendered as `sub` x `sub` sub-bins, blurred at that
    # resolution and averaged (`psf_sub_bins`); 1 without one.
    sub: int = eqx.field(static=True)
    # The image's pixels are point samples (`Observation.pixels`): without a PSF each
    # is rendered by one node at its centre; a Gaussian PSF is narrowed by the
    # pixel's box (`BOX_VARIANCE`), which the model's area averages add.
    point: bool = eqx.field(static=True)
    # Yaw and pitch held at zero and no roll: the model's view is concretely unrotated
    # (a plan without the view rotation and its tangents, the edge's offsets exact in
    # the image plane), whose Jacobian compiles sooner.
    centred: bool = eqx.field(static=True)


class Select(eqx.Module):
    """Which of `Problem.names` are fitted and the values of the others: `index`
    (int, one an entry of theta: its position in `names`), `free` (bool, one a
    name), `internal` and `value` (one a name: the internal and the physical value;
    the held ones are used as they are). Fits freeing as many parameters share a
    program. (Padding theta with spare entries would share more, but each spare is
    one more tangent of the Jacobian: a ring fit's step took 30 % longer with one.)"""

    index: jax.Array
    free: jax.Array
    internal: jax.Array
    value: jax.Array


def select(names, free, values) -> Select:
    """The `Select` of the parameters `free` (physical `values` for every name)."""
    return Select(
        to_device([names.index(n) for n in free], jnp.int32),
        to_device([n in free for n in names]),
        to_device([parameter(n).transform.inverse(values[n]) for n in names]),
        to_device([float(values[n]) for n in names]),
    )


def internal(theta, sel: Select):
    return sel.internal.at[sel.index].set(theta)


def physical(u, sel: Select, prob: Problem):
    """Every parameter's physical value from the internal values `u` (`_internal`)."""
    return {n: jnp.where(sel.free[i], parameter(n).transform.forward(u[i]), sel.value[i])
            for i, n in enumerate(prob.names)}  # fmt: skip


class SourceSphere(eqx.Module):
    """The radius of the sphere the model's source lies on, $R = $ `slope` $\\cdot D$ +
    `offset` (units of R_S; `SourceDistance.linear`), arrays so that fits of sources
    at different distances share their programs."""

    slope: jax.Array
    offset: jax.Array


def source_sphere(source) -> SourceSphere | None:
    """The `SourceSphere` of a `SourceDistance` (None, a source at infinity: the model
    is then the one without it)."""
    if source is None:
        return None
    slope, offset = source.linear()
    return SourceSphere(to_device(slope, jnp.float64), to_device(offset, jnp.float64))


def model_table(distance, source: SourceSphere | None, knots: int):
    """The ray map of the model at `distance` (R_S): `escape_table`'s for a source at
    infinity, `source_table`'s for one on the sphere of `source`."""
    if source is None:
        return escape_table(distance, knots=knots)
    return source_table(distance, source.slope * distance + source.offset, knots=knots)


def model_image(p, scene, grid, otf, prob: Problem, source: SourceSphere | None = None):
    """Grey model of the compared bins (before clipping), data units, one value a bin:
    the fine bins then the coarse blocks (one rule of order k for both), or with a PSF
    the regular grid of bins, each rendered as `prob.sub` x `prob.sub` sub-bins on a
    margin, blurred, cropped and averaged (row-major); `p` the physical value of every
    parameter (`_physical`)."""
    # Concrete zeros, which the plan reads as no rotation: the model's camera is at the
    # origin of the sky's frame (`fit` places it there), and with `prob.centred` its
    # view is unrotated.
    zero = np.zeros((), scene.camera.dtype)
    fields = ["azimuth", "elevation"] + ["yaw", "pitch", "roll"] * prob.centred
    scene = eqx.tree_at(lambda s: [getattr(s.camera, n) for n in fields], scene,
                        [zero] * len(fields))  # fmt: skip
    p = {n: v for n, v in p.items() if n not in fields}
    scene = apply(scene, {n: v for n, v in p.items() if in_scene(n)})
    table = model_table(scene.camera.distance, source, prob.knots)
    plan = _plan.plan(scene)
    refs = _kernel.ring_references(table, table.phi.dtype)
    rf = p["ring_flux"]

    def render(x0, y0, side):
        n = x0.size
        count, per = chunk_layout(n, prob.k, 1 << 16)
        pad = count * per - n
        xs, ys, ss = (jnp.pad(jnp.broadcast_to(v, x0.shape).ravel(), (0, pad),
                              constant_values=1.0).reshape(count, per)
                      for v in (x0, y0, side))  # fmt: skip

        def one(xys):
            main, thin = _kernel.cells(scene, plan, table, *xys, prob.k, references=refs)
            return jnp.mean(main, -1) + rf * jnp.mean(thin, -1)

        return jax.lax.map(one, (xs, ys, ss)).reshape(-1)[:n]

    if prob.psf is None:
        # The fine bins and the coarse blocks in one pass (the side a cell).
        x0, y0, side = grid
        return render(x0, y0, side)
    x0, y0 = grid
    side = prob.block / prob.sub
    img = render(x0, y0, jnp.asarray(side)).reshape(x0.shape)
    if prob.psf == "gaussian":
        # The width is positive by its transform: the OTF without the run-time check,
        # whose host callback would keep the program out of the command line's cache.
        width = p["psf_sigma"]
        if prob.point:
            width = jnp.sqrt(jnp.maximum(width * width - BOX_VARIANCE, 1e-6))
        otf = _psf.gaussian_otf_unchecked(img.shape, width / side)
    img = _psf.convolve_psf(img, otf, pad=prob.pad * prob.sub)
    h, w = (n // prob.sub for n in img.shape)
    return img.reshape(h, prob.sub, w, prob.sub).mean(axis=(1, 3)).ravel()


class Data(eqx.Module):
    """What the residuals take besides the parameters: the model's scene, the compared
    bins' grid (`model_image`), the PSF's OTF for a PSF image (else None), each bin's
    mean `data` and `weight` (the square root of its pixels; 0: left out), the noise
    model with its level (`AbstractNoise.estimated`), the parameters' `Select` and the
    source's sphere (`SourceSphere`; None: at infinity)."""

    scene: object
    grid: tuple
    otf: object
    data: jax.Array
    weight: jax.Array
    noise: object
    sel: Select
    source: SourceSphere | None = None


def residuals_model(theta, d: Data, prob: Problem):
    """The residuals (noise units; a last one for the ring-flux prior, 0 when the flux
    is held) and the model."""
    u = internal(theta, d.sel)
    m = model_image(physical(u, d.sel, prob), d.scene, d.grid, d.otf, prob, d.source)
    r = d.noise.residuals(m, d.data, d.weight)
    i = prob.names.index("ring_flux")
    prior = jnp.where(d.sel.free[i], (u[i] - 1.0) / RING_FLUX_PRIOR, 0.0)
    return jnp.concatenate([r.ravel(), prior[None]]), m


def residuals(theta, d: Data, prob: Problem):
    return residuals_model(theta, d, prob)[0]


@program(profile="legacy_fusion_o1")
def solve(theta0, d: Data, prob: Problem, rtol, atol, max_steps):
    """`dense_least_squares` on the residuals, the model as its auxiliary output."""
    return dense_least_squares(
        lambda th: residuals_model(th, d, prob), theta0, rtol, atol, max_steps
    )


@program(profile="legacy_fusion_o1")
def loss(theta, d: Data, prob: Problem):
    return jnp.sum(residuals(theta, d, prob) ** 2)


@program(profile="legacy_fusion_o0_side")
def renoised(model, d: Data, new: Gaussian, r, jac, moved):
    """The residuals and Jacobian of a Gaussian fit's point (model `model` before
    clipping, residuals `r` and Jacobian `jac` under `d.noise`) under the noise `new`,
    and the Newton decrement under it at the point moved by `moved` (the solve's
    settling step; the residuals there to first order): what a pass with the new noise
    would still gain. The rows' derivatives of the model are the old rows' with the
    clipped slope and the noise scale changed (rows whose old slope is below 1e-6,
    clipped away, are dropped); the last residual, the ring-flux prior, is kept."""
    old = d.noise
    rows = new.residuals(model, d.data, d.weight)
    slope_old = clipped_slope(model, old.lo, old.hi, old.sigma)
    slope_new = clipped_slope(model, new.lo, new.hi, new.sigma)
    factor = jnp.where(slope_old > 1e-6, slope_new / jnp.maximum(slope_old, 1e-6), 0.0)
    factor = factor * old.scale / new.scale
    r = jnp.concatenate([rows.ravel(), r[-1:]])
    jac = jac * jnp.concatenate([factor.ravel(), jnp.ones(1, jac.dtype)])[:, None]
    return r, jac, newton_decrement(r + jac @ moved, jac)


# A fit of a clipped image with the noise estimated takes a second pass with the noise
# re-estimated from its residuals, unless the first pass's point gains less than this
# in chi^2 under the new noise (its Newton decrement): a step of 0.03 standard errors,
# three times the solver's own stop (`solve.SETTLED_CHI2`), well inside what the noise
# estimate itself is uncertain by. On the fit benchmark's first ring (400 x 300, the
# noise re-estimated 1.3 % lower) the decrement was 2.3e-4 and the second pass moved
# D by 0.004 and the rings' flux by 0.01 standard errors, in three more steps.
RENOISED_CHI2 = 1e-3


def renoise_placeholders(d: Data, n_theta: int):
    """Arguments of the shapes `renoised` takes for `d` (to compile it ahead)."""
    shape = d.data.shape
    n = int(np.prod(shape)) + 1
    model, r, jac, moved = (to_device(np.zeros(v)) for v in (shape, n, (n, n_theta), n_theta))
    return (renoised, model, d, d.noise, r, jac, moved)


def solve_passes(theta0, d: Data, prob: Problem, free, *, rtol, atol, max_steps,
                 report=None):  # fmt: skip
    """Levenberg-Marquardt from `theta0`; where the noise model is `reestimated`, its
    level is re-estimated from the first pass's residuals well inside the clipping
    range and a second pass runs only if the new noise moves the optimum
    (`RENOISED_CHI2`). Each pass told to `report` (a `Progress`) where given: its
    steps and the chi^2 of its last point.

    **Returns:** `(theta, r, jac, model, result, steps, noise)`: the residuals at
    `theta` to first order from the point the solve evaluated last (its Jacobian
    stands for theta's), and the noise model they are in units of."""
    settings = (to_device(rtol), to_device(atol), int(max_steps))
    passes, steps = 2 if d.noise.reestimated else 1, 0
    for i in range(passes):
        if report is not None:
            report(f"solving, pass {i + 1} (Levenberg-Marquardt, at most {max_steps} steps)")
        theta, r, jac, model, result, taken, moved = solve(to_device(theta0), d, prob, *settings)
        steps += int(taken)
        if report is not None:
            chi2 = float(np.sum(np.square(np.asarray(r))))
            report(f"solving, pass {i + 1}: {int(taken)} steps, chi2 {chi2:.4g}")
        if i + 1 < passes:
            new = _residual_noise(np.asarray(model), d)
            if new is None:
                break
            r2, jac2, dec = renoised(model, d, new, r, jac, moved)
            d = eqx.tree_at(lambda x: x.noise, d, new)
            if float(dec) < RENOISED_CHI2:
                r, jac = r2, jac2
                break
            theta0 = np.asarray(theta)
    r, jac = np.asarray(r).ravel(), np.asarray(jac)
    jac = jac.reshape(r.size, -1)
    r = r + jac @ np.asarray(moved)
    return np.asarray(theta), r, jac, np.asarray(model), result, steps, d.noise


def _residual_noise(model, d: Data):
    """A clipped image's noise re-estimated from the residuals of bins well inside the
    clipping range, within [0.7, 1.5] of the image's own estimate (a model far from the
    image, a floor below the sky's whose clipped mean a larger noise then explains,
    must not buy a smaller chi^2 by a larger noise: seen noise x 3, floor 0 for 0.05,
    chi^2/dof 0.1); `None` with 50 such bins or fewer."""
    noise = d.noise
    lo, hi, sigma = float(noise.lo), float(noise.hi), float(noise.sigma)
    count = np.asarray(d.weight) ** 2
    inside = (count > 0) & (model > lo + 4 * sigma) & (model < hi - 4 * sigma)
    if inside.sum() <= 50:
        return None
    refit = float(np.std((np.asarray(d.data) - model)[inside] * np.sqrt(count[inside])))
    level = min(max(refit, 0.7 * sigma), 1.5 * sigma)
    return noise.with_level(level, lo, hi, float(np.max(np.abs(d.data))), float(noise.rel))
