"""Make the README's images with the library (nothing downloaded):

    .venv/bin/python docs/make_images.py [--quick] [--out DIR]

`--quick` renders every image at a quarter of its size (a smoke test); `--out DIR`
writes them to DIR instead of `docs/images/`.

- `images/ring.png`: a star exactly behind the hole seen from D = 20 R_S: the Einstein
  ring at 20.2039 degrees, the shadow, the faint relativistic rings at its edge.
- `images/milkyway_panorama.jpg`: the procedural Milky-Way-like sky sampled onto a
  2048 x 1024 equirectangular grid (the panorama itself).
- `images/milkyway.png`: that panorama around the shadow, from D = 12 R_S.
- `images/approach_strip.png`: six frames of an approach from D = 1e5 to 3 R_S.
"""

import argparse
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

import jaxlens as jl  # noqa: E402

OUT = ROOT / "docs" / "images"
F32 = np.float32


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a quarter of each size (smoke test)")
    ap.add_argument("--out", type=pathlib.Path, default=OUT, help="folder (default docs/images)")
    args = ap.parse_args(argv)
    out, q = args.out, 4 if args.quick else 1
    out.mkdir(parents=True, exist_ok=True)
    deg = math.radians

    ring = jl.render(jl.Camera(20.0, deg(60.0), 640 // q, 360 // q, supersample=4, dtype=F32),
                     jl.GaussianStar(deg(1.0), 1.0))  # fmt: skip
    jl.write_image(out / "ring.png", ring, exposure=0.5)

    pano = jl.equirectangular(jl.DefaultSky(), 2048 // q, 1024 // q, supersample=2)
    jl.write_image(out / "milkyway_panorama.jpg", pano[::2, ::2], exposure=1.0)
    sky = jl.Panorama(pano)
    view = jl.render(jl.Camera(12.0, deg(75.0), 640 // q, 360 // q, supersample=3, dtype=F32),
                     sky)  # fmt: skip
    jl.write_image(out / "milkyway.png", view, exposure=1.0)

    distances = np.geomspace(1e5, 3.0, 6)
    w, h = 192 // q, 108 // q
    base = jl.Camera(20.0, deg(120.0), w, h, supersample=3, dtype=F32)
    frames = jl.render(jl.Scene(jl.approach(base, distances), sky))  # one image a frame
    pad = 4
    strip = Image.new("RGB", (len(frames) * (w + pad) - pad, h + 16), "white")
    draw = ImageDraw.Draw(strip)
    for i, (frame, d) in enumerate(zip(frames, distances)):
        x = i * (w + pad)
        strip.paste(Image.fromarray(jl.to_display(frame, exposure=1.0)), (x, 16))
        draw.text((x + 4, 2), f"D = {d:.3g} R_S", fill="black")
    strip.save(out / "approach_strip.png", optimize=True)
    for p in sorted(out.iterdir()):
        shown = p.relative_to(ROOT) if p.is_relative_to(ROOT) else p
        print(f"{shown}: {p.stat().st_size / 1024:.0f} KB")


if __name__ == "__main__":
    main()
