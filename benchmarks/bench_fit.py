"""Benchmark: fitting D and FOV to Einstein rings made by an independent renderer.

    .venv/bin/python benchmarks/bench_fit.py [--only rings|arcs|files|speed] [--cases N]
        [--keep DIR]
    .venv/bin/python benchmarks/bench_fit.py --render-only [--cases N] [--keep DIR]

Writes benchmarks/results/fit.md and fit.json. Each image is rendered here by a
renderer that shares no code with jaxlens: the escape angle from scipy quadrature of the
orbit integral (the turning-point singularity removed by u = u_p - s^2), splined in
ln(alpha - alpha_sh), and every pixel averaged over 12 x 12 samples (PHYSICS.md's pixel
convention). Each fit is one fresh `jaxlens fit IMAGE --json` process with the
persistent compile cache switched off, so its wall time includes starting Python,
importing JAX and compiling.

Four sections, one report:

- **Rings** (`CASES`): a Gaussian star exactly behind the hole. Gaussian noise is added,
  the image clipped to [0, 1] and stored as an 8- or 16-bit grey PNG (linear values, no
  sRGB transfer, tagged linear so that the fit reads them as stored). The cases cover
  the issue's held-out range: D from 12 to 40, FOV from 40 to 90 deg, 8- and 16-bit
  PNGs, noise, with and without a floor, the star's width given or fitted, images from
  256 x 256 to 800 x 600.
- **General cases** (`ARC_CASES`): a star off the axis at (lon, lat), 0.3 to 4.1 deg
  from it (lon > 0 right, lat > 0 up; a sample's ray leaves along n = -cos(Phi) f +
  sin(Phi) (cos(psi) e_x + sin(psi) e_y), psi its image azimuth), so two arcs; some with
  a Gaussian point-spread function of 1 to 2 px (rendered with a margin of ceil(5 S) px
  at the same focal length, blurred by `scipy.ndimage.gaussian_filter`, cropped: light
  from beyond the frame spreads into it), Gaussian noise or Poisson counts (value =
  Poisson(gain x clean) / gain, the gain left for the fit to estimate), rings wider than
  the frame's height in most; D from 15 to 200, FOV from 12 to 70 deg, 256 x 192 to
  640 x 480. The fit gets `--psf-sigma-px`, `--noise poisson` and `--star-sigma-deg` as
  the case says. The report adds the source position's error and the pulls of lon, lat.

- **Files as users have them** (`FILE_SCENES` x `FILE_CASES`): the rings above stored
  the way other software stores them, not tagged for the fit. Linear values in an
  untagged 8- or 16-bit grey PNG (no sRGB, gAMA or iCCP chunk: what numpy, Pillow and
  camera pipelines write), written byte by byte by `tests/user_images.py`'s own PNG
  writer, fitted with `--transfer linear` and with the default (auto, which must fit
  them right or say that it cannot tell); and the files `jaxlens render` writes itself
  of the same ring (its sRGB-tagged 8-bit PNG and its linear float EXR, no noise but
  the PNG's quantisation), fitted with the default. The report says which decoding the
  fit used and why, and counts the fits that are valid but off by more than 1 %: the
  silent failures.

- **Speed**: the CPU time of a fit of a 320 x 240 ring, in a cold `jaxlens fit` process
  (compile cache off) and warm in one process, against the goals (5 and 1 CPU-s).

`--only rings|arcs|files|speed` runs one section; the other sections' rows are then taken
from the existing fit.json (where it has them: rows without a "section" key are rings) and
reported again under a note that they were not run this time, so a one-section run
leaves a complete report. `--cases N` runs the first N cases of each section run.
`--render-only` renders the general cases' clean images at 3 x 3 samples a pixel (a few
seconds each), writes their noisy PNGs and prints (peak - floor) / noise, the Einstein
ring's angle and the frame's half-height and half-width: no fits, no report.
"""

import argparse
import json
import math
import os
import pathlib
import subprocess
import sys
import tempfile
import time
import warnings

import _common
import numpy as np
import OpenImageIO as oiio
from scipy.integrate import IntegrationWarning, quad
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter
from scipy.optimize import brentq

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = _common.RESULTS  # or $JAXLENS_BENCH_RESULTS
B_C = 1.5 * math.sqrt(3.0)
# quad warns on the innermost knots (alpha - alpha_sh ~ 1e-9 alpha_sh, Phi ~ 20 rad), whose
# relative error is still ~1e-9 there (checked against `trace`) and whose area is ~0.
warnings.simplefilter("ignore", IntegrationWarning)

# (D, FOV deg, width, height, sigma deg, brightness, floor, noise, bits, sigma given)
CASES = [
    (12.0, 90.0, 400, 300, 1.5, 0.8, 0.05, 0.01, 16, True),
    (12.0, 70.0, 640, 480, 1.0, 0.9, 0.00, 0.02, 8, True),
    (15.0, 60.0, 512, 512, 2.0, 0.7, 0.10, 0.01, 8, False),
    (17.0, 80.0, 320, 240, 1.2, 0.8, 0.00, 0.005, 16, False),
    (20.0, 60.0, 800, 600, 1.5, 0.8, 0.05, 0.02, 16, True),
    (20.0, 45.0, 256, 256, 1.0, 0.6, 0.02, 0.01, 8, False),
    (25.0, 50.0, 640, 480, 0.8, 0.9, 0.10, 0.01, 16, False),
    (25.0, 90.0, 400, 300, 2.0, 0.8, 0.00, 0.01, 8, True),
    (30.0, 40.0, 512, 384, 1.0, 0.8, 0.05, 0.015, 8, True),
    (30.0, 70.0, 640, 480, 1.5, 0.7, 0.08, 0.01, 16, False),
    (35.0, 55.0, 400, 400, 1.2, 0.8, 0.00, 0.01, 16, True),
    (40.0, 40.0, 640, 480, 0.7, 0.9, 0.05, 0.01, 8, False),
    (40.0, 60.0, 320, 240, 1.5, 0.8, 0.10, 0.02, 16, True),
    (40.0, 90.0, 800, 600, 2.5, 0.8, 0.00, 0.005, 8, False),
]


