"""Compiled programs kept between processes.

XLA's persistent cache keeps compiled programs, but a fresh process still traces and
lowers each program before it can look one up (0.8 s of a 960 x 540 render whose
compiled programs were all in the cache, 6.8 s of a fit). Where a folder is set
(`use_folder`: the command line sets its cache folder, as `keep_programs` does), a
`Stored` function also keeps each executable it compiles
(`jax.experimental.serialize_executable`) in `<folder>/jaxlens-programs`, under a
digest of everything that decides it, and a later process loads and calls it: no
tracing, no lowering, no lookup in XLA's cache.

What decides a program, and so goes into its key: jaxlens's own source files, the
versions of JAX, jaxlib, equinox, lineax and optimistix, the backend and its devices
(the CPU's instruction set: XLA compiles for the host's), `jax_enable_x64`, the
function, and its arguments' structure, static values, shapes and dtypes. A call whose
static values have no faithful text (an object shown by its address) is not stored,
nor is one on more than one device or one with host callbacks; a stored file that
cannot be read is made again. These programs compile past XLA's persistent cache (an
executable it serves would be kept without its code), so each is stored once. A file
is loaded as code (as XLA's own cache loads its entries): the folder must be the
user's own.
"""

import functools
import hashlib
import math
import os
import pathlib
import pickle
import platform
import tempfile
import threading

import equinox as eqx
import jax
import numpy as np

from ._util import has_tracer

_FOLDER: pathlib.Path | None = None
_SUFFIX = ".executable"


def use_folder(folder) -> None:
    """Keep programs in `folder / "jaxlens-programs"` (`None`: keep none, the default)."""
    global _FOLDER
    _FOLDER = None if folder is None else pathlib.Path(folder) / "jaxlens-programs"


def keeping() -> bool:
    """Whether programs are kept (a folder is set)."""
    return _FOLDER is not None


def keep_programs(folder: str | os.PathLike | None = None) -> pathlib.Path | None:
    """Keep this process's compiled programs in a folder, for later processes, as the
    command line does: the next notebook kernel or script that renders a scene,
    traces a batch of rays or fits an image of the same kind and size loads the
    programs instead of compiling them (a default render: ~1.2 s sooner; a ring fit:
    ~6 s).

    Two stores in one folder: JAX's persistent compilation cache (the small programs),
    and the executables of `render`, `trace` and `fit` in its `jaxlens-programs`, which a
    later process loads without tracing them (keyed by everything that decides them:
    jaxlens's code, the versions of JAX and of the libraries it traces, the CPU, the
    shapes and settings; files of older versions are not removed, and the whole folder
    can be deleted at any time). The files are loaded as code, as XLA's own cache
    entries are: keep the folder your own. It applies to the whole process from the
    call on; call it before the first render, trace or fit.

    **Arguments:** `folder`: where to keep them; `None`: `$JAXLENS_CACHE_DIR`, else
    JAX's `$JAX_COMPILATION_CACHE_DIR`, else JAX's `jax_compilation_cache_dir` where
    the script set it, else `~/.cache/jaxlens/xla` (under `$XDG_CACHE_HOME` where
    set). An empty value (`""`, or an empty variable) keeps nothing.

    **Returns:** the folder, or `None` when nothing is kept (an empty value, or a
    folder that cannot be created).
    """
    if folder is None:
        folder = os.environ.get("JAXLENS_CACHE_DIR")
    if folder is None:
        folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if folder is None:
        folder = jax.config.jax_compilation_cache_dir  # set in the script
    if folder is None:
        base = os.environ.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
        folder = pathlib.Path(base) / "jaxlens" / "xla"
    if not str(folder):
        return None
    folder = pathlib.Path(folder).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # Every program: the ones under a second add up (1.8 s of compiling was left in a
    # render with the cache warm when only those over 0.5 s were kept).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    use_folder(folder)
    return folder


