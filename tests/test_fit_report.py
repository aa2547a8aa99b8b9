"""What a fit tells its user: progress lines while it runs (on where someone watches,
off in a test run or a batch job), one summary for Python and `jaxlens fit`, no noise
level beside "no pixel noise found", and negative fluxes flagged or explained.

Every fit is of a 16-bit PNG of test_fit's CLI ring (96 x 72, its star's width given),
as `jaxlens fit` fits it, so that they share the compiled programs of that test's
fits (through the suite's compilation cache) and of each other: the first fit
compiles them, most of this file's time where it runs alone."""

import io
import math
import re
import sys
import time
import types

import jax
import numpy as np
import pytest
from helpers import run
from user_images import quantise, write_png

import jaxlens as jl
from jaxlens._fit.diagnose import _nuisance_notes
from jaxlens._fit.progress import Progress

W, H = 96, 72


def _model():
    # The scene `jaxlens fit` fits, with the star's width given (--star-sigma-deg).
    return jl.Scene(jl.Camera(20.0, 1.0, 8, 8), jl.GaussianStar(0.01) + jl.Uniform(0.0))


FREE = tuple(n for n in jl.DEFAULT_FREE if n != "sigma")
INIT = {"sigma": math.radians(1.5)}


def _seconds_out(text: str) -> str:
    """A report without its wall time (two runs of one fit take different times)."""
    return re.sub(r"; [0-9.]+ s$", "; (time) s", text, flags=re.M)


def _ring(*, ring_flux: float = 1.0, noise: float = 0.0, seed: int = 0):
    """test_fit's ring (`modelled`): D = 20, FOV 60 deg, star 1.5 deg wide, peak 0.8,
    floor 0.1, the relativistic rings' flux times `ring_flux`, Gaussian noise."""
    # test_fit's call, whose program the suite's compilation cache then holds.
    model = jax.jit(jl.ring_image, static_argnums=(2, 3), static_argnames="supersample")
    img = model(20.0, math.radians(60.0), W, H, sigma=math.radians(1.5), brightness=0.8,
                floor=0.1, ring_flux=ring_flux, supersample=8)  # fmt: skip
    rng = np.random.default_rng(seed)
    return np.asarray(img, np.float64) + noise * rng.standard_normal((H, W))


def _png(path, img) -> str:
    """`img` as a 16-bit PNG tagged linear (gAMA 1.0), as test_fit's CLI test writes."""
    return str(write_png(path, quantise(img, 16), tag="gamma1"))


@pytest.fixture(scope="module")
def image_file(tmp_path_factory):
    return _png(tmp_path_factory.mktemp("report") / "ring.png", _ring(noise=0.01, seed=16))


def test_the_summary_is_the_command_lines_report(image_file, capsys):
    # `jaxlens fit FILE --mass-msun 10` prints the file's name and Fit.summary() of the
    # same fit, with the metres for the mass: the same lines, from one function.
    code, out, _ = run(["fit", image_file, "--star-sigma-deg", "1.5", "--mass-msun", "10"],
                       capsys)  # fmt: skip
    assert code == 0
    fit = jl.fit(_model(), image_file, free=FREE, init=INIT, progress=False)
    assert fit.valid, fit.summary()
    want = f"fit of {image_file}\n{fit.summary(mass_msun=10.0)}\n"
    assert _seconds_out(out) == _seconds_out(want)
    d_m, d_m_err = fit.distance_m(10.0)
    assert f"distance     = {d_m:.6g} +- {d_m_err:.2g} m (mass 10 M_sun)" in out
    # ... and the JSON line is to_dict()'s with the same addition.
    code, out, _ = run(["fit", image_file, "--star-sigma-deg", "1.5", "--distance-m", "6e5",
                        "--json"], capsys)  # fmt: skip
    got = __import__("json").loads(out.strip().splitlines()[-1])
    want = fit.to_dict(distance_m=6e5)
    assert got["mass_msun"] == pytest.approx(want["mass_msun"], rel=1e-9)
    assert got["mass_msun_err"] == pytest.approx(want["mass_msun_err"], rel=1e-9)


def test_a_fit_reports_its_stages_steps_and_loss(image_file, capsys):
    fit = jl.fit(_model(), image_file, free=FREE, init=INIT, progress=True)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    # A few lines a fit, each "fit: <stage> | <seconds> s", in order of time.
    assert 5 <= len(lines) <= 20, err
    assert all(re.fullmatch(r"fit: .+ \| [0-9.]+ s", line) for line in lines), err
    times = [float(line.rsplit("| ", 1)[1][:-2]) for line in lines]
    assert times == sorted(times)
    assert "looking for a ring or arcs in the 96 x 72 image" in lines[0]
    # The solver's pass: its steps and chi^2, which are the fit's (the summary's).
    m = re.search(r"solving, pass 1: (\d+) steps, chi2 (\S+) \|", err)
    assert m is not None, err
    assert int(m.group(1)) == fit.num_steps
    # chi^2 of the solver's last point, in units of the noise it solved under: the
    # fit's chi2/dof x dof where the noise is not re-estimated; a clipped image's is,
    # from the residuals, within [0.7, 1.5] of the image's own estimate, so chi^2 within
    # [1 / 1.5^2, 1 / 0.7^2] of the fit's (and the ring-flux prior's square, < 4 here).
    ratio = (float(m.group(2)) - 4.0) / (fit.chi2_dof * (fit.n_pixels - len(fit.names)))
    assert 1.0 / 1.5**2 - 1e-3 < ratio < 1.0 / 0.7**2 + 1e-3, err
    assert lines[-1].startswith("fit: done: valid,"), err
    # Off: nothing.
    jl.fit(_model(), image_file, free=FREE, init=INIT, progress=False)
    assert capsys.readouterr().err == ""
    # A callable takes the stages' texts instead (the command line's status line).
    texts = []
    jl.fit(_model(), image_file, free=FREE, init=INIT, progress=texts.append)
    assert capsys.readouterr().err == ""
    assert [t.split(" | ")[0] for t in texts] == [line[5:].rsplit(" | ", 1)[0] for line in lines]


