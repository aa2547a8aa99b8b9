"""The stub jaxlens/__init__.pyi shows type checkers and editors the same public names
as the lazy `_MODULES` of jaxlens/__init__.py, each from the module that serves it, and
is what tools/make_stub.py writes; shipping it changes nothing at run time."""

import ast
import runpy
import subprocess
import sys
from pathlib import Path

import jaxlens as jl

ROOT = Path(__file__).resolve().parents[1]
STUB = ROOT / "jaxlens" / "__init__.pyi"


def _stub_names() -> tuple[dict[str, str], list[str]]:
    """The stub's `from .MODULE import NAME as NAME` pairs (name -> module) and its
    `__all__`."""
    where, every = {}, None
    for node in ast.parse(STUB.read_text()).body:
        if isinstance(node, ast.ImportFrom):
            assert node.level == 1, ast.unparse(node)
            for alias in node.names:
                # `X as X`: what a type checker takes as re-exported by the package
                assert alias.asname == alias.name, ast.unparse(node)
                assert alias.name not in where, f"{alias.name} imported twice"
                where[alias.name] = node.module
        elif isinstance(node, ast.Assign) and ast.unparse(node.targets[0]) == "__all__":
            every = ast.literal_eval(node.value)
    return where, every


def test_stub_lists_the_names_and_modules_of_the_lazy_loader():
    where, every = _stub_names()
    # The same names (none added, none left out), each from the module that loads it.
    assert where == jl._WHERE
    assert every == jl.__all__


def test_stub_is_what_the_generator_writes():
    run = subprocess.run([sys.executable, str(ROOT / "tools" / "make_stub.py"), "--check"],
                         capture_output=True, text=True)  # fmt: skip
    assert run.returncode == 0, run.stderr


def test_generator_follows_a_changed_loader():
    # A name added to `_MODULES` appears in the stub; one removed disappears.
    stub = runpy.run_path(str(ROOT / "tools" / "make_stub.py"))["stub"]
    changed = {m: n for m, n in jl._MODULES.items() if m != "_weak"}
    changed["_trace"] = (*changed["_trace"], "new_name")
    text = stub(changed)
    assert "from ._trace import (" in text and "    new_name as new_name," in text
    assert '    "new_name",' in text and "weak_field_escape_angle" not in text


def test_import_still_loads_no_jax_and_runs_the_source():
    # Python never reads a .pyi: `import jaxlens` runs __init__.py and stays lazy.
    code = "import sys, jaxlens\nprint(jaxlens.__file__)\nprint(' '.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split("\n")  # fmt: skip
    assert out[0].endswith("__init__.py")
    assert not {"jax", "numpy", "equinox"} & set(out[1].split())
