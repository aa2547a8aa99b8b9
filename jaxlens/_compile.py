"""Where compilation lives: XLA's option profiles, the `program` wrapper, the programs
kept between processes, and the compiles a host driver asks for ahead.

- **Profiles** (`PROFILES`): XLA option sets a program may compile with on the CPU
  backend (other backends compile with XLA's defaults). XLA refuses an option it does
  not know by name; a profile's option that the installed XLA does not know is then
  dropped for the rest of the process, with one warning, and the program compiles
  without it (`_known_options`). Why each profile exists, and what it saves, is
  measured in `benchmarks/results/latency.md`.
- **`program(fn, profile=..., keep=True)`**: `fn` jitted with arrays traced and every
  other argument static (as `eqx.filter_jit`), compiled with its profile. Called inside
  another trace, it is part of that trace (no options: JAX takes them at the top only).
- **Kept programs**: where a folder is set (`keep_programs`; the command line sets
  its cache folder), a program's executable is also written to
  `<folder>/jaxlens-programs` with the structure of its result, under a digest of all
  that decides it (`_key`), and a later process loads and calls it: no tracing, no
  lowering, no look-up in XLA's cache. A file is loaded as code (as XLA's own cache
  entries are): the folder must be the user's own.
- **`ahead(*calls)`**: the one way to compile on a second core, for host drivers
  (`render`, `fit`, an eager `trace` through a table): the calls' programs are
  lowered by the caller, compiled on a thread while the driver's block runs, and
  waited for at its end.
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
import warnings

import equinox as eqx
import jax
import numpy as np

from ._util import has_tracer

# XLA's own fusion emitters off: the CPU backend's older loop fusion, whose code for
# these programs compiles in about half the time and runs as fast.
_LEGACY_FUSION = {"xla_cpu_use_fusion_emitters": False}
# The code generated in one piece, not split over the cores: for a program that compiles
# beside another, which then keeps the other core.
_ONE_PIECE = {"xla_cpu_parallel_codegen_split_count": 1}

PROFILES = {
    # XLA's defaults: programs that run many times on much data (a render's blocks).
    "xla": {},
    # The older fusion, LLVM at level 1 (XLA's default is 3): programs whose compile is
    # long and that run a few times or often (the fit's solver, loss and start search,
    # the exact trace, a ray-map look-up), which run as fast.
    "legacy_fusion_o1": {**_LEGACY_FUSION, "xla_backend_optimization_level": 1},
    # ... with LLVM's optimisations off, in one piece: programs that run once or twice
    # on little data and compile beside another (a ray map's table, the fit's noise
    # check).
    "legacy_fusion_o0_side": {**_LEGACY_FUSION, **_ONE_PIECE, "xla_backend_optimization_level": 0},
}

_UNKNOWN: set[str] = set()  # options the installed XLA refused by name
_UNKNOWN_LOCK = threading.Lock()


def options(profile: str) -> dict | None:
    """The XLA options of `profile` on the current backend (`None`: XLA's defaults),
    without those this XLA does not know."""
    if jax.default_backend() != "cpu":
        return None
    return {k: v for k, v in PROFILES[profile].items() if k not in _UNKNOWN} or None


def _known_options(run):
    """`run()`; where XLA refuses one of the profiles' options by name (a jaxlib that
    renamed or removed it), that option is dropped from every profile and `run()`
    runs again (it must build its program from `options` anew)."""
    while True:
        try:
            return run()
        except Exception as e:  # noqa: BLE001 - re-raised unless an option is named
            text = str(e)
            named = {k for p in PROFILES.values() for k in p if k in text} - _UNKNOWN
            if not named or "option" not in text.lower():
                raise
            with _UNKNOWN_LOCK:
                _UNKNOWN.update(named)
            warnings.warn(f"XLA does not know the compile option(s) {sorted(named)}: "
                          "compiling without them", RuntimeWarning, stacklevel=3)  # fmt: skip


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
    programs instead of compiling them (`benchmarks/results/latency.md`: the
    "warm cache" rows).

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
    # Every program: the ones under a second add up.
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
    it would crash the process. Lowering a small QR does it."""
    import jax.numpy as jnp

    jax.jit(jnp.linalg.qr).lower(np.zeros((2, 2), np.float32))