def _cpu_flags() -> str:
    """The host CPU's model and instruction-set flags where the system tells them."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [line for line in f if line.startswith(("flags", "model name", "Features"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor() or platform.machine()


def _version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


@functools.cache
def _code_digest() -> str:
    """Digest of jaxlens's source files, the versions of JAX and of the libraries the
    programs trace, the backend and the host."""
    import jaxlib

    h = hashlib.sha256()
    root = pathlib.Path(__file__).parent
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    device = jax.devices()[0]
    h.update(f"{jax.__version__} {jaxlib.__version__} {jax.default_backend()}".encode())
    # The libraries whose code the fit's programs trace (its solver, its linear solves).
    h.update(repr([_version(name) for name in ("equinox", "lineax", "optimistix")]).encode())
    h.update(f"{device.device_kind} {device.client.platform_version}".encode())
    h.update(_cpu_flags().encode())
    # XLA's flags and JAX's settings from the environment change the compiled code.
    skip = "JAX_COMPILATION_CACHE_DIR"
    env = sorted((k, v) for k, v in os.environ.items()
                 if k.startswith(("XLA_", "JAX_")) and k != skip)  # fmt: skip
    h.update(repr(env).encode())
    return h.hexdigest()


@functools.cache
def _lapack_ready() -> None:
    """Set up JAX's LAPACK kernels (for a kept program that calls them), which JAX does
    when it lowers a program that calls them: a loaded program that calls them without
    it would crash the process. Lowering a small QR does it (0.1 s: scipy's LAPACK)."""
    import jax.numpy as jnp

    jax.jit(jnp.linalg.qr).lower(np.zeros((2, 2), np.float32))


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


def _not_written_to_xla_cache():
    """A context in which this thread's compiles are not written to XLA's persistent
    cache. (`jax_enable_compilation_cache` cannot say it for one thread: JAX decides on
    a process's first compile whether it uses the cache, and keeps to that.)"""
    from jax._src import config

    return config.persistent_cache_min_compile_time_secs(math.inf)


_SERVED = threading.local()  # `count`: this thread's hits in XLA's persistent cache


@functools.cache
def _count_cache_hits() -> None:
    def on_event(event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            _SERVED.count = getattr(_SERVED, "count", 0) + 1

    jax.monitoring.register_event_listener(on_event)


class Stored:
    """A jitted function (`eqx.filter_jit`) whose compiled programs are kept in the
    folder `use_folder` set; without one it is the function itself.

    `structure(*args)` gives the pytree structure of the function's result without
    tracing it (a kept program returns the flat leaves); a call checks it against the
    traced result when it compiles a program.
    """

    def __init__(self, fn, structure):
        self._fn = fn
        self._structure = structure
        self._name = f"{fn.__module__}.{getattr(fn, '__qualname__', repr(fn))}"
        self._programs = {}
        self._lock = threading.Lock()  # one entry a key, whichever thread comes first
        self._loading = {}  # the keys `preload_last` is loading: their events

    def _keyed(self, args):
        """`(key, tree, static, leaves)` of a call whose program can be kept (a folder
        set, one device, no tracer among its arrays), else `None`."""
        if not keeping() or jax.device_count() != 1:
            return None
        tree, static, leaves = _split(args)
        if has_tracer(leaves):
            return None  # part of a caller's trace
        key = _key(self._name, tree, static, leaves)
        return None if key is None else (key, tree, static, leaves)

    def _entry(self, args):
        """`(entry, leaves)` of a kept call, or `None`: `entry` holds the executable
        (once loaded or compiled), the program to compile otherwise (`jax.jit` of the
        function on the flat leaves), the result's structure and the file."""
        keyed = self._keyed(args)
        if keyed is None:
            return None
        key, tree, static, leaves = keyed
        with self._lock:
            loading = self._loading.get((_FOLDER, key))
        if loading is not None:  # `preload_last` is loading it: no second load
            loading.wait()
        with self._lock:
            # An entry a folder: a program kept in one is written to the next one set.
            if (_FOLDER, key) not in self._programs:
                self._programs[_FOLDER, key] = self._load(key, args, tree, static, leaves)
            entry = self._programs[_FOLDER, key]
        return None if entry is None else (entry, leaves)

    def _load(self, key, args, tree, static, leaves):
        """The entry of a call: its kept executable, or the program to compile (`None`
        where it cannot be kept: the function is then called as it is)."""
        out_tree = self._structure(*args)
        entry = _new_entry(_FOLDER, key, out_tree)
        if entry["path"].with_suffix(".refused").exists():
            return None
        try:
            entry["compiled"] = _read(entry["path"], len(leaves), out_tree.num_leaves)
        except Exception:  # noqa: BLE001 - missing, partial or from another version
            pass
        if entry["compiled"] is None:
            traced = []

            def flat(*values):
                out = self._fn(*eqx.combine(jax.tree.unflatten(tree, values), static))
                traced.append(jax.tree.structure(out))
                return jax.tree.leaves(out)

            def check():
                if traced and traced[0] != out_tree:
                    raise AssertionError(f"{self._name}: result {traced[0]}, expected {out_tree}")

            # Named apart from the function's own jit, whose entries XLA's cache keeps.
            flat.__name__ = flat.__qualname__ = f"kept_{getattr(self._fn, '__name__', 'fn')}"
            options = getattr(self._fn, "options", lambda: None)()  # `filter_jit_cpu`'s
            entry["program"] = jax.jit(flat, compiler_options=options)
            entry["check"] = check
        return entry

    def _compiled(self, entry, lower):
        """The entry's executable: compiled from `lower()` (the program lowered) and
        kept in its file, where it was not loaded. One compile an entry: a caller that
        comes while another thread compiles it waits for that one."""
        with entry["lock"]:
            if entry["compiled"] is None:
                lowered = lower()
                text = lowered.as_text()
                # Past XLA's persistent cache (the CLI sets one): an executable it
                # serves serialises without its code, and the kept file would then
                # fail in the next process ("Function ... not found"). Not written
                # there (the file keeps it), under a name of its own (no entry of
                # another program matches it); one served all the same is not kept.
                _count_cache_hits()
                served = getattr(_SERVED, "count", 0)
                with _not_written_to_xla_cache():
                    compiled = lowered.compile()
                entry["check"]()
                if getattr(_SERVED, "count", 0) == served:
                    _keep(entry["path"], compiled, text)
                entry["compiled"] = compiled
        return entry["compiled"]

    def __call__(self, *args):
        found = self._entry(args)
        if found is None:
            return self._fn(*args)
        entry, leaves = found
        if entry["compiled"] is None:

            def lower():
                try:
                    return entry["program"].lower(*leaves)
                except Exception as e:  # the function's own call raises it
                    raise _NotLowered from e

            try:
                self._compiled(entry, lower)
            except _NotLowered:
                return self._fn(*args)
        return jax.tree.unflatten(entry["out_tree"], entry["compiled"](*leaves))

    def is_kept(self, *args) -> bool:
        """Whether a call with `args` would find its executable kept (loaded, being
        loaded, or in its file), and so neither trace nor compile. Never waits."""
        keyed = self._keyed(args)
        if keyed is None:
            return False
        key = keyed[0]
        with self._lock:
            if (_FOLDER, key) in self._loading:
                return True
            entry = self._programs.get((_FOLDER, key))
        if entry is not None:
            return entry["compiled"] is not None
        return (_FOLDER / f"{key}{_SUFFIX}").exists()

    def preload(self, *args) -> threading.Thread | None:
        """Load the kept executable of this call on a background thread (returned), for
        a later call with arguments of the same kind (nothing where no folder is set or
        none was kept: this never traces or compiles)."""
        if not keeping():
            return None
        x64 = jax.config.read("jax_enable_x64")

        def load():
            with jax.enable_x64(x64):
                try:
                    self._entry(args)
                except Exception:  # noqa: BLE001, S110 - the call itself reports it
                    pass

        thread = threading.Thread(target=load, name="jaxlens-preload", daemon=True)
        thread.start()
        return thread

    def _hint_path(self, hint: str) -> pathlib.Path:
        digest = hashlib.sha256(f"{self._name}\0{hint}".encode()).hexdigest()[:32]
        return _FOLDER / "last" / digest

    def note(self, hint: str, *args) -> None:
        """Note under `hint` (any text that a caller knows before it has the arguments)
        the key of a call with `args`, for `preload_last` in a later process."""
        if not keeping() or jax.device_count() != 1:
            return
        tree, static, leaves = _split(args)
        key = _key(self._name, tree, static, leaves)
        path = self._hint_path(hint)
        text = f"{key} {len(leaves)}"
        try:
            if key is None or path.read_text() == text:
                return
        except OSError:
            pass
        _write(path, text.encode())

    def preload_last(self, hint: str) -> threading.Thread | None:
        """Load on a background thread (returned) the kept executable of the call last
        noted under `hint` (`note`), before the arguments of the next call are known:
        a call with the same key then finds it loaded, and one with another key does
        not wait for it. For a function whose result's structure does not depend on
        its arguments. Nothing where no folder is set or no call was noted."""
        if not keeping():
            return None
        folder = _FOLDER
        try:
            key, n_in = self._hint_path(hint).read_text().split()
            n_in = int(n_in)
        except (OSError, ValueError):
            return None
        with self._lock:
            if (folder, key) in self._programs or (folder, key) in self._loading:
                return None
            done = self._loading[folder, key] = threading.Event()

        def load():
            try:
                entry = _new_entry(folder, key, self._structure())
                entry["compiled"] = _read(entry["path"], n_in, entry["out_tree"].num_leaves)
                with self._lock:
                    self._programs.setdefault((folder, key), entry)
            except Exception:  # noqa: BLE001, S110 - missing or stale: the call compiles
                pass
            finally:
                with self._lock:
                    del self._loading[folder, key]
                done.set()

        thread = threading.Thread(target=load, name="jaxlens-preload", daemon=True)
        thread.start()
        return thread

    def lower(self, *args):
        """The call lowered, for `compile_ahead`: the function's, or the kept
        program's, whose executable the next call then uses."""
        found = self._entry(args)
        if found is None:
            return self._fn.lower(*args)
        entry, leaves = found
        if entry["compiled"] is not None:
            return _Lowered(self, entry, None)
        return _Lowered(self, entry, entry["program"].lower(*leaves))


def _split(args):
    """`(tree, static, leaves)` of a call's arguments: the structure and leaves of its
    arrays, and the rest (`eqx.partition`)."""
    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, tree = jax.tree.flatten(dyn)
    return tree, static, leaves


def _new_entry(folder: pathlib.Path, key: str, out_tree) -> dict:
    """An entry of `Stored._programs` for `key` in `folder`: nothing loaded yet."""
    return {"out_tree": out_tree, "path": folder / f"{key}{_SUFFIX}", "compiled": None,
            "program": None, "lock": threading.Lock()}  # fmt: skip


class _NotLowered(Exception):
    """A kept program's function failed to trace (its own call then says why)."""


class _Lowered:
    """A kept program lowered: `compile()` compiles and keeps the executable for its
    calls (or gives the one loaded)."""

    def __init__(self, stored, entry, lowered):
        self._stored, self._entry, self._lowered = stored, entry, lowered

    def compile(self):
        return self._stored._compiled(self._entry, lambda: self._lowered)


def _keep(path: pathlib.Path, compiled, text: str) -> None:
    """Write `compiled` to `path` with what loading it needs (whether it calls JAX's
    LAPACK kernels); a program with host callbacks is not kept (`.refused`)."""
    if "callback" in text:
        _write(path.with_suffix(".refused"), b"")
        return
    from jax.experimental import serialize_executable

    try:
        payload = serialize_executable.serialize(compiled)[0]
    except Exception:  # noqa: BLE001 - a backend that cannot serialise: not kept
        _write(path.with_suffix(".refused"), b"")
        return
    _write(path, pickle.dumps({"lapack": "lapack" in text, "payload": payload}))


def _read(path: pathlib.Path, n_in: int, n_out: int):
    """The executable kept in `path` (for `n_in` flat arguments and `n_out` results)."""
    from jax.experimental import serialize_executable

    kept = pickle.loads(path.read_bytes())  # noqa: S301 - the user's own cache folder
    if kept["lapack"]:
        _lapack_ready()
    in_tree = jax.tree.structure((tuple(range(n_in)), {}))
    out_tree = jax.tree.structure(list(range(n_out)))
    compiled = serialize_executable.deserialize_and_load(kept["payload"], in_tree, out_tree)
    if len(compiled.out_info) != n_out:
        raise ValueError(f"{path}: {len(compiled.out_info)} results, expected {n_out}")
    return compiled
