"""Rendering: against an independent per-sample reference, the Einstein ring angle,
area sampling, panoramas at large distance, chunking, batches, memory, gradients."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens as jl
from jaxlens import (
    Camera,
    Exact,
    GaussianStar,
    Panorama,
    RayMap,
    Uniform,
    approach,
    block_memory,
    render,
    render_array,
    render_frames,
    rotation_matrix,
    shadow_angle,
    sky_directions,
    trace,
)

CHUNK_SAMPLES = 1 << 21  # render's default block size (area samples)

# One compiled table builder for the module (the distance is an argument). Tests that
# hand render_array a static camera's table pass one built here: render_array would
# build the same table inside each of its programs, recompiling RayMap.build every time.
_ray_map = eqx.filter_jit(RayMap.build)


@eqx.filter_jit
def _sky_eval(sky, n):
    return sky(n)


@jax.jit
def _exact_trace(alpha, distance):
    res = trace(alpha, distance, method=Exact())
    return res.phi, res.escaped


def reference_render(w, h, k, *, distance, fov, sky, yaw=0.0, pitch=0.0, roll=0.0,
                     azimuth=0.0, elevation=0.0):  # fmt: skip
    """An independent renderer, PHYSICS.md written out with NumPy: every sample's ray
    traced on its own with the exact closed form (`trace(..., method=Exact())`), its
    sky direction built from (Phi, beta), the same sky looked up, captured rays 0, the
    k x k samples averaged. No ray map, no symmetry, no coverage ramp.

    **Returns:** the image `(h, w, 3)` and the alpha of every sample `(h, w, k*k)`.
    """
    f = (w / 2) / math.tan(fov / 2)
    sub = (np.arange(k) + 0.5) / k
    col = (np.arange(w)[:, None] + sub).reshape(-1)  # sample columns
    row = (np.arange(h)[:, None] + sub).reshape(-1)
    x = np.broadcast_to(col[None, :] - w / 2, (h * k, w * k))
    y = np.broadcast_to(h / 2 - row[:, None], (h * k, w * k))
    d = np.stack([x, y, np.full_like(x, f)], -1) @ np.asarray(rotation_matrix(yaw, pitch, roll)).T
    alpha = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
    beta = np.arctan2(d[..., 1], d[..., 0])
    phi, escaped = _exact_trace(alpha, distance)
    phi = np.asarray(phi)
    n = np.stack([np.sin(phi) * np.cos(beta), np.sin(phi) * np.sin(beta), -np.cos(phi)], -1)
    n = n @ np.asarray(rotation_matrix(azimuth, elevation, 0.0)).T
    rad = np.asarray(_sky_eval(sky, jnp.asarray(n)))
    rad = np.where(np.asarray(escaped)[..., None], rad, 0.0)
    img = rad.reshape(h, k, w, k, 3).mean(axis=(1, 3))
    a = alpha.reshape(h, k, w, k).transpose(0, 2, 1, 3).reshape(h, w, k * k)
    return img, a


SKY = (
    GaussianStar(math.radians(4.0), 1.0)
    + GaussianStar(math.radians(6.0), 0.5, lon=math.radians(30.0), lat=math.radians(10.0))
    + Uniform(0.05)
)
SKY_MAX = 1.55  # no direction is brighter than the sum of the peaks and the floor


@pytest.mark.parametrize(
    "orient",
    [
        {},
        {"yaw": 0.15, "pitch": -0.1, "roll": 0.4},
        {"azimuth": 0.3, "elevation": 0.2},
    ],
    ids=["centred", "oriented", "orbit"],
)
def test_render_equals_per_sample_reference(orient):
    w, h, k, d, fov = 20, 14, 2, 8.0, math.radians(90.0)
    cam = Camera(d, fov, w, h, supersample=k, **orient)
    img = render(cam, SKY)
    ref, alpha = reference_render(w, h, k, distance=d, fov=fov, sky=SKY, **orient)
    # Samples within one sample width of the shadow edge are area-weighted by the
    # render and point-sampled by the reference; elsewhere both see the same rays.
    f = (w / 2) / math.tan(fov / 2)
    width = np.cos(alpha) ** 2 / (f * k) * 1.5  # a sample's extent in alpha, and margin
    straddle = np.abs(alpha - float(shadow_angle(d))) < width
    clear = ~straddle.any(axis=-1)
    assert clear.sum() > 0.8 * w * h and straddle.any()
    # Clear pixels: the ray map's 1e-8 rad times the sky's slope (< 20 per radian),
    # and the float32 output (6e-8 relative): 1e-6.
    np.testing.assert_allclose(img[clear], ref[clear], atol=1e-6, rtol=0)
    # Edge pixels differ at most by their straddling samples' share of the radiance.
    bound = straddle.sum(axis=-1) / k**2 * SKY_MAX + 1e-6
    assert np.all(np.abs(img - ref).max(axis=-1) <= bound)


def test_fast_path_equals_general_path_and_chunks_do_not_matter():
    # The centred fast path (mirrored halves, paired row blocks) against the general
    # per-sample path of render_array, odd and even sizes; blocks of any size give the
    # same pixels (identical arithmetic, so float32 output round-off only: 1e-7).
    rm = _ray_map(jnp.asarray(12.0), accuracy=1e-8)  # the table render builds for D = 12
    for w, h, k in [(21, 15, 3), (16, 12, 2)]:
        cam = Camera(12.0, math.radians(70.0), w, h, supersample=k)
        whole = render(cam, SKY)
        # A yaw of 1e-300 rad is no turn at all but forces the per-sample path.
        oriented = eqx.tree_at(lambda c: c.yaw, cam, jnp.asarray(1e-300))
        general = np.asarray(eqx.filter_jit(render_array)(oriented, SKY, ray_map=rm))
        np.testing.assert_allclose(whole, general, atol=1e-6)
        for chunk in (w * k * k, 5 * w * k * k + 3):
            np.testing.assert_allclose(render(cam, SKY, chunk_samples=chunk), whole, atol=1e-7)


@pytest.mark.parametrize("distance,ring_deg", [(10.0, 29.8283), (20.0, 20.2039)])
def test_einstein_ring_radius(distance, ring_deg):
    # A star exactly behind the hole: the image peaks where Phi = pi, the primary
    # Einstein ring (PHYSICS.md). One row of pixels through the hole; a parabola
    # through log(I) at the brightest pixel and its neighbours locates the peak to a
    # small fraction of a pixel: the cubic term of Phi over +-1 pixel (0.035 deg)
    # biases it by < 1e-4 deg. Tolerance 2e-3 deg (1/17 of a pixel).
    w, fov = 2000, math.radians(70.0)
    sigma = math.radians(0.3)
    cam = Camera(distance, fov, w, 1)
    img = render(cam, GaussianStar(sigma, 1.0))[0, :, 0].astype(np.float64)
    f = (w / 2) / math.tan(fov / 2)
    right = img[w // 2 :]
    i = int(np.argmax(right))
    ly = np.log(right[i - 1 : i + 2])
    offset = 0.5 * (ly[0] - ly[2]) / (ly[0] - 2 * ly[1] + ly[2])
    x = i + offset + 0.5  # pixel i of the right half is centred at x = i + 0.5
    assert math.degrees(math.atan(x / f)) == pytest.approx(ring_deg, abs=2e-3)
    assert right[i] > 0.99  # the ring reaches the star's peak brightness (1)


def test_supersampling_matches_a_brute_force_area_average():
    # The criterion: star behind the hole, 6 x 6 area samples against an
    # independent 30 x 30 point-sampled average: mean absolute difference below 0.3 %
    # of the peak. The small image (2.5 degrees a pixel) makes the 1-degree star's
    # ring and the shadow edge sub-pixel, where sampling matters most.
    w, h, d, fov = 24, 16, 20.0, math.radians(60.0)
    sky = GaussianStar(math.radians(1.0), 1.0)
    ref, _ = reference_render(w, h, 30, distance=d, fov=fov, sky=sky)
    mad = {
        k: np.abs(render(Camera(d, fov, w, h, supersample=k), sky) - ref).mean() / 1.0
        for k in (1, 6)
    }
    assert mad[6] < 3e-3
    assert mad[6] < mad[1] / 3  # and the test can tell sampling apart


def test_panorama_reduces_to_the_undistorted_panorama_far_away():
    # Far from the hole the deflection (2/b in the weak field, b = D sin(alpha)/sqrt(1 -
    # 1/D)) vanishes and the render is the panorama seen through a pinhole. The error
    # is at most the panorama's slope (its largest texel step over a texel, 0.05 rad)
    # times the largest deflection in the image (at the innermost pixel), and it falls
    # as 1/D.
    rng = np.random.default_rng(0)
    img = rng.random((64, 128, 3)).astype(np.float32)
    sky = Panorama(img)
    w, h, fov = 40, 30, math.radians(20.0)
    f = (w / 2) / math.tan(fov / 2)
    x = np.arange(w) + 0.5 - w / 2
    y = h / 2 - (np.arange(h) + 0.5)
    pinhole = np.stack(np.broadcast_arrays(x[None, :], y[:, None], f), -1)
    pinhole = pinhole / np.linalg.norm(pinhole, axis=-1, keepdims=True)
    direct = np.asarray(_sky_eval(sky, jnp.asarray(pinhole)))
    steps = [np.abs(np.diff(img, axis=a)).max() for a in (0, 1)]
    slope = max(steps) / (np.pi / 64) * math.sqrt(2)  # per radian, any direction
    alpha_min = math.atan(math.hypot(0.5, 0.5) / f)
    errors = []
    for d in (1e5, 1e7, 1e9):
        err = np.abs(render(Camera(d, fov, w, h), sky) - direct).max()
        deflection = 2.0 / (d * math.sin(alpha_min))
        assert err <= 1.1 * slope * deflection + 1e-6  # 1e-6: float32 output rounding
        errors.append(err)
    assert errors[1] < errors[0] / 50 and errors[2] < errors[1] / 50
    assert errors[2] < 1e-5


FRAME = Camera(20.0, math.radians(60.0), 12, 8, supersample=2)  # two frames: one program


def test_frames_are_one_batched_render():
    cams = approach(FRAME, [30.0, 10.0, 4.0])
    frames = render_frames(cams, SKY, chunk_samples=2 * 12 * 8 * 4)  # two frames a block
    assert frames.shape == (3, 8, 12, 3) and frames.dtype == np.float32
    for i, d in enumerate([30.0, 10.0, 4.0]):
        single = render(Camera(d, math.radians(60.0), 12, 8, supersample=2), SKY)
        np.testing.assert_allclose(frames[i], single, atol=1e-7)


def test_the_block_program_compiled_ahead_is_the_one_the_render_runs(jax_events):
    # render compiles its block program on a thread while the ray maps are built (the
    # two compiles overlap); the render must then find it compiled: one compile of
    # each program, not a second for the real ray maps.
    with jax_events("/jax/core/compile/backend_compile_duration") as compiled:
        cams = approach(Camera(20.0, math.radians(60.0), 14, 10, supersample=2), [30.0, 8.0])
        frames = render_frames(cams, SKY)  # a size no other test renders
    assert jl.plan(jl.Scene(cams, SKY)).geometry == "table"
    assert compiled.count("jit(_block_body)") == 1, compiled
    single = render(Camera(8.0, math.radians(60.0), 14, 10, supersample=2), SKY)
    np.testing.assert_allclose(frames[1], single, atol=1e-7)


def test_a_render_from_the_same_place_reuses_its_ray_map():
    from jaxlens import _raymap

    _raymap._tabulated_recent.cache_clear()
    cam = Camera(13.0, math.radians(50.0), 12, 8)
    first, again = render(cam, SKY), render(cam, SKY)
    moved = render(Camera(13.5, math.radians(50.0), 12, 8), SKY)
    info = _raymap._tabulated_recent.cache_info()
    assert (info.misses, info.hits) == (2, 1)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, moved)


def test_kept_programs_are_called_without_tracing_and_give_the_same_image(tmp_path, jax_events):
    # Where the CLI keeps its cache, the render's programs are kept compiled (their
    # executables): a later process calls them without tracing the renderer. A fresh
    # process is played by forgetting the programs and the ray maps held in memory.
    from jaxlens import _compile, _raymap, _render

    stored = (_render._block, _raymap._tabulated_compiled)

    def forget():
        for f in stored:
            f._kept.clear()
        _raymap._tabulated_recent.cache_clear()

    scene = jl.Scene(Camera(20.0, math.radians(50.0), 18, 12, supersample=2), SKY)
    direct = render(scene)
    _raymap._tabulated_recent.cache_clear()
    _compile.use_folder(tmp_path)
    try:
        with jax_events("/jax/core/compile/jaxpr_trace_duration") as traced:
            first = render(scene)
            kept = sorted((tmp_path / "jaxlens-programs").glob("*.executable"))
            assert len(kept) == 2, kept
            forget()
            traced.clear()
            again = render(scene)
            assert "_block_body" not in traced and "_tabulated_compiled" not in traced, traced
        # A damaged file is made again, not trusted.
        kept[0].write_bytes(b"not a program")
        forget()
        repaired = render(scene)
        assert kept[0].read_bytes() != b"not a program"
    finally:
        _compile.use_folder(None)
    for image in (first, again, repaired):
        np.testing.assert_array_equal(image, direct)


# A small float32 scene rendered in many blocks by the memory and the progress tests:
# one compiled block program for both.
SMALL_SKY = GaussianStar(np.float32(0.02)) + Uniform(np.float32(0.1))
SMALL_CAM = Camera(20.0, 1.0, 16, 10, dtype=jnp.float32)
SMALL_CHUNK = 16 * 2 * 2  # two mirrored row pairs a block: 3 blocks


def test_memory_is_bounded_by_the_block_size():
    # An 8192 x 8192 render is split into blocks of at most CHUNK_SAMPLES samples; XLA's
    # accounting of the compiled block (compiled, not run) is independent of the image
    # height and far below the 24 GiB budget; the output image itself is 0.8 GB.
    big = Camera(20.0, 1.0, 8192, 8192, supersample=2, dtype=jnp.float32)
    sky = SMALL_SKY
    plan = jl.plan(jl.Scene(big, sky))
    assert plan.samples <= CHUNK_SAMPLES and plan.rows < 8192 and plan.blocks > 1
    m_big = block_memory(big, sky)
    assert m_big["temp"] + m_big["output"] < 2 * 2**30
    # Any height runs the same compiled block (same plan, same shapes), so the same
    # memory: it does not grow with the image.
    shorter = jl.plan(jl.Scene(Camera(20.0, 1.0, 8192, 2048, supersample=2), sky))
    assert shorter.kernel_key() == plan.kernel_key() and shorter.samples == plan.samples
    # And a render in many small blocks equals the one-block render (rows and frames).
    cam = SMALL_CAM
    np.testing.assert_array_equal(render(cam, sky, chunk_samples=SMALL_CHUNK), render(cam, sky))


def test_progress_bar_on_request(capsys):
    assert jl.plan(jl.Scene(SMALL_CAM, SMALL_SKY), chunk_samples=SMALL_CHUNK).blocks > 1
    render(SMALL_CAM, SMALL_SKY, chunk_samples=SMALL_CHUNK, progress=True)
    assert "render" in capsys.readouterr().err
    render(SMALL_CAM, SMALL_SKY, chunk_samples=SMALL_CHUNK, progress=False)
    assert capsys.readouterr().err == ""


def test_render_array_gradients_match_finite_differences():
    # Gradient of a pixel sum with respect to the field of view and the position of a
    # star through the whole traceable render. Central differences of step 1e-6 on a
    # smooth sky: truncation ~1e-12, round-off ~1e-10 relative; the coverage ramp at
    # the shadow edge is piecewise linear and its kinks are not crossed at this step.
    # Tolerance 1e-5 relative. (The gradient with respect to the distance goes through
    # RayMap.build, checked in test_hard_cases and the fit's tests; here the distance is
    # fixed, so the table is an input built once, as render_array would build it.)
    rm = _ray_map(jnp.asarray(8.0), accuracy=1e-8)

    def loss(fov, lon, m):
        cam = Camera(8.0, fov, 12, 8, supersample=2)
        sky = GaussianStar(math.radians(4.0), 1.0, lon=lon) + Uniform(0.05)
        return jnp.sum(render_array(cam, sky, ray_map=m) ** 2)

    vg = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))  # one compiled program
    g = vg(1.2, 0.05, rm)[1]

    def f(fov, lon):
        return vg(fov, lon, rm)[0]

    h = 1e-6
    fd = [(f(1.2 + h, 0.05) - f(1.2 - h, 0.05)) / (2 * h),
          (f(1.2, 0.05 + h) - f(1.2, 0.05 - h)) / (2 * h)]  # fmt: skip
    for gi, fi in zip(g, fd):
        assert np.isfinite(float(gi))
        assert float(gi) == pytest.approx(float(fi), rel=1e-5)


def test_ray_map_in_float32_keeps_its_accuracy():
    d = 20.0
    rm = _ray_map(jnp.asarray(d), accuracy=1e-8)
    a_sh = float(rm.alpha_sh)
    alpha = a_sh + np.geomspace(1e-9, math.pi - a_sh - 1e-9, 4000)
    ev = eqx.filter_jit(lambda m, a: m.escape_angle(a))
    # float64 copy: the same table (astype to its own dtype changes nothing).
    np.testing.assert_array_equal(ev(rm.astype(jnp.float64), alpha), ev(rm, alpha))
    # float32: the error of phi over |d phi / d alpha| is the shift of the image on
    # the sky (radians of alpha); it must stay below 0.01 of a 1080p pixel at 60
    # degrees (5.5e-6 rad). The reference is the exact trace at the float32 alphas.
    a32 = alpha.astype(np.float32)
    a32 = a32[a32 > np.float32(a_sh)]
    view = rm.astype(jnp.float32)
    assert view.phi.dtype == jnp.float32 and view.tau.dtype == jnp.float32
    got = np.asarray(ev(view, jnp.asarray(a32)), np.float64)
    exact = np.asarray(_exact_trace(a32.astype(np.float64), d)[0])
    dphi = jax.jit(jax.vmap(jax.grad(lambda m, a: m.escape_angle(a), argnums=1), (None, 0)))
    slope = np.abs(np.asarray(dphi(rm, a32.astype(np.float64))))
    assert np.max(np.abs(got - exact) / slope) < 0.01 * math.radians(60.0) / 1920


def test_float32_sky_directions_match_float64():
    # The float32 hot path (polynomial atan2, sin and cos in place of XLA's scalar
    # ones) against the float64 path of the same camera, on samples clear of the
    # shadow edge (alpha > 1.01 alpha_sh, where |d phi / d alpha| < 60): the distance
    # between the two directions of a sample (the angle, for unit vectors) is the
    # float32 round-off of alpha (6e-8 rad) times that slope plus that of phi and the
    # direction: below 1e-5 rad (4e-6 seen); the coverage agrees to float32 round-off.
    for cam in (
        Camera(6.0, math.radians(120.0), 41, 29, supersample=2),
        Camera(6.0, math.radians(120.0), 41, 29, yaw=0.2, pitch=-0.1, roll=0.3),
    ):
        n32, c32 = sky_directions(cam, dtype=jnp.float32)
        n64, c64 = sky_directions(cam, dtype=jnp.float64)
        assert n32.dtype == np.float32 and n64.dtype == np.float64
        w, h, k = cam.width, cam.height, cam.supersample
        f = (w / 2) / math.tan(float(cam.fov) / 2)
        sub = (np.arange(k) + 0.5) / k
        x = (np.arange(w)[:, None] + sub).reshape(-1) - w / 2
        y = h / 2 - (np.arange(h)[:, None] + sub).reshape(-1)
        d = np.stack(np.broadcast_arrays(x[None, :], y[:, None], f), -1)
        d = d @ np.asarray(rotation_matrix(cam.yaw, cam.pitch, cam.roll)).T
        alpha = np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2])
        clear = alpha > 1.01 * float(shadow_angle(6.0))
        assert clear.mean() > 0.5
        gap = np.linalg.norm(n32.astype(np.float64) - n64, axis=-1)
        assert np.max(gap[clear]) < 1e-5
        assert np.abs(c32 - c64).max() < 1e-5


def test_sky_directions_are_unit_vectors_and_shadow_is_covered():
    cam = Camera(5.0, math.radians(90.0), 16, 12, supersample=2)
    n, cover = sky_directions(cam)
    assert n.shape == (24, 32, 3) and cover.shape == (24, 32)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-12)
    assert cover[12, 16] == 0.0 and cover[0, 0] == 1.0  # centre: captured; corner: sky


def test_render_array_rejects_a_batch_and_render_takes_it_as_frames():
    # Two frames of FRAME: the block program of test_frames_are_one_batched_render.
    cam = approach(FRAME, [10.0, 20.0])
    with pytest.raises(ValueError, match="one camera"):
        render_array(cam, SKY)
    assert render(cam, SKY).shape == (2, 8, 12, 3)


def test_render_under_jit_says_to_use_render_array():
    # `render` drives blocks from the host; traced, it says what to call instead
    # (the trace failed inside its checks with a TracerArrayConversionError before).
    with pytest.raises(TypeError, match="render_array"):
        jax.jit(lambda d: render(Camera(d, 1.0, 12, 8), SKY))(12.0)
    with pytest.raises(TypeError, match="render_array"):
        jax.grad(lambda d: render(Camera(d, 1.0, 12, 8), SKY).sum())(12.0)