def _key(name: str, opts, tree, static, leaves) -> str | None:
    """The key of a call, or `None` where a static value has no faithful text."""
    text = repr((tree, jax.tree.structure(static), jax.tree.leaves(static)))
    if " at 0x" in text:
        return None
    avals = [(x.shape, x.dtype.name, bool(getattr(x, "weak_type", False))) for x in leaves]
    x64 = jax.dtypes.canonicalize_dtype(np.float64) == np.float64  # this thread's setting
    blob = repr((_code_digest(), name, opts, x64, text, avals)).encode()
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


class _Static:
    """The non-array part of a call's arguments (`eqx.partition`), hashable: a static
    argument of `jax.jit`."""

    def __init__(self, tree):
        self.leaves, self.treedef = jax.tree.flatten(tree)
        self._hash = hash((tuple(self.leaves), self.treedef))

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        return (isinstance(other, _Static) and self.treedef == other.treedef
                and self.leaves == other.leaves)  # fmt: skip

    def tree(self):
        return jax.tree.unflatten(self.treedef, self.leaves)


class _Call:
    """A call's arguments split: the structure and leaves of its arrays, the rest (and
    the rest made hashable once: `jax.jit`'s static argument and part of the call's
    signature)."""

    def __init__(self, args):
        dynamic, static = eqx.partition(args, eqx.is_array)
        self.leaves, self.tree = jax.tree.flatten(dynamic)
        self.dynamic, self.static = dynamic, static
        self.hashable = _Static(static)

    def traced(self) -> bool:
        return has_tracer(self.leaves)

    def signature(self):
        """What decides the call's program in this process (hashable)."""
        avals = tuple((x.shape, x.dtype, bool(getattr(x, "weak_type", False)))
                      for x in self.leaves)  # fmt: skip
        return self.tree, self.hashable, avals


class _Kept:
    """A program kept in a file: its executable once loaded or compiled, else the
    program to compile (`jax.jit` of the function on the flat leaves), and the
    structure of its result (recorded when traced, stored in the file)."""

    def __init__(self, path: pathlib.Path):
        self.path = path
        self.compiled = None
        self.out_tree = None
        self.program = None
        self.traced = []  # the result's structure, once traced
        self.lock = threading.Lock()


class _NotLowered(Exception):
    """A kept program's function failed to trace (its own call then says why)."""


