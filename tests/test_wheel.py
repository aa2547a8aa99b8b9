"""A wheel built from the repository works outside it: built with pip (the project's
own build backend), unpacked into a folder that comes first on the path, and used
from another folder, with the repository's files out of reach: the package imports
from the wheel, renders, reads its stored fit table, and the command line runs."""

import os
import subprocess
import sys
import textwrap
import zipfile


def test_wheel_works_outside_the_repository(tmp_path, wheel_site):
    wheel, site = wheel_site  # built with pip and installed into a folder (conftest.py)
    names = zipfile.ZipFile(wheel).namelist()
    assert "jaxlens/_fit/ring_table_data.py" in names and "jaxlens/__main__.py" in names
    assert not [n for n in names if n.startswith(("tests/", "docs/", "notebooks/"))]

    away = tmp_path / "elsewhere"
    away.mkdir()
    # The wheel's copy first on the path (the repository's editable install comes later).
    env = dict(os.environ, PYTHONPATH=str(site), JAXLENS_CACHE_DIR="")
    code = textwrap.dedent(
        """
        import math, jaxlens as jl
        from pathlib import Path
        assert Path(jl.__file__).resolve().is_relative_to(Path(SITE).resolve()), jl.__file__
        cam = jl.Camera(20.0, math.radians(60.0), 12, 8, supersample=1)
        img = jl.render(cam, jl.DefaultSky() + jl.GaussianStar(math.radians(1.0), 1.0))
        assert img.shape == (8, 12, 3) and img.max() > 0
        from jaxlens._fit import starts
        assert len(starts.ring_table()[0]) > 10  # the stored ring table is in the wheel
        print(jl.__version__)
        """
    ).replace("SITE", repr(str(site)))
    run = subprocess.run([sys.executable, "-c", code], cwd=away, env=env, capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    cli = subprocess.run(
        [sys.executable, "-m", "jaxlens", "render", "--size", "12x8", "--supersample", "1",
         "-o", "x.png"],
        cwd=away, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert cli.returncode == 0 and (away / "x.png").is_file(), cli.stderr[-3000:]
    keys = subprocess.run([sys.executable, "-m", "jaxlens", "render", "--scene-keys"], cwd=away,
                          env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert keys.returncode == 0 and "[camera]" in keys.stdout
