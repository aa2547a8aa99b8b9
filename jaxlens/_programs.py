"""Traced programs kept between processes (`jax.export`).

XLA's persistent cache keeps compiled programs, but a fresh process still traces and
lowers each program before it can look one up (0.8 s of a 960 x 540 render whose
compiled programs were all in the cache, 6.8 s of a fit). Where a folder is set
(`use_folder`: the command line sets its cache folder), a `Stored` function also keeps
its lowered program (StableHLO, serialised by `jax.export`) in
`<folder>/jaxlens-programs`, under a digest of everything that decides it, and a later
process calls that program without tracing the function; XLA's cache then supplies the
compiled code. (Reading a kept program back costs some of that again: the render
starts 0.3 s sooner, the fit 4.5 s.)

What decides a program, and so goes into its key: jaxlens's own source files, the
versions of JAX and jaxlib, the backend, `jax_enable_x64`, the function, and its
arguments' structure, static values, shapes and dtypes. A call whose static values
have no faithful text (an object shown by its address) is not stored, nor is one on
more than one device; a stored file that cannot be read is made again.
"""

import functools
import hashlib
import os
import pathlib
import tempfile

import equinox as eqx
import jax
import numpy as np

_FOLDER: pathlib.Path | None = None
# A stored program is only ever used by the JAX and backend that stored it (both are in
# its key), so the guarantee of custom calls (LAPACK's, for the fit's QR and
# eigensolver) across versions is not needed: every target is allowed ("ALL", in newer
# JAX), and by name those the fit uses (for older JAX, which knows no "ALL").
_CHECKS = [jax.export.DisabledSafetyCheck.custom_call(t) for t in
           ["ALL"] + [f"lapack_{p}{op}_ffi" for p in "sd" for op in ("ormqr", "orgqr", "geqrf",
                                                                    "syevd", "gesdd")]]  # fmt: skip


def use_folder(folder) -> None:
    """Keep programs in `folder / "jaxlens-programs"` (`None`: keep none, the default)."""
    global _FOLDER
    try:
        import flatbuffers  # noqa: F401  (jax.export's serialisation needs it)
    except ImportError:
        folder = None
    _FOLDER = None if folder is None else pathlib.Path(folder) / "jaxlens-programs"


@functools.cache
def _code_digest() -> str:
    """Digest of jaxlens's source files, the JAX versions and the backend."""
    import jaxlib

    h = hashlib.sha256()
    root = pathlib.Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    h.update(f"{jax.__version__} {jaxlib.__version__} {jax.default_backend()}".encode())
    return h.hexdigest()


def _key(name: str, tree, static, leaves) -> str | None:
    """The key of a call, or `None` where a static value has no faithful text."""
    text = repr((tree, jax.tree.structure(static), jax.tree.leaves(static)))
    if " at 0x" in text:
        return None
    avals = [(x.shape, x.dtype.name, bool(getattr(x, "weak_type", False))) for x in leaves]
    x64 = jax.dtypes.canonicalize_dtype(np.float64) == np.float64  # this thread's setting
    blob = repr((_code_digest(), name, x64, text, avals)).encode()
    return hashlib.sha256(blob).hexdigest()[:32]


def _write(path: pathlib.Path, data: bytes) -> None:
    """Write atomically (a reader sees the whole file or none); failures are ignored:
    the program is then traced again next time."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError:
        pass


class Stored:
    """A jitted function (`eqx.filter_jit`) whose lowered programs are kept in the
    folder `use_folder` set; without one it is the function itself.

    `structure(*args)` gives the pytree structure of the function's result without
    tracing it (a stored program returns the flat leaves); a call checks it against
    the traced result when it stores a program.
    """

    def __init__(self, fn, structure):
        self._fn = fn
        self._structure = structure
        self._name = f"{fn.__module__}.{getattr(fn, '__qualname__', repr(fn))}"
        self._programs = {}

    def _entry(self, args):
        """`(entry, leaves)` of a stored call, or `None`: `entry` holds the program
        (`jax.jit` of the exported call), the result's structure and, once compiled
        ahead (`lower`), its executable."""
        if _FOLDER is None or jax.device_count() != 1:
            return None
        dyn, static = eqx.partition(args, eqx.is_array)
        leaves, tree = jax.tree.flatten(dyn)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return None  # part of a caller's trace
        key = _key(self._name, tree, static, leaves)
        if key is None:
            return None
        if key not in self._programs:
            self._programs[key] = self._load(key, args, tree, static, leaves)
        entry = self._programs[key]
        return None if entry is None else (entry, leaves)

    def _load(self, key, args, tree, static, leaves):
        """The entry of a call: its stored program, or one exported now (`None` where
        `jax.export` cannot keep it: the function is then called as it is)."""
        out_tree = self._structure(*args)
        path = _FOLDER / f"{key}.jaxexport"
        refused = path.with_suffix(".refused")  # jax.export could not keep it: not again
        if refused.exists():
            return None
        exported = None
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
            if len(exported.out_avals) != out_tree.num_leaves:
                exported = None
        except Exception:  # noqa: BLE001 - missing, partial or from another version
            exported = None
        if exported is None:
            traced = []

            def flat(*values):
                out = self._fn(*eqx.combine(jax.tree.unflatten(tree, values), static))
                traced.append(jax.tree.structure(out))
                return jax.tree.leaves(out)

            try:
                exported = jax.export.export(jax.jit(flat), disabled_checks=_CHECKS)(*leaves)
            except Exception:  # noqa: BLE001 - e.g. a host callback; or the call's own
                _write(refused, b"")  # error, which the function's own call then raises
                return None
            if traced[0] != out_tree:
                raise AssertionError(f"{self._name}: result {traced[0]}, expected {out_tree}")
            _write(path, bytes(exported.serialize()))
        options = getattr(self._fn, "options", lambda: None)()  # `filter_jit_cpu`'s
        program = jax.jit(exported.call, compiler_options=options)
        return {"program": program, "out_tree": out_tree, "compiled": None}

    def __call__(self, *args):
        found = self._entry(args)
        if found is None:
            return self._fn(*args)
        entry, leaves = found
        run = entry["compiled"] or entry["program"]
        return jax.tree.unflatten(entry["out_tree"], run(*leaves))

    def lower(self, *args):
        """The call lowered, for `compile_ahead`: the function's, or the stored
        program's, whose executable the next call then uses."""
        found = self._entry(args)
        if found is None:
            return self._fn.lower(*args)
        entry, leaves = found
        return _Lowered(entry, entry["program"].lower(*leaves))


class _Lowered:
    """A stored program lowered: `compile()` keeps the executable for its calls."""

    def __init__(self, entry, lowered):
        self._entry, self._lowered = entry, lowered

    def compile(self):
        self._entry["compiled"] = compiled = self._lowered.compile()
        return compiled