# General cases: (D, FOV deg, width, height, star lon deg, lat deg, sigma deg, brightness,
# floor, PSF sigma px (0: none), noise, bits, sigma given); noise is a Gaussian sigma or
# ("poisson", gain in counts per unit). Each comment: what the case is for, and the
# Einstein ring's angle against the frame's half-height (deg); "cut" when it is wider.
ARC_CASES = [
    # near the hole, wide view, two arcs well inside the frame (ring 23.7, frame 27.7)
    (15.0, 70.0, 640, 480, 3.0, 2.0, 1.0, 0.8, 0.05, 0, 0.01, 16, True),
    # negative lon only; Poisson, 8-bit, PSF 1.5 px, sigma fitted (20.2, 23.4)
    (20.0, 60.0, 512, 384, -3.0, 0.0, 1.0, 0.7, 0.03, 1.5, ("poisson", 1000.0), 8, False),
    # lat only, no floor (no shadow edge: sigma given), PSF 1 px (17.9, 17.3: cut)
    (25.0, 45.0, 400, 300, 0.0, 1.5, 1.2, 0.9, 0.0, 1.0, 0.01, 16, True),
    # the largest offset, 4.1 deg: short arcs, bright floor, 8-bit, sigma fitted (16.2, 15.3: cut)
    (30.0, 40.0, 320, 240, 4.0, -1.0, 1.0, 0.8, 0.1, 0, 0.02, 8, False),
    # the smallest offset, 0.3 deg: a nearly full ring; Poisson, PSF 2 px (13.9, 13.7: cut)
    (40.0, 36.0, 640, 480, 0.2, 0.22, 0.8, 0.75, 0.02, 2.0, ("poisson", 2000.0), 16, True),
    # up and left, arcs near the frame's top; PSF 1.2 px, 8-bit, sigma fitted (11.2, 11.4)
    (60.0, 30.0, 400, 300, -1.5, 1.5, 0.6, 0.85, 0.05, 1.2, 0.01, 8, False),
    # far camera, narrow view; Poisson at a low gain on a bright floor (8.5, 7.5: cut)
    (100.0, 20.0, 320, 240, 0.8, 0.0, 0.4, 0.7, 0.1, 0, ("poisson", 800.0), 16, True),
    # the smallest image, 256 x 192, no floor, 8-bit, PSF 1 px (6.9, 6.0: cut)
    (150.0, 16.0, 256, 192, 0.5, -0.5, 0.3, 0.9, 0.0, 1.0, 0.015, 8, True),
    # the farthest camera and narrowest view, the arcs in the corners; sigma fitted (5.9, 4.5: cut)
    (200.0, 12.0, 640, 480, 0.25, 0.25, 0.2, 0.85, 0.05, 1.5, 0.01, 8, False),
    # Poisson with no floor (zero counts off the arcs), negative lon and lat (7.7, 6.8: cut)
    (120.0, 18.0, 480, 360, -1.0, -0.5, 0.35, 0.8, 0.0, 0, ("poisson", 600.0), 16, True),
]

# Files as users have them. Scenes: (D, FOV deg, width, height, sigma deg (given to the
# fit), brightness, floor, noise); the noise is added to the PNGs written here, not to
# `jaxlens render`'s files. Cases: (how the file is made, bits, --transfer): "png" is
# linear values in an untagged grey PNG (`user_images.write_png`, no colour chunk);
# "render-png" / "render-exr" are `jaxlens render`'s own sRGB PNG and float EXR; "auto"
# is the default (no --transfer given).
FILE_SCENES = [
    (20.0, 60.0, 320, 240, 1.5, 0.8, 0.05, 0.01),
    (35.0, 45.0, 400, 300, 1.0, 0.8, 0.00, 0.005),
]
FILE_CASES = [
    ("png", 8, "linear"),
    ("png", 8, "auto"),
    ("png", 16, "linear"),
    ("png", 16, "auto"),
    ("render-png", 8, "auto"),
    ("render-exr", 32, "auto"),
]

# ------------------------------------------------------------ independent renderer


def _g(u, b):
    return 1.0 / b**2 - u * u + u**3


def _to_turning_point(a, up, b):
    """int_a^up du / sqrt(G(u)), with u = up - s^2 (finite integrand at s = 0)."""
    top = math.sqrt(max(up - a, 0.0))

    def f(s):
        return (
            2.0 * s / math.sqrt(max(_g(up - s * s, b), 1e-300))
            if s > 0
            else (
                2.0 / math.sqrt(3.0 * up * up - 2.0 * up)  # limit: 2 / sqrt(-G'(up))
            )
        )

    return quad(f, 0.0, top, epsabs=1e-13, epsrel=1e-12, limit=400)[0]


def escape_angle(alpha, d):
    """Phi(alpha) for a static camera at D > 1.5 on an escaping ray (scipy quadrature)."""
    u0 = 1.0 / d
    b = d * math.sin(alpha) / math.sqrt(1.0 - u0)
    if alpha >= 0.5 * math.pi:
        return quad(lambda u: 1.0 / math.sqrt(_g(u, b)), 0.0, u0, epsabs=1e-13)[0]
    up = brentq(lambda u: _g(u, b), 0.0, 2.0 / 3.0, xtol=1e-16, rtol=1e-15)
    return _to_turning_point(0.0, up, b) + _to_turning_point(u0, up, b)


def shadow_alpha(d):
    return math.asin(B_C * math.sqrt(1.0 - 1.0 / d) / d)


def phi_spline(d, a_max):
    """Phi as a cubic spline in ln(alpha - alpha_sh), 3000 knots up to alpha = a_max."""
    a_sh = shadow_alpha(d)
    tau = np.linspace(math.log(1e-9 * a_sh), math.log(a_max - a_sh), 3000)
    phi = np.array([escape_angle(a_sh + math.exp(t), d) for t in tau])
    return CubicSpline(tau, phi)


