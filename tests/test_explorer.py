"""The notebook explorer's callback, driven without a browser: build the widgets, move
a slider, and the image changes (and stays a valid render)."""

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

pytest.importorskip("ipywidgets")

import jaxlens as jl  # noqa: E402


def test_sliders_rerender_the_image():
    ex = jl.Explorer(48, 27)
    first, png = ex.image.copy(), ex.view.value
    assert first.shape == (27, 48, 3) and png[:8] == b"\x89PNG\r\n\x1a\n"
    # Star behind the hole at D = 20: an Einstein ring of 20.2 degrees, black shadow.
    assert first[13, 24].max() == 0.0 and first.max() > 0.5
    ex.distance.value = 5.0  # the observe callback re-renders
    assert ex.view.value != png
    assert np.abs(ex.image - first).max() > 0.1
    assert ex.status.value.startswith("48x27")
    ex.distance.value = 20.0
    before = ex.image.copy()
    ex.star_lon.value = 10.0  # moving the star off the axis breaks the ring's symmetry
    assert np.abs(ex.image - ex.image[:, ::-1]).max() > 0.05
    assert np.abs(ex.image - before).max() > 0.05
    ex.sky.value = "checker"
    assert ex.image.mean() > before.mean()  # the checker sphere lights every direction
    cam, sky = ex.scene()
    assert float(cam.distance) == pytest.approx(20.0) and float(cam.fov) == pytest.approx(
        math.radians(60.0)
    )


def test_the_image_keeps_its_aspect_ratio_and_says_when_it_renders():
    # A 240 x 135 render was shown stretched to 320 x 284 beside the sliders.
    ex = jl.Explorer(48, 27)
    assert (ex.view.width, ex.view.height) == ("320", "180")  # HTML attributes
    assert (ex.view.layout.width, ex.view.layout.height) == ("320px", "180px")
    assert ex.view.layout.align_self == "flex-start"  # not stretched to the sliders' height
    seen = []
    ex.status.observe(lambda change: seen.append(change["new"]), names="value")
    ex.fov.value = 50.0
    assert seen[0] == "rendering..." and seen[-1].startswith("48x27")


def test_bad_setting_is_reported_not_raised():
    ex = jl.Explorer(48, 27)  # the size above: its first render's program is compiled
    ex.distance.min = -1.0  # log10: lets the slider reach D = 0.5, which the camera refuses
    ex.distance.value = 0.5
    assert ex.status.value.startswith("error: distance=0.5")


def test_jaxlens_works_without_ipywidgets():
    """ipywidgets is an optional extra: `import jaxlens` does not import it, and only
    building an `Explorer` needs it."""
    code = textwrap.dedent(
        """
        import sys
        import jaxlens as jl
        assert "ipywidgets" not in sys.modules
        sys.modules["ipywidgets"] = None  # `import ipywidgets` raises ImportError
        try:
            jl.Explorer(8, 4)
        except ImportError:
            pass
        else:
            raise AssertionError("an Explorer was built without ipywidgets")
        """
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    with pytest.raises(AttributeError, match="no attribute 'Explorr'"):
        jl.Explorr