class Program:
    """A function compiled as one program with its XLA profile, kept between processes
    where a folder is set. Made by `program`."""

    def __init__(self, fn, profile: str, keep: bool):
        if profile not in PROFILES:
            raise ValueError(f"profile={profile!r}: one of {sorted(PROFILES)}")
        functools.update_wrapper(self, fn)
        self._fn, self.profile, self.keep = fn, profile, keep
        self._name = f"{fn.__module__}.{getattr(fn, '__qualname__', repr(fn))}"
        self._jits = {}  # (backend, options) -> jax.jit; "nested": inside a trace
        self._kept = {}  # (folder, key) -> _Kept (None: not keepable)
        self._scheduled = set()  # the signatures called or compiled ahead so far
        self._lock = threading.Lock()

    # ---------------------------------------------------------------- plain jit
    def _jit(self, nested: bool = False):
        opts = None if nested else options(self.profile)
        key = "nested" if nested else (jax.default_backend(), repr(opts))
        if key not in self._jits:
            fn = self._fn

            def call(dynamic, static):
                return fn(*eqx.combine(dynamic, static.tree()))

            call.__name__ = call.__qualname__ = fn.__name__  # as profiles name it
            self._jits[key] = jax.jit(call, static_argnums=1, compiler_options=opts)
        return self._jits[key]

    # ---------------------------------------------------------------- kept programs
    def _entry(self, c: _Call, load: bool = True) -> "_Kept | None":
        """The kept program of call `c` (loaded from its file where `load`), or `None`
        where it cannot be kept: no folder set, several devices, a static value without
        a faithful text, a program refused before (host callbacks)."""
        if not (self.keep and keeping()) or jax.device_count() != 1:
            return None
        key = _key(self._name, options(self.profile), c.tree, c.static, c.leaves)
        if key is None:
            return None
        folder = _FOLDER
        with self._lock:  # one entry a key, whichever thread comes first
            if (folder, key) not in self._kept:
                path = folder / f"{key}{_SUFFIX}"
                self._kept[folder, key] = (None if path.with_suffix(".refused").exists()
                                           else _Kept(path))  # fmt: skip
            entry = self._kept[folder, key]
        if entry is not None and load:
            with entry.lock:
                if entry.compiled is None and entry.program is None:
                    self._load(entry, c)
        return entry

    def _load(self, entry: _Kept, c: _Call) -> None:
        """Read `entry`'s executable from its file, else make the program to compile."""
        try:
            entry.compiled, entry.out_tree = _read(entry.path, len(c.leaves))
            return
        except Exception:  # noqa: BLE001, S110 - missing, partial or of another version
            pass
        fn, tree, static, traced = self._fn, c.tree, c.static, []

        def flat(*values):
            out = fn(*eqx.combine(jax.tree.unflatten(tree, values), static))
            traced.append(jax.tree.structure(out))
            return jax.tree.leaves(out)

        # Named apart from the function's own jit, whose entries XLA's cache keeps.
        flat.__name__ = flat.__qualname__ = f"kept_{getattr(fn, '__name__', 'fn')}"
        entry.program = jax.jit(flat, compiler_options=options(self.profile))
        entry.traced = traced

    def _compile_kept(self, entry: _Kept, lower) -> None:
        """Compile `lower()` (the kept program lowered) where `entry` has no executable
        yet, and keep it in its file. One compile an entry: a caller that comes while
        another thread compiles it waits for that one."""
        with entry.lock:
            if entry.compiled is not None:
                return
            lowered = lower()
            text = lowered.as_text()
            # Past XLA's persistent cache (the CLI sets one): an executable it serves
            # serialises without its code, and the kept file would fail in the next
            # process ("Function ... not found"). Not written there (the file keeps
            # it); one served all the same is not kept.
            _count_cache_hits()
            served = getattr(_SERVED, "count", 0)
            with _not_written_to_xla_cache():
                compiled = lowered.compile()
            entry.out_tree = entry.traced[0]
            if getattr(_SERVED, "count", 0) == served:
                _keep(entry.path, compiled, text, entry.out_tree)
            entry.compiled = compiled

    def _lower_kept(self, entry: _Kept, c: _Call):
        try:
            return entry.program.lower(*c.leaves)
        except Exception as e:  # the function's own call raises it
            raise _NotLowered from e

    # ---------------------------------------------------------------- calls
    def __call__(self, *args):
        c = _Call(args)
        if c.traced():  # part of a caller's trace
            return self._jit(nested=True)(c.dynamic, c.hashable)
        return _known_options(lambda: self._call(c))

    def _call(self, c: _Call):
        entry = self._entry(c)
        if entry is not None:
            try:
                self._compile_kept(entry, lambda: self._lower_kept(entry, c))
            except _NotLowered:
                entry = None  # the function's own call says why
        if entry is None:
            out = self._jit()(c.dynamic, c.hashable)
        else:
            out = jax.tree.unflatten(entry.out_tree, entry.compiled(*c.leaves))
        self._scheduled.add(c.signature())
        return out

    def _ahead(self, *args):
        """A compile of this call for `ahead`: `None` where it is compiled already,
        else a function to run on the thread, this call's program lowered here (a
        trace on the thread would take turns with the caller's for the GIL) or, where
        it is kept in a file, loaded there."""
        c = _Call(args)
        signature = c.signature()
        if c.traced() or signature in self._scheduled:
            return None
        self._scheduled.add(signature)
        entry = self._entry(c, load=False)
        if entry is None:
            lowered = self._jit().lower(c.dynamic, c.hashable)
            return lowered.compile
        if entry.compiled is not None:
            return None
        if entry.program is None and entry.path.exists():
            return lambda: self._entry(c)  # loaded on the thread
        self._entry(c)
        if entry.compiled is not None:
            return None
        lowered = self._lower_kept(entry, c)
        return lambda: self._compile_kept(entry, lambda: lowered)

    def lower(self, *args):
        """The call lowered (`jax.stages.Lowered`), as `jax.jit(...).lower` gives it."""
        c = _Call(args)
        return self._jit().lower(c.dynamic, c.hashable)