def ring_image(d, fov, w, h, sigma, amp, floor, k=12):
    """Area-averaged image (k x k samples a pixel) of a Gaussian star behind the hole."""
    f = (w / 2) / math.tan(fov / 2)
    a_sh = shadow_alpha(d)
    spline = phi_spline(d, math.atan(math.hypot(w, h) / 2 / f) + 1e-3)
    sub = (np.arange(k) + 0.5) / k
    x = (np.arange(w)[:, None] + sub[None, :]).ravel() - w / 2
    img = np.empty((h, w))
    for j in range(h):
        y = h / 2 - (j + sub)
        alpha = np.arctan(np.hypot(x[None, :], y[:, None]) / f)
        t = np.log(np.maximum(alpha - a_sh, 1e-9 * a_sh))
        sep = np.abs(np.mod(spline(t), 2 * math.pi) - math.pi)
        val = np.where(alpha > a_sh, amp * np.exp(-0.5 * (sep / sigma) ** 2) + floor, 0.0)
        img[j] = val.reshape(k, w, k).mean(axis=(0, 2))
    return img


def sky_direction(lon, lat):
    """Unit vector (components along f, e_x, e_y) at longitude lon, latitude lat (rad)."""
    return np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])


def arc_image(d, fov, w, h, sigma, amp, floor, lon, lat, margin=0, k=12):
    """Area-averaged image (k x k samples a pixel) of a Gaussian star at (lon, lat), on a
    frame enlarged by `margin` pixels on every side at the same focal length, so
    `(h + 2 margin, w + 2 margin)`.

    A sample at (x, y) looks at alpha = atan(hypot(x, y) / f_px) from the hole, image
    azimuth psi = atan2(y, x); its ray leaves along n = -cos(Phi) f + sin(Phi) (cos(psi)
    e_x + sin(psi) e_y) (Phi = pi: exactly behind the hole) and sees the star at the
    angle atan2(|n x s|, n . s) from its centre.
    """
    f = (w / 2) / math.tan(fov / 2)
    ww, hh = w + 2 * margin, h + 2 * margin
    a_sh = shadow_alpha(d)
    spline = phi_spline(d, math.atan(math.hypot(ww, hh) / 2 / f) + 1e-3)
    s0, s1, s2 = sky_direction(lon, lat)
    sub = (np.arange(k) + 0.5) / k
    x = (np.arange(ww)[:, None] + sub[None, :]).ravel()[None, :] - ww / 2
    img = np.empty((hh, ww))
    for j in range(hh):
        y = (hh / 2 - (j + sub))[:, None]
        rho = np.hypot(x, y)
        alpha = np.arctan(rho / f)
        phi = spline(np.log(np.maximum(alpha - a_sh, 1e-9 * a_sh)))
        n0, sp = -np.cos(phi), np.sin(phi) / np.maximum(rho, 1e-300)
        n1, n2 = sp * x, sp * y
        cross = np.sqrt((n1 * s2 - n2 * s1) ** 2 + (n2 * s0 - n0 * s2) ** 2
                        + (n0 * s1 - n1 * s0) ** 2)  # fmt: skip
        sep = np.arctan2(cross, n0 * s0 + n1 * s1 + n2 * s2)
        val = np.where(alpha > a_sh, amp * np.exp(-0.5 * (sep / sigma) ** 2) + floor, 0.0)
        img[j] = val.reshape(k, ww, k).mean(axis=(0, 2))
    return img


def einstein_alpha(d):
    """The Einstein ring's angle from the hole: Phi(alpha) = pi (rad)."""
    a_sh = shadow_alpha(d)
    return brentq(lambda a: escape_angle(a, d) - math.pi, 1.001 * a_sh, 1.2, xtol=1e-14)


def write_png(path, img, bits):
    top = 255 if bits == 8 else 65535
    q = np.clip(np.round(img * top), 0, top).astype(np.uint8 if bits == 8 else np.uint16)
    out = oiio.ImageOutput.create(str(path))
    spec = oiio.ImageSpec(q.shape[1], q.shape[0], 1, oiio.UINT8 if bits == 8 else oiio.UINT16)
    spec.attribute("oiio:ColorSpace", "linear")  # gAMA 1.0: the fit reads it as stored
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(q[..., None]))
    out.close()


# ---------------------------------------------------------------------------- run


def fit_file(path, sigma_deg, extra=()):
    """One fresh `jaxlens fit PATH --json [--star-sigma-deg S] [extra...]` process."""
    # The `jaxlens` entry point of the environment running this script.
    argv = [str(pathlib.Path(sys.executable).with_name("jaxlens")), "fit", str(path), "--json"]
    if sigma_deg is not None:
        argv += ["--star-sigma-deg", repr(sigma_deg)]
    argv += list(extra)
    env = dict(os.environ, JAXLENS_CACHE_DIR="")
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1]}, wall
    return json.loads(done.stdout.strip().splitlines()[-1]), wall


def run_rings(n, folder):
    rows = []
    rng = np.random.default_rng(2026)
    for i, (d, fov, w, h, sig, amp, floor, noise, bits, given) in enumerate(CASES[:n]):
        t0 = time.perf_counter()
        clean = ring_image(d, math.radians(fov), w, h, math.radians(sig), amp, floor)
        t_render = time.perf_counter() - t0
        path = folder / f"ring{i:02d}.png"
        write_png(path, clean + noise * rng.standard_normal(clean.shape), bits)
        out, wall = fit_file(path, sig if given else None)
        row = dict(section="rings", case=i, d=d, fov=fov, w=w, h=h, sig=sig, floor=floor,
                   noise=noise, bits=bits, given=given, wall=wall, render=t_render,
                   fit=out)  # fmt: skip
        rows.append(row)
        if "error" in out:
            print(f"ring {i}: error {out['error']}", flush=True)
            continue
        print(
            f"ring {i}: D {out['distance']:.4f}+-{out['distance_err']:.2g} (true {d}), "
            f"FOV {out['fov_deg']:.4f}+-{out['fov_deg_err']:.2g} (true {fov}), "
            f"{out['num_steps']} steps, {wall:.1f} s, degenerate={out['degenerate']}",
            flush=True,
        )
    return rows


def arc_frame(case, k=12):
    """The clean frame of an arc case (the PSF applied, cropped) and the time it took."""
    d, fov, w, h, lon, lat, sig, amp, floor, psf, _noise, _bits, _given = case
    t0 = time.perf_counter()
    margin = math.ceil(5 * psf) if psf else 0
    big = arc_image(d, math.radians(fov), w, h, math.radians(sig), amp, floor,
                    math.radians(lon), math.radians(lat), margin=margin, k=k)  # fmt: skip
    if psf:
        big = gaussian_filter(big, psf, mode="nearest", truncate=6)[margin:-margin, margin:-margin]
    return big, time.perf_counter() - t0