def test_progress_is_on_where_someone_watches(monkeypatch):
    # Under pytest stderr is captured (not a terminal): off, as in a pipe or a job's log.
    assert Progress(None).on is False
    assert Progress(True).on is True and Progress(False).on is False
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert Progress(None).on is True
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    # A Jupyter kernel's shell: a notebook.
    shell = type("ZMQInteractiveShell", (), {})()
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert Progress(None).on is True
    # A terminal IPython without a terminal (its output piped): off.
    shell = type("TerminalInteractiveShell", (), {})()
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert Progress(None).on is False
    with pytest.raises(TypeError, match="progress='yes' is not valid"):
        Progress("yes")


def test_no_noise_level_beside_no_pixel_noise_found(tmp_path):
    # A noiseless image: no pixel noise, so its residuals are a misfit, not a noise
    # level, and the summary says so rather than printing one.
    path = _png(tmp_path / "clean.png", _ring())
    fit = jl.fit(_model(), path, free=FREE, init=INIT, progress=False)
    text = fit.summary()
    assert "no pixel noise found" in fit.message
    verdict = next(line for line in text.splitlines() if line.startswith("converged"))
    assert "residuals" not in verdict and "standard deviations" not in verdict, text
    assert "chi2/dof" not in verdict, text
    assert "no pixel noise found, misfit" in verdict, text
    assert not fit.noise_seen and fit.to_dict()["noise_seen"] is False


def test_negative_fluxes_are_flagged_beyond_3_errors_and_explained_within():
    free = ("distance", "brightness", "ring_flux")
    err = [0.1, 0.01, 0.5]
    # Beyond 3 standard errors: a note (which flags the fit), naming a PSF.
    notes, explained = _nuisance_notes(free, {"distance": 20.0, "brightness": 0.8,
                                              "ring_flux": -1.6}, err, False, False)  # fmt: skip
    assert explained == [] and len(notes) == 1
    assert "ring_flux = -1.6 +- 0.5 is negative" in notes[0] and "psf=" in notes[0]
    # Within them: zero within its error, explained (for the caveat), not flagged.
    notes, explained = _nuisance_notes(free, {"distance": 20.0, "brightness": -0.02,
                                              "ring_flux": -1.4}, err, False, False)  # fmt: skip
    assert notes == [] and len(explained) == 2
    assert "brightness = -0.02 +- 0.01 is negative" in explained[0]
    assert "within 3 standard errors of zero" in explained[1] and "relativistic" in explained[1]
    # Positive: nothing.
    assert _nuisance_notes(free, {"distance": 20.0, "brightness": 0.8, "ring_flux": 0.2},
                           err, False, False) == ([], [])  # fmt: skip


@pytest.mark.parametrize(("ring_flux", "flagged"), [(-1.0, False), (-4.0, True)])
def test_a_fit_of_dark_rings_flags_or_explains_its_negative_flux(tmp_path, ring_flux, flagged):
    # Relativistic rings of negative flux (no star and hole make them). The flux's
    # prior N(1, 1) pulls the fitted value toward 1 (by a third: -0.56 +- 0.56 for -1,
    # -1.90 for -3, -3.92 for -6, seed 4): for -1 within 3 errors of zero, explained
    # in the caveat, the fit valid; for -4 (about -2.6, 4.6 errors) beyond them,
    # flagged in the message.
    path = _png(tmp_path / "dark.png", _ring(ring_flux=ring_flux, noise=0.003, seed=4))
    fit = jl.fit(_model(), path, free=FREE, init=INIT, progress=False)
    assert fit.ring_flux < 0.0, fit.summary()
    beyond = fit.ring_flux < -3.0 * fit.ring_flux_err
    assert beyond is flagged, fit.summary()
    text = fit.summary()
    if flagged:
        assert not fit.valid and "FLAGGED" in text
        assert "ring_flux" in fit.message and "is negative" in fit.message
        assert "ring_flux" not in fit.caveat
    else:
        assert fit.valid and "FLAGGED" not in text, text
        assert "ring_flux" not in fit.message
        assert "ring_flux" in fit.caveat and "within 3 standard errors of zero" in fit.caveat
        assert f"caveat: {fit.caveat}" in text


def test_the_status_line_keeps_to_one_row_of_the_terminal():
    # `jaxlens fit`'s stages on its status line: a line longer than the terminal wraps,
    # and every redraw (a carriage return) then left a row behind. Cut to 79 columns
    # (80 where the stream does not say), the time kept.
    from jaxlens import _spinner

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    stream = Terminal()
    long = "fitting ring.png: start: 6 free parameters, 6912 bins compared (compiling " * 2
    with _spinner.Spinner("jaxlens fit", stream=stream, delay=0.0, interval=0.01):
        _spinner.status(long)
        time.sleep(0.3)
    rows = [r.replace("\x1b[K", "") for r in stream.getvalue().split("\r")]
    shown = [r for r in rows if r.startswith("jaxlens fit: fitting ring.png: start")]
    assert shown and all(len(r) <= 79 for r in rows), rows
    assert all(re.search(r"\.\.\. [|/\\-] \d+ s$", r) for r in shown), shown
