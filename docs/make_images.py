"""Make the README's images with the library (nothing downloaded):

    .venv/bin/python docs/make_images.py

- `images/ring.png`: a star exactly behind the hole seen from D = 20 R_S: the Einstein
  ring at 20.2039 degrees, the shadow, the faint relativistic rings at its edge.
- `images/milkyway_panorama.jpg`: the procedural Milky-Way-like sky sampled onto a
  2048 x 1024 equirectangular grid (the panorama itself).
- `images/milkyway.png`: that panorama around the shadow, from D = 12 R_S.
- `images/approach_strip.png`: six frames of an approach from D = 1e5 to 3 R_S.
"""

import math
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from PIL import Image, ImageDraw  # noqa: E402

from jaxlens import (  # noqa: E402
    Camera,
    DefaultSky,
    GaussianStar,
    Panorama,
    approach,
    equirectangular,
    render,
    render_frames,
    to_display,
    write_image,
)

OUT = ROOT / "docs" / "images"
F32 = np.float32


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    deg = math.radians

    ring = render(Camera(20.0, deg(60.0), 640, 360, supersample=4, dtype=F32),
                  GaussianStar(deg(1.0), 1.0))  # fmt: skip
    write_image(OUT / "ring.png", ring, exposure=0.5)

    pano = equirectangular(DefaultSky(), 2048, 1024, supersample=2)
    write_image(OUT / "milkyway_panorama.jpg", pano[::2, ::2], exposure=1.0)
    sky = Panorama(pano)
    view = render(Camera(12.0, deg(75.0), 640, 360, supersample=3, dtype=F32), sky)
    write_image(OUT / "milkyway.png", view, exposure=1.0)

    distances = np.geomspace(1e5, 3.0, 6)
    base = Camera(20.0, deg(120.0), 192, 108, supersample=3, dtype=F32)
    frames = render_frames(approach(base, distances), sky)
    pad = 4
    strip = Image.new("RGB", (len(frames) * (192 + pad) - pad, 108 + 16), "white")
    draw = ImageDraw.Draw(strip)
    for i, (frame, d) in enumerate(zip(frames, distances)):
        x = i * (192 + pad)
        strip.paste(Image.fromarray(to_display(frame, exposure=1.0)), (x, 16))
        draw.text((x + 4, 2), f"D = {d:.3g} R_S", fill="black")
    strip.save(OUT / "approach_strip.png", optimize=True)
    for p in sorted(OUT.iterdir()):
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