def peak_to_noise(clean, floor, noise):
    """(Brightest pixel - floor) / the noise at that pixel (Poisson: sqrt(peak / gain))."""
    peak = float(clean.max())
    sd = math.sqrt(peak / noise[1]) if isinstance(noise, tuple) else noise
    return (peak - floor) / sd


def frame_check(case):
    """The Einstein ring's angle and the frame's half-height and half-width (deg)."""
    d, fov, w, h = case[:4]
    half_w = math.radians(fov) / 2
    half_h = math.atan(h / w * math.tan(half_w))
    return math.degrees(einstein_alpha(d)), math.degrees(half_h), math.degrees(half_w)


def run_arcs(n, folder, render_only=False):
    rows = []
    for i, case in enumerate(ARC_CASES[:n]):
        d, fov, w, h, lon, lat, sig, amp, floor, psf, noise, bits, given = case
        rng = np.random.default_rng([2027, i])
        clean, t_render = arc_frame(case, k=3 if render_only else 12)
        snr = peak_to_noise(clean, floor, noise)
        if isinstance(noise, tuple):
            data = rng.poisson(noise[1] * clean) / noise[1]
        else:
            data = clean + noise * rng.standard_normal(clean.shape)
        path = folder / f"arc{i:02d}.png"
        write_png(path, data, bits)  # clipped to [0, 1] there
        if render_only:
            ring, half_h, half_w = frame_check(case)
            print(f"arc {i}: peak {clean.max():.3f}, (peak - floor) / noise {snr:.0f}, "
                  f"Einstein ring {ring:.2f} deg, frame half-height {half_h:.2f}, half-width "
                  f"{half_w:.2f} deg, share above 1 {np.mean(data > 1):.1e}, "
                  f"{t_render:.1f} s -> {path}", flush=True)  # fmt: skip
            continue
        extra = ["--psf-sigma-px", repr(psf)] if psf else []
        if isinstance(noise, tuple):
            extra += ["--noise", "poisson"]
        out, wall = fit_file(path, sig if given else None, extra)
        row = dict(section="arcs", case=i, d=d, fov=fov, w=w, h=h, lon=lon, lat=lat, sig=sig,
                   amp=amp, floor=floor, psf=psf,
                   noise="poisson" if isinstance(noise, tuple) else noise,
                   gain=noise[1] if isinstance(noise, tuple) else None, bits=bits, given=given,
                   snr=snr, wall=wall, render=t_render, argv=extra, fit=out)  # fmt: skip
        rows.append(row)
        if "error" in out:
            print(f"arc {i}: error {out['error']}", flush=True)
            continue
        print(
            f"arc {i}: D {out['distance']:.4f}+-{out['distance_err']:.2g} (true {d}), "
            f"FOV {out['fov_deg']:.4f}+-{out['fov_deg_err']:.2g} (true {fov}), "
            f"lon {out['source_lon_deg']:.4f}+-{out['source_lon_deg_err']:.2g} (true {lon}), "
            f"lat {out['source_lat_deg']:.4f}+-{out['source_lat_deg_err']:.2g} (true {lat}), "
            f"{out['num_steps']} steps, {wall:.1f} s, converged={out['converged']}, "
            f"degenerate={out['degenerate']}",
            flush=True,
        )
    return rows


def user_file(kind, bits, scene, clean, rng, folder, name):
    """The file of one `FILE_CASES` case: `(path, seconds to make it)`.

    "png": `clean` plus Gaussian noise, quantised (clipped to [0, 1]) and written as an
    untagged grey PNG by `user_images.write_png`; "render-png" / "render-exr": `jaxlens
    render --sky star` of the scene (area-exact Gauss-Legendre cells, 8 x 8 a pixel,
    float64), in a fresh process."""
    import user_images

    d, fov, w, h, sig, amp, floor, noise = scene
    t0 = time.perf_counter()
    if kind == "png":
        path = folder / f"{name}.png"
        data = clean + noise * rng.standard_normal(clean.shape)
        user_images.write_png(path, user_images.quantise(data, bits))
        assert user_images.png_chunks(path) == [b"IHDR", b"IDAT", b"IEND"]  # untagged
        return path, time.perf_counter() - t0
    path = folder / f"{name}.{kind.split('-')[1]}"
    argv = [str(pathlib.Path(sys.executable).with_name("jaxlens")), "render", "--sky", "star",
            "--distance", repr(d), "--fov-deg", repr(fov), "--size", f"{w}x{h}",
            "--star-sigma-deg", repr(sig), "--star-brightness", repr(amp), "--floor",
            repr(floor), "--sampling", "gauss", "--supersample", "8", "--float64",
            "-o", str(path)]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True,
                          env=dict(os.environ, JAXLENS_CACHE_DIR=""))  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"jaxlens render failed: {done.stderr.strip()[-500:]}")
    return path, time.perf_counter() - t0


def run_files(n, folder):
    """The first `n` of `FILE_SCENES` x `FILE_CASES`: make each file, fit it."""
    sys.path.insert(0, str(ROOT / "tests"))  # user_images: a PNG writer of its own
    rows = []
    cases = [(s, c) for s in range(len(FILE_SCENES)) for c in range(len(FILE_CASES))][:n]
    clean = {}
    for i, (si, ci) in enumerate(cases):
        scene = FILE_SCENES[si]
        d, fov, w, h, sig, amp, floor, noise = scene
        kind, bits, transfer = FILE_CASES[ci]
        t_render = 0.0
        if kind == "png" and si not in clean:
            t0 = time.perf_counter()
            clean[si] = ring_image(d, math.radians(fov), w, h, math.radians(sig), amp, floor)
            t_render = time.perf_counter() - t0
        # one noise draw a scene and bit depth: --transfer linear and auto fit the same file
        rng = np.random.default_rng([2028, si, bits])
        path, t_file = user_file(kind, bits, scene, clean.get(si), rng, folder, f"file{i:02d}")
        extra = [] if transfer == "auto" else ["--transfer", transfer]
        out, wall = fit_file(path, sig, extra)
        row = dict(section="files", case=i, kind=kind, bits=bits, transfer=transfer, d=d,
                   fov=fov, w=w, h=h, sig=sig, floor=floor,
                   noise=noise if kind == "png" else 0.0, wall=wall,
                   render=t_render + t_file, argv=extra, fit=out)  # fmt: skip
        rows.append(row)
        if "error" in out:
            print(f"file {i}: error {out['error']}", flush=True)
            continue
        print(
            f"file {i} ({kind}, {bits} bit, --transfer {transfer}): D {out['distance']:.4f}"
            f"+-{out['distance_err']:.2g} (true {d}), FOV {out['fov_deg']:.4f}"
            f"+-{out['fov_deg_err']:.2g} (true {fov}), read as {out.get('transfer')} "
            f"({out.get('transfer_reason')}), valid={out.get('valid')}, {wall:.1f} s"
            + (f", message: {out['message']}" if out.get("message") else ""),
            flush=True,
        )
    return rows


