"""An interactive explorer (ipywidgets): sliders for the camera and the star, a sky
menu, and the image re-rendered on every change, like the original C++ program's
window.

The widget logic is plain Python: `Explorer.update()` is the callback the sliders
call, and it can be driven without a browser (tests/test_explorer.py does).
"""

import math

import numpy as np

from ._camera import Camera
from ._io import png_bytes
from ._render import render
from ._sky import Checker, DefaultSky, GaussianStar, Panorama, Uniform

SKIES = ("star", "default", "checker", "panorama")


class Explorer:
    """Sliders and an image: distance (R_S, logarithmic), field of view (degrees),
    star offset (longitude and latitude from the point behind the hole, degrees),
    star brightness and size, sky choice, exposure.

    **Arguments:** `width`, `height`: image size in pixels (small keeps it
    interactive); `panorama`: an `(h, w, 3)` equirectangular image for the
    "panorama" sky (default: the procedural sky sampled onto a 512 x 256 grid the
    first time it is chosen); `supersample`: k x k samples a pixel.

    `explorer.widget` is the `ipywidgets` box to display; `explorer.image` holds
    the last linear render `(height, width, 3)`.
    """

    def __init__(self, width: int = 320, height: int = 180, *, panorama=None, supersample=1):
        import ipywidgets as w

        self.width, self.height, self.supersample = int(width), int(height), int(supersample)
        self._panorama = panorama
        style = {"description_width": "9em"}
        layout = w.Layout(width="30em")
        kw = dict(continuous_update=False, style=style, layout=layout)
        self.distance = w.FloatLogSlider(
            value=20.0, base=10, min=math.log10(1.05), max=4, step=0.01,
            description="distance (R_S)", **kw,
        )  # fmt: skip
        self.fov = w.FloatSlider(value=60.0, min=1.0, max=170.0, step=0.5,
                                 description="FOV (deg)", **kw)  # fmt: skip
        self.star_lon = w.FloatSlider(value=0.0, min=-180.0, max=180.0, step=0.1,
                                      description="star lon (deg)", **kw)  # fmt: skip
        self.star_lat = w.FloatSlider(value=0.0, min=-90.0, max=90.0, step=0.1,
                                      description="star lat (deg)", **kw)  # fmt: skip
        self.brightness = w.FloatLogSlider(value=1.0, base=10, min=-2, max=2, step=0.05,
                                           description="star brightness", **kw)  # fmt: skip
        self.sigma = w.FloatLogSlider(value=1.0, base=10, min=-1.5, max=1.2, step=0.05,
                                      description="star sigma (deg)", **kw)  # fmt: skip
        self.sky = w.Dropdown(options=SKIES, value="star", description="sky", style=style)
        self.exposure = w.FloatSlider(value=0.0, min=-6.0, max=6.0, step=0.25,
                                      description="exposure (stops)", **kw)  # fmt: skip
        # Shown at least 320 px wide, at the render's own aspect ratio: both sides fixed
        # and not stretched to the height of the sliders beside it.
        shown = max(self.width, 320)
        px = (shown, max(1, round(self.height * shown / self.width)))
        self.view = w.Image(
            format="png", width=px[0], height=px[1],
            layout=w.Layout(width=f"{px[0]}px", height=f"{px[1]}px", object_fit="contain",
                            align_self="flex-start", flex="0 0 auto"),
        )  # fmt: skip
        self.status = w.Label()
        self.controls = (
            self.distance, self.fov, self.star_lon, self.star_lat, self.brightness, self.sigma,
            self.sky, self.exposure,
        )  # fmt: skip
        for c in self.controls:
            c.observe(self.update, names="value")
        self.widget = w.HBox([w.VBox(list(self.controls) + [self.status]), self.view])
        self.image = None
        self.update()

    def scene(self):
        """The camera and sky the sliders describe."""
        camera = Camera(
            self.distance.value, math.radians(self.fov.value), self.width, self.height,
            supersample=self.supersample, dtype=np.float32,
        )  # fmt: skip
        star = GaussianStar(
            math.radians(self.sigma.value), self.brightness.value,
            lon=math.radians(self.star_lon.value), lat=math.radians(self.star_lat.value),
        )  # fmt: skip
        choice = self.sky.value
        if choice == "star":
            sky = star + Uniform(0.0)
        elif choice == "default":
            sky = DefaultSky() + star
        elif choice == "checker":
            sky = Checker(brightness=0.5) + star
        else:
            sky = Panorama(self._panorama_image()) + star
        return camera, sky

    def _panorama_image(self):
        if self._panorama is None:
            from ._sky import equirectangular

            self._panorama = equirectangular(DefaultSky(), 512, 256, supersample=2)
        return self._panorama

    def update(self, change=None):
        """Render the current settings into the image widget (the slider callback)."""
        import time

        t = time.perf_counter()
        # Sent to the front end at once: a new sky or size compiles for seconds.
        self.status.value = "rendering..."
        try:
            camera, sky = self.scene()
            self.image = render(camera, sky, progress=False)
        except ValueError as e:  # a setting out of range: say so, keep the last image
            self.status.value = f"error: {e}"
            return
        self.view.value = png_bytes(self.image, exposure=self.exposure.value)
        self.status.value = f"{self.width}x{self.height} in {time.perf_counter() - t:.2f} s"

    def _ipython_display_(self):  # pragma: no cover - needs a front end
        from IPython.display import display

        display(self.widget)


def explore(width: int = 320, height: int = 180, **kwargs) -> Explorer:
    """Build an `Explorer` (display it in a notebook cell by leaving it last)."""
    return Explorer(width, height, **kwargs)
