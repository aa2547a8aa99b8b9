"""The package's import is lazy: names load on first use, the CLI's parser needs no JAX."""

import subprocess
import sys

import pytest

import jaxlens as jl


def _modules_after(code: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sys.modules))"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return set(out.split())


def test_import_loads_no_jax():
    loaded = _modules_after("import jaxlens")
    assert not {"jax", "optimistix", "equinox", "matplotlib", "ipywidgets"} & loaded


def test_cli_parser_and_help_load_no_jax():
    loaded = _modules_after(
        "import contextlib, io\n"
        "from jaxlens.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    main(['render', '--help'])"
    )
    assert "jax" not in loaded and "jaxlens._scene" not in loaded


def test_first_use_loads_the_defining_module():
    loaded = _modules_after("import jaxlens\njaxlens.trace")
    assert {"jax", "jaxlens._trace"} <= loaded and "optimistix" not in loaded


@pytest.mark.parametrize("name", sorted(set(jl.__all__) - {"Explorer"}))
def test_every_public_name_resolves(name):
    # A name listed for the wrong module raises AttributeError here.
    assert getattr(jl, name) is not None
    assert name in dir(jl)


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'tracee'"):
        jl.tracee  # noqa: B018
    assert "__version__" in dir(jl) and jl.__version__


@pytest.mark.parametrize("writes_png", [False, True])
def test_importing_jaxlens_leaves_the_interpreter_exit_as_it_is(tmp_path, writes_png):
    # An exit handler registered before any of jaxlens's runs after them (last in,
    # first out) and sees what they left: the collector not frozen.
    code = (
        "import atexit, gc\n"
        "atexit.register(lambda: print('frozen', gc.get_freeze_count() > 0))\n"
        "import numpy as np, jaxlens as jl\n"
        "jl.trace(np.linspace(0.1, 3.0, 64), 10.0)\n"
    )
    if writes_png:
        code += f"jl.write_image({str(tmp_path / 'a.png')!r}, np.ones((4, 4, 3)))\n"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)  # fmt: skip
    assert done.stdout.split()[-2:] == ["frozen", "False"]
    # OpenImageIO's binding reports the objects a frozen exit leaves as leaks.
    assert "leak" not in done.stderr