# The speed section's ring: (D, FOV deg, width, height, sigma deg (given), brightness,
# floor, noise), a 16-bit PNG, three noise draws.
SPEED_SCENE = (20.0, 60.0, 320, 240, 1.0, 0.8, 0.05, 0.01)
# Goals of the fit's speed (CPU seconds, every thread): a cold `jaxlens fit` process with
# the compile cache off, and a fit of a same-size image in a process that fitted one.
SPEED_GOALS = {"cold": 5.0, "warm": 1.0}

_WARM = """
import json, sys, time
import jaxlens as jl
out = []
for path in sys.argv[2:]:
    c0, w0 = time.process_time(), time.perf_counter()
    fit = jl.fit_ring(path, star_sigma=float(sys.argv[1]))
    out.append(dict(cpu=time.process_time() - c0, wall=time.perf_counter() - w0,
                    distance=fit.distance, valid=fit.valid))
print(json.dumps(out))
"""


def run_speed(n, folder):
    """CPU time per fit of `SPEED_SCENE`: `n` (at most 3) cold `jaxlens fit` processes
    (their own and their threads' CPU time, `RUSAGE_CHILDREN`), and one process that
    fits the three images in turn (`time.process_time` of each fit: the first compiles,
    the others are warm)."""
    import resource

    d, fov, w, h, sig, amp, floor, noise = SPEED_SCENE
    clean = ring_image(d, math.radians(fov), w, h, math.radians(sig), amp, floor)
    paths = []
    for seed in range(3):
        rng = np.random.default_rng([2029, seed])
        paths.append(folder / f"speed{seed}.png")
        write_png(paths[-1], clean + noise * rng.standard_normal(clean.shape), 16)
    env = dict(os.environ, JAXLENS_CACHE_DIR="")
    jaxlens = str(pathlib.Path(sys.executable).with_name("jaxlens"))
    rows = []
    for i in range(min(max(n, 1), 3)):
        argv = [jaxlens, "fit", str(paths[i]), "--json", "--star-sigma-deg", repr(sig)]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        done = subprocess.run(argv, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        fit = json.loads(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else {}
        rows.append(dict(section="speed", kind="cold", cpu=cpu, wall=wall,
                         distance=fit.get("distance"), valid=fit.get("valid")))  # fmt: skip
        print(f"speed: cold process {cpu:.1f} CPU-s, {wall:.1f} s wall", flush=True)
    argv = [sys.executable, "-c", _WARM, repr(math.radians(sig)), *map(str, paths)]
    done = subprocess.run(argv, capture_output=True, text=True, env=env)
    fits = json.loads(done.stdout.strip().splitlines()[-1]) if done.returncode == 0 else []
    for i, f in enumerate(fits):
        rows.append(dict(section="speed", kind="first" if i == 0 else "warm", **f))
        print(
            f"speed: in-process fit {i}: {f['cpu']:.2f} CPU-s, {f['wall']:.2f} s wall", flush=True
        )
    return rows


def speed_lines(rows, note=None):
    d, fov, w, h, sig, *_ = SPEED_SCENE
    lines = [
        f"A ring of the first section's renderer (D = {d:g}, FOV {fov:g} deg, {w} x {h}, "
        f"16-bit PNG, sigma {sig:g} deg given), three noise draws. 'cold': one fresh "
        "`jaxlens fit IMAGE --json` process, compile cache off (Python, JAX's import and "
        "every compile included); 'first' and 'warm': `jl.fit_ring` on the three images "
        "in turn in one process (the first compiles, the others reuse its programs). CPU "
        "seconds count every thread (user + system).",
        "",
    ]
    if note:
        lines += [note, ""]
    lines += ["| run | CPU s | wall s | D | valid | goal (CPU s) |",
              "|---|---:|---:|---:|---|---:|"]  # fmt: skip
    for r in rows:
        goal = SPEED_GOALS.get(r["kind"])
        dist = "-" if r.get("distance") is None else f"{r['distance']:.4f}"
        lines.append(f"| {r['kind']} | {r['cpu']:.2f} | {r['wall']:.2f} | {dist} | "
                     f"{r.get('valid')} | {'-' if goal is None else f'{goal:g}'} |")  # fmt: skip
    for kind, goal in SPEED_GOALS.items():
        got = [r["cpu"] for r in rows if r["kind"] == kind]
        if got:
            lines.append(f"- {kind}: median **{np.median(got):.2f} CPU-s** (goal: {goal:g}).")
    return lines


def previous_rows(section):
    """The rows of `section` in the existing fit.json (rows without a section: rings)."""
    try:
        old = json.loads((RESULTS / "fit.json").read_text())
    except (OSError, ValueError):
        return []
    return [r for r in old if isinstance(r, dict) and r.get("section", "rings") == section]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=("rings", "arcs", "files", "speed"),
                    help="run one section (default all four)")  # fmt: skip
    ap.add_argument("--cases", type=int, help="the first N cases of each section (default all)")
    ap.add_argument("--keep", type=pathlib.Path, help="keep the PNGs in this folder")
    ap.add_argument("--render-only", action="store_true",
                    help="render the arc cases' images (3 x 3 samples a pixel) and print their "
                    "visibility; no fits, no report")  # fmt: skip
    args = ap.parse_args()
    folder = args.keep or pathlib.Path(tempfile.mkdtemp(prefix="jaxlens-fit-"))
    folder.mkdir(parents=True, exist_ok=True)
    if args.render_only:
        run_arcs(len(ARC_CASES) if args.cases is None else args.cases, folder, render_only=True)
        return
    load = os.getloadavg()[0]
    sections = {}
    n_files = len(FILE_SCENES) * len(FILE_CASES)
    for name, cases, run in (("rings", CASES, run_rings), ("arcs", ARC_CASES, run_arcs),
                             ("files", range(n_files), run_files),
                             ("speed", range(3), run_speed)):  # fmt: skip
        if args.only in (None, name):
            sections[name] = (run(len(cases) if args.cases is None else args.cases, folder), True)
        else:
            sections[name] = (previous_rows(name), False)
    write_report(sections, load)


def write_report(sections, load):
    """fit.md: the machine, the rings, the general cases, the users' files; fit.json:
    every section's rows.

    A section not run this time keeps the rows the previous fit.json held for it."""
    (rings, rings_ran), (arcs, arcs_ran) = sections["rings"], sections["arcs"]
    files, files_ran = sections["files"]
    lines = [
        "# Fit benchmark: Einstein rings from an independent renderer",
        "",
        _common.machine_markdown().rstrip(),
        f"- Load average {load:.1f} at the start. Produced by `benchmarks/bench_fit.py`.",
        "",
    ]
    lines += ring_lines(rings, None if rings_ran else _not_run_note("rings", rings))
    lines += ["", "## General cases: arcs, PSF, Poisson", ""]
    lines += arc_lines(arcs, None if arcs_ran else _not_run_note("arcs", arcs))
    lines += ["", "## Files as users have them: untagged PNGs, the library's own files", ""]
    lines += file_lines(files, None if files_ran else _not_run_note("files", files))
    speed, speed_ran = sections.get("speed", ([], False))
    lines += ["", "## Speed: CPU time per fit", ""]
    lines += speed_lines(speed, None if speed_ran else _not_run_note("speed", speed))
    rows = rings + arcs + files + speed
    (RESULTS / "fit.json").write_text(json.dumps(rows, indent=1) + "\n")
    (RESULTS / "fit.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {RESULTS / 'fit.md'}")


def _not_run_note(section, rows):
    other = "/".join(s for s in ("rings", "arcs", "files", "speed") if s != section)
    if rows:
        return (f"**Not run this time** (`--only {other}`): the {len(rows)} rows below are "
                "those the previous `fit.json` held, from an earlier run (machine and "
                "commit may differ from the lines above).")  # fmt: skip
    return f"**Not run this time** (`--only {other}`), and `fit.json` held no earlier rows."


def _walls_line(walls, goal):
    return (f"- Wall time per fit, compile included: median {np.median(walls):.1f} s, "
            f"largest **{max(walls):.1f} s** (goal: {goal}).")  # fmt: skip


def ring_lines(rows, note=None):
    lines = [
        "Each ring: scipy quadrature of the orbit (no jaxlens code), 12 x 12 samples a "
        "pixel, Gaussian noise, clipped to [0, 1], stored as a linear 8- or 16-bit grey "
        "PNG. Each fit: one fresh `jaxlens fit IMAGE --json` process, persistent compile "
        "cache off, so the time includes Python start-up, JAX import and compilation. "
        "'pull' is (fit - truth) / reported standard error.",
    ]
    if note:
        lines += ["", note]
    if not rows:
        return lines
    lines += [
        "",
        "| D | FOV deg | size | bits | floor | noise | sigma | D fit | D rel. err | D pull "
        "| FOV fit | FOV rel. err | FOV pull | steps | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    ok = [{**r["fit"], **r} for r in rows if "error" not in r["fit"]]
    for r in rows:
        sig = f"{r['sig']} given" if r["given"] else f"fitted ({r['sig']})"
        head = (f"| {r['d']:g} | {r['fov']:g} | {r['w']}x{r['h']} | {r['bits']} | "
                f"{r['floor']:g} | {r['noise']:g} | {sig} |")  # fmt: skip
        if "error" in r["fit"]:
            lines.append(head + f" error: {r['fit']['error']} |||||||{r['wall']:.1f} |")
            continue
        r = {**r["fit"], **{k: v for k, v in r.items() if k != "fit"}}
        de = r["distance"] / r["d"] - 1
        fe = r["fov_deg"] / r["fov"] - 1
        flag = " (degenerate)" if r["degenerate"] else ("" if r["converged"] else " (not conv.)")
        lines.append(
            head + f" {r['distance']:.4f} +- {r['distance_err']:.2g} | {de:+.2e} | "
            f"{(r['distance'] - r['d']) / r['distance_err']:+.2f} | "
            f"{r['fov_deg']:.4f} +- {r['fov_deg_err']:.2g} | {fe:+.2e} | "
            f"{(r['fov_deg'] - r['fov']) / r['fov_deg_err']:+.2f} | {r['num_steps']}{flag} | "
            f"{r['wall']:.1f} |"
        )
    good = [r for r in ok if r["converged"] and not r["degenerate"]]
    flagged = [r for r in ok if not (r["converged"] and not r["degenerate"])]
    walls = [r["wall"] for r in rows]
    lines += ["", f"{len(ok)} of {len(rows)} fits returned a result; {len(good)} converged and "
              f"were not flagged degenerate."]  # fmt: skip
    if good:
        worst_d = max(abs(r["distance"] / r["d"] - 1) for r in good)
        worst_f = max(abs(r["fov_deg"] / r["fov"] - 1) for r in good)
        pulls = np.array(
            [
                [
                    (r["distance"] - r["d"]) / r["distance_err"],
                    (r["fov_deg"] - r["fov"]) / r["fov_deg_err"],
                ]
                for r in good
            ]  # fmt: skip
        )
        lines += [
            f"- Largest relative error of those: D **{worst_d:.2e}**, FOV **{worst_f:.2e}** "
            "(goal: 1e-2 each).",
            f"- Their pulls: D rms {np.sqrt(np.mean(pulls[:, 0] ** 2)):.2f}, FOV rms "
            f"{np.sqrt(np.mean(pulls[:, 1] ** 2)):.2f} (1 if the reported errors are "
            f"honest and the two renderers agree); |pull| <= 2 in "
            f"{np.mean(np.abs(pulls) <= 2) * 100:.0f} % of the {pulls.size} values.",
        ]
    for r in flagged:
        lines.append(
            f"- Flagged: D = {r['d']:g}, FOV {r['fov']:g} deg, {r['w']}x{r['h']}, "
            f"floor {r['floor']:g}, sigma {'given' if r['given'] else 'fitted'}: "
            f"D off by {r['distance'] / r['d'] - 1:+.2e}; message: {r['message']}"
        )
    lines.append(_walls_line(walls, "under 60 s"))
    return lines


def _valid(fit) -> bool:
    """Whether a fit's JSON reports a measurement (`Fit.valid`; rows from before it was
    recorded: converged and not degenerate)."""
    return bool(fit.get("valid", fit["converged"] and not fit["degenerate"]))


def _angle_deg(a, b):
    """Angle between two unit vectors (deg), atan2(|a x b|, a . b)."""
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def _pull(fit, err, truth):
    return (fit - truth) / err if err and err > 0 else float("nan")


def arc_lines(rows, note=None):
    lines = [
        "Each case: a Gaussian star of width sigma at sky position (lon, lat) (0, 0 exactly "
        "behind the hole, lon > 0 to the right, lat > 0 up), drawn by the same independent "
        "renderer: a sample's ray leaves along n = -cos(Phi) f + sin(Phi) (cos(psi) e_x + "
        "sin(psi) e_y), psi its image azimuth, and sees the star at atan2(|n x s|, n . s) "
        "from its centre; 12 x 12 samples a pixel. With a point-spread function of S px the "
        "frame is rendered with a margin of ceil(5 S) px at the same focal length, blurred "
        "(`scipy.ndimage.gaussian_filter`, mode nearest, truncate 6) and cropped, so light "
        "from beyond the frame's edge spreads into it. Then Gaussian noise, or Poisson "
        "counts (value = Poisson(G x clean) / G), clipped to [0, 1], a linear 8- or 16-bit "
        "grey PNG. The fit gets `--psf-sigma-px S`, `--noise poisson` (the gain estimated "
        "by the fit) and `--star-sigma-deg` where the table says so. Offset: the star's "
        "angle from the axis; 'pos. err': the angle between the fitted and the true "
        "direction of the star; S/N: (brightest clean pixel - floor) / the noise there.",
    ]
    if note:
        lines += ["", note]
    if not rows:
        return lines
    lines += [
        "",
        "| D | FOV deg | size | bits | floor | lon, lat (offset) deg | PSF px | noise | S/N "
        "| sigma deg | D fit | D rel. err | D pull | FOV fit | FOV rel. err | FOV pull "
        "| lon fit deg | lon pull | lat fit deg | lat pull | pos. err deg | steps | wall s |",
        "|" + "---|" * 23,
    ]
    done = []
    for r in rows:
        s = sky_direction(math.radians(r["lon"]), math.radians(r["lat"]))
        offset = math.degrees(math.atan2(math.hypot(s[1], s[2]), s[0]))
        sig = f"{r['sig']} given" if r["given"] else f"fitted ({r['sig']})"
        noise = f"poisson gain {r['gain']:g}" if r["noise"] == "poisson" else f"{r['noise']:g}"
        head = (f"| {r['d']:g} | {r['fov']:g} | {r['w']}x{r['h']} | {r['bits']} | "
                f"{r['floor']:g} | {r['lon']:+g}, {r['lat']:+g} ({offset:.2f}) | "
                f"{r['psf'] or '-'} | {noise} | {r['snr']:.0f} | {sig} |")  # fmt: skip
        if "error" in r["fit"]:
            lines.append(head + f" error: {r['fit']['error']} |" + "|" * 11 + f"{r['wall']:.1f} |")
            continue
        f = r["fit"]
        fitted = sky_direction(math.radians(f["source_lon_deg"]), math.radians(f["source_lat_deg"]))
        e = dict(
            r, offset=offset, pos=_angle_deg(fitted, s),
            de=f["distance"] / r["d"] - 1, fe=f["fov_deg"] / r["fov"] - 1,
            pulls=[
                _pull(f["distance"], f["distance_err"], r["d"]),
                _pull(f["fov_deg"], f["fov_deg_err"], r["fov"]),
                _pull(f["source_lon_deg"], f["source_lon_deg_err"], r["lon"]),
                _pull(f["source_lat_deg"], f["source_lat_deg_err"], r["lat"]),
            ],
        )  # fmt: skip
        done.append(e)
        flag = " (degenerate)" if f["degenerate"] else ("" if f["converged"] else " (not conv.)")
        if not flag and not f.get("valid", True):
            flag = " (flagged)"
        p = e["pulls"]
        lines.append(
            head + f" {f['distance']:.4f} +- {f['distance_err']:.2g} | {e['de']:+.2e} | "
            f"{p[0]:+.2f} | {f['fov_deg']:.4f} +- {f['fov_deg_err']:.2g} | {e['fe']:+.2e} | "
            f"{p[1]:+.2f} | {f['source_lon_deg']:+.4f} +- {f['source_lon_deg_err']:.2g} | "
            f"{p[2]:+.2f} | {f['source_lat_deg']:+.4f} +- {f['source_lat_deg_err']:.2g} | "
            f"{p[3]:+.2f} | {e['pos']:.2g} | {f['num_steps']}{flag} | {r['wall']:.1f} |"
        )
    # A fit reports a measurement only when valid (converged, not degenerate, no check
    # failed): the pulls are those of the valid fits, and of every converged one below.
    good = [e for e in done if _valid(e["fit"])]
    lines += ["", f"{len(done)} of {len(rows)} fits returned a result; {len(good)} valid "
              "(converged, not degenerate, no check failed)."]  # fmt: skip
    if good:
        worst_d = max(abs(e["de"]) for e in good)
        worst_f = max(abs(e["fe"]) for e in good)
        worst_pos = max(good, key=lambda e: e["pos"])
        worst_frac = max(good, key=lambda e: e["pos"] / e["offset"])
        meet = sum(e["pos"] <= max(0.05, 0.03 * e["offset"]) for e in good)
        pulls = np.array([e["pulls"] for e in good])
        fin = pulls[np.isfinite(pulls)]
        rms = ", ".join(
            f"{n} {np.sqrt(np.nanmean(pulls[:, i] ** 2)):.2f}"
            for i, n in enumerate(("D", "FOV", "lon", "lat"))
        )
        lines += [
            f"- Largest relative error of those: D **{worst_d:.2e}**, FOV **{worst_f:.2e}** "
            "(goal: 1e-2 each).",
            f"- Source position: largest error **{worst_pos['pos']:.3f} deg** (offset "
            f"{worst_pos['offset']:.2f} deg); largest as a share of the offset **"
            f"{worst_frac['pos'] / worst_frac['offset'] * 100:.1f} %** ({worst_frac['pos']:.3f} "
            f"of {worst_frac['offset']:.2f} deg); within the goal (0.05 deg or 3 % of the "
            f"offset, whichever is larger) in {meet} of {len(good)}.",
            f"- Their pulls: rms {np.sqrt(np.mean(fin**2)):.2f} over all {fin.size} ({rms}; 1 if "
            f"the reported errors are honest and the two renderers agree); |pull| <= 2 in "
            f"{np.mean(np.abs(fin) <= 2) * 100:.0f} % of them.",
        ]
        conv = [e for e in done if e["fit"]["converged"] and not e["fit"]["degenerate"]]
        every = np.array([e["pulls"] for e in conv])
        every = every[np.isfinite(every)]
        if len(conv) > len(good):
            lines.append(f"- Every converged, non-degenerate fit, the flagged ones too "
                         f"({len(conv)}): pulls rms {np.sqrt(np.mean(every**2)):.2f} over "
                         f"{every.size}.")  # fmt: skip
    for e in done:
        if e in good:
            continue
        lines.append(
            f"- Flagged: D = {e['d']:g}, FOV {e['fov']:g} deg, {e['w']}x{e['h']}, star at "
            f"({e['lon']:g}, {e['lat']:g}) deg, floor {e['floor']:g}, sigma "
            f"{'given' if e['given'] else 'fitted'}: D off by {e['de']:+.2e}, FOV by "
            f"{e['fe']:+.2e}, position by {e['pos']:.3f} deg; "
            f"{'converged' if e['fit']['converged'] else 'not converged'}; "
            f"message: {e['fit']['message']}"
        )
    lines.append(_walls_line([r["wall"] for r in rows], "well under 60 s"))
    return lines


def file_lines(rows, note=None):
    lines = [
        "Each file: a ring of the first section's renderer (12 x 12 samples a pixel), or "
        "`jaxlens render --sky star` of the same scene (Gauss-Legendre cells, 8 x 8 a "
        "pixel, float64). 'png': linear values plus Gaussian noise, clipped to [0, 1], in "
        "an untagged grey PNG (no sRGB, gAMA or iCCP chunk, written by "
        "`tests/user_images.py`, not by the library), as numpy, Pillow and camera "
        "pipelines store them; 'render-png' / 'render-exr': the library's own sRGB-tagged "
        "8-bit PNG and linear float EXR, no noise but the PNG's quantisation. 'asked': "
        "the `--transfer` given (auto: none, the default); 'read as': the decoding the fit "
        "used and its reason. The star's width is given. A fit that is valid but off by "
        "more than 1 % in D or FOV is a silent failure.",
    ]
    if note:
        lines += ["", note]
    if not rows:
        return lines
    lines += [
        "",
        "| file | bits | asked | D | FOV deg | size | floor | noise | D fit | D rel. err "
        "| D pull | FOV fit | FOV rel. err | FOV pull | read as (why) | valid | wall s |",
        "|" + "---|" * 17,
    ]
    done = []
    for r in rows:
        bits = "32 float" if r["kind"] == "render-exr" else r["bits"]
        head = (f"| {r['kind']} | {bits} | {r['transfer']} | {r['d']:g} | {r['fov']:g} | "
                f"{r['w']}x{r['h']} | {r['floor']:g} | {r['noise']:g} |")  # fmt: skip
        f = r["fit"]
        if "error" in f:
            lines.append(head + f" error: {f['error']} |" + "|" * 7 + f"{r['wall']:.1f} |")
            continue
        e = dict(r, de=f["distance"] / r["d"] - 1, fe=f["fov_deg"] / r["fov"] - 1,
                 valid=bool(f.get("valid")))  # fmt: skip
        done.append(e)
        lines.append(
            head + f" {f['distance']:.4f} +- {f['distance_err']:.2g} | {e['de']:+.2e} | "
            f"{_pull(f['distance'], f['distance_err'], r['d']):+.2f} | "
            f"{f['fov_deg']:.4f} +- {f['fov_deg_err']:.2g} | {e['fe']:+.2e} | "
            f"{_pull(f['fov_deg'], f['fov_deg_err'], r['fov']):+.2f} | "
            f"{f.get('transfer')} ({f.get('transfer_reason') or '-'}) | "
            f"{'yes' if e['valid'] else 'no'} | {r['wall']:.1f} |"
        )
    good = [e for e in done if e["valid"]]
    right = [e for e in good if max(abs(e["de"]), abs(e["fe"])) <= 1e-2]
    silent = [e for e in good if e not in right]
    lines += [
        "",
        f"{len(done)} of {len(rows)} fits returned a result; {len(good)} valid, {len(right)} "
        f"of them within 1 % in D and FOV; **{len(silent)} valid but off by more than 1 %** "
        f"(silent failures); {len(done) - len(good)} flagged.",
    ]
    for e in silent:
        lines.append(
            f"- Silent: {e['kind']} ({e['bits']} bits), --transfer {e['transfer']}, D = "
            f"{e['d']:g}, FOV {e['fov']:g}: D off by {e['de']:+.2e}, FOV by {e['fe']:+.2e}, "
            f"read as {e['fit'].get('transfer')}"
        )
    for e in done:
        if not e["valid"]:
            lines.append(
                f"- Flagged: {e['kind']} ({e['bits']} bits), --transfer {e['transfer']}, D = "
                f"{e['d']:g}, FOV {e['fov']:g} (D off by {e['de']:+.2e}): {e['fit']['message']}"
            )
    lines.append(_walls_line([r["wall"] for r in rows], "under 60 s; auto may fit twice"))
    return lines


if __name__ == "__main__":
    main()