def program(fn=None, *, profile: str = "xla", keep: bool = True):
    """`fn` as one compiled program: arrays traced, every other argument static (as
    `eqx.filter_jit`), compiled on the CPU with the XLA options of `profile` (a key of
    `PROFILES`) and, where `keep`, kept between processes in the folder
    `keep_programs` set. Used as `@program(profile=...)` or `program(fn, ...)`."""
    if fn is None:
        return functools.partial(program, profile=profile, keep=keep)
    return Program(fn, profile, keep)


class ahead:
    """Compile `calls` (each `(program, *args)`: a `Program` and arguments of the kind a
    later call will have) on a thread, started at once; `with ahead(...): ...` runs the
    block meanwhile and waits for the compiles at its end (not where it raises). For
    host drivers (`render`, `fit`, an eager `trace`): a program the driver needs next
    compiles on the second core while the current one compiles or runs (XLA compiles
    without holding the GIL). Each call's program is lowered here, by the caller (a
    trace on the thread would take turns with the caller's for the GIL), or loaded on
    the thread where it is kept; a call compiled or scheduled before is skipped. A
    failed compile is left to the later call to report.
    """

    def __init__(self, *calls):
        work = []
        for prog, *args in calls:
            try:
                step = prog._ahead(*args)
            except Exception:  # noqa: BLE001, S112 - the call itself reports it
                continue
            if step is not None:
                work.append(step)
        self._thread = None
        if work:
            x64 = jax.config.read("jax_enable_x64")

            def run():
                with jax.enable_x64(x64):
                    for step in work:
                        try:
                            step()
                        except Exception:  # noqa: BLE001, S112 - the call reports it
                            continue

            self._thread = threading.Thread(target=run, name="jaxlens-compile", daemon=True)
            self._thread.start()

    def wait(self) -> None:
        """Wait for the compiles (a later call of these programs then finds them)."""
        if self._thread is not None:
            self._thread.join()

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb):
        if kind is None:
            self.wait()
        return False


def _keep(path: pathlib.Path, compiled, text: str, out_tree) -> None:
    """Write `compiled` to `path` with what loading it needs: the structure of its
    result (an instance of it, which a later process flattens) and whether it calls
    JAX's LAPACK kernels. A program with host callbacks, or whose result's structure
    cannot be written, is not kept (`.refused`)."""
    if "callback" in text:
        _write(path.with_suffix(".refused"), b"")
        return
    from jax.experimental import serialize_executable

    try:
        payload = serialize_executable.serialize(compiled)[0]
        shape = pickle.dumps(jax.tree.unflatten(out_tree, [0] * out_tree.num_leaves))
    except Exception:  # noqa: BLE001 - a backend or a result that cannot be written
        _write(path.with_suffix(".refused"), b"")
        return
    _write(path, pickle.dumps({"lapack": "lapack" in text, "payload": payload,
                               "result": shape}))  # fmt: skip


def _read(path: pathlib.Path, n_in: int):
    """`(executable, result structure)` kept in `path`, for `n_in` flat arguments."""
    from jax.experimental import serialize_executable

    kept = pickle.loads(path.read_bytes())  # noqa: S301 - the user's own cache folder
    if kept["lapack"]:
        _lapack_ready()
    out_tree = jax.tree.structure(pickle.loads(kept["result"]))  # noqa: S301 - likewise
    n_out = out_tree.num_leaves
    in_tree = jax.tree.structure((tuple(range(n_in)), {}))
    compiled = serialize_executable.deserialize_and_load(
        kept["payload"], in_tree, jax.tree.structure(list(range(n_out)))
    )
    if len(compiled.out_info) != n_out:
        raise ValueError(f"{path}: {len(compiled.out_info)} results, expected {n_out}")
    return compiled, out_tree
