"""Commands spread over processes joined by `jax.distributed`.

One code path for one process, several local processes and a cluster. A command run
with `--distributed` joins the job (`join`: the coordinator from `launch`'s variables,
or the cluster's own, e.g. SLURM's), takes its share of the work (`share`) and leaves
the putting together to process 0: frames and blocks through files in a folder beside
the output (`Stage`), fit results through the job's key-value store (`post`, `collect`).
`--processes N` runs the command as N local processes (`launch`) through the same
start-up a cluster's launcher gives, and stops them all when one fails.
"""

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from . import _io
from ._messages import cut

# What `launch` tells each process: the coordinator's address, the process count and
# this process's index (read by `join`).
COORDINATOR = "JAXLENS_COORDINATOR"
PROCESSES = "JAXLENS_PROCESSES"
PROCESS_ID = "JAXLENS_PROCESS_ID"
# A file process 0 makes once its command has finished its work (results written):
# a process that fails after that has cost nothing.
DONE = "JAXLENS_DONE_FILE"
# The process id of the `--processes` launcher: a process whose parent is another has
# lost its launcher, and stops.
LAUNCHER = "JAXLENS_LAUNCHER"

# Seconds a process waits for another's result or for process 0 to finish (`collect`):
# process 0 writes the results after everyone's share, and a long video takes a while to
# encode. A process that dies ends the others sooner: the coordination service notices
# its missing heartbeats within 100 s.
_WAIT = 24 * 3600

# Seconds a stopped process has to unwind (remove its temporary files) before it is
# killed.
_GRACE = 10.0

# Seconds a wait for another process (`collect`) lasts between checks that the launcher
# is still there (and between the moments a SIGTERM can stop it).
_SLICE = 1.0

# How many processes `--processes` may start. The work is CPU-bound and XLA already
# spreads one process's work over the cores: beyond the cores processes only take
# turns, and two a core leave room for the single-threaded moments (compiles, process
# 0 writing). Each costs memory: a process of a small render or animation (32 x 16)
# peaks at 325 to 432 MiB (VmHWM of the workers of `--processes 2`, JAX 0.10 on x86-64
# Linux, compiled programs loaded or compiled; 243 MiB for JAX alone), so N processes
# must find N x 400 MiB available (a render's own workspace is checked by each process
# beside it).
PER_CORE = 2
PROCESS_MEMORY = 400 << 20


def add_options(parser) -> None:
    """The `--processes` and `--distributed` options of a command that can spread."""
    parser.add_argument("--processes", type=int, metavar="N",
                        help="run as N local processes joined by jax.distributed (each takes "
                        "a share of the work; process 0 writes the results)")  # fmt: skip
    parser.add_argument("--distributed", action="store_true",
                        help="this is one process of a multi-process job (a cluster's "
                        "launcher, e.g. srun): join it through jax.distributed")  # fmt: skip


def join() -> tuple[int, int]:
    """Join the job this process belongs to (`jax.distributed.initialize`) and return
    `(index, count)`. The coordinator comes from `launch`'s variables when set, else
    from the cluster's environment (JAX detects SLURM, Open MPI and others). Collectives
    between CPU processes go through gloo. Call before anything runs on a device."""
    import jax

    _quiet_native_stdout()
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    # JAX's runtime takes SIGTERM for its preemption notices (the process then goes on
    # as if nothing happened); the command's own handler, which unwinds and removes
    # temporary files, is put back.
    on_term = signal.getsignal(signal.SIGTERM)
    if callable(on_term):
        on_term = _quiet_when_orphaned(on_term)
        signal.signal(signal.SIGTERM, on_term)
    # A process `--processes` started ends with its launcher (the kernel's signal at
    # its parent's death): killed while JAX holds SIGTERM (below), then terminated.
    _end_with_launcher(signal.SIGKILL)
    stop_if_orphaned()  # a launcher that ended while this process loaded JAX
    address = os.environ.get(COORDINATOR)
    try:
        if address:
            jax.distributed.initialize(address, num_processes=int(os.environ[PROCESSES]),
                                       process_id=int(os.environ[PROCESS_ID]))  # fmt: skip
        else:
            jax.distributed.initialize()
    except (ValueError, RuntimeError) as e:
        if address:
            raise
        msg = (f"--distributed: no multi-process job to join ({e}); start one with a "
               "cluster's launcher (srun ...) or use --processes N")  # fmt: skip
        raise ValueError(msg) from None
    if on_term is not None:
        signal.signal(signal.SIGTERM, on_term)
    _end_with_launcher(signal.SIGTERM)
    stop_if_orphaned()  # a launcher that ended before the kernel was told
    return jax.process_index(), jax.process_count()


def _end_with_launcher(sig: signal.Signals) -> None:
    """Linux: have the kernel send `sig` to this process when the launcher that started
    it ends (`prctl(PR_SET_PDEATHSIG)`; only in a process `launch` started). Elsewhere
    the waits check for it (`stop_if_orphaned`)."""
    if not os.environ.get(LAUNCHER) or not sys.platform.startswith("linux"):
        return
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, int(sig), 0, 0, 0)  # PR_SET_PDEATHSIG


def _orphaned() -> bool:
    """Whether this process was started by a `--processes` launcher that has ended (its
    parent is another now)."""
    launcher = os.environ.get(LAUNCHER)
    return bool(launcher) and os.getppid() != int(launcher)


def stop_if_orphaned() -> None:
    """SIGTERM this process (it unwinds, removing its temporary files) when the
    `--processes` launcher that started it has ended."""
    if _orphaned():
        signal.raise_signal(signal.SIGTERM)


def _quiet_when_orphaned(handler):
    """The SIGTERM handler `handler`, but in a process whose launcher has ended its
    standard error (process 0's: a pipe to the launcher, read by no one now) goes to
    /dev/null first: its last line would fail (EPIPE) and the unwinding with it, and
    the process would hang in JAX's shutdown, waiting for the others. Process 0 also
    removes the launcher's folder of logs."""

    def on_term(signum, frame):
        if _orphaned():
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 2)
            os.close(null)
            if os.environ.get(PROCESS_ID) == "0" and os.environ.get(DONE):
                import shutil

                shutil.rmtree(Path(os.environ[DONE]).parent, ignore_errors=True)
        return handler(signum, frame)

    return on_term


def _quiet_native_stdout() -> None:
    """Keep standard output for the command's results: what native code prints there
    (gloo announces its connections: "[Gloo] Rank 0 is connected to 1 peer ranks")
    goes to /dev/null, Python's `sys.stdout` to the original stream."""
    sys.stdout.flush()
    keep = os.dup(1)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.close(null)
    sys.stdout = open(keep, "w", buffering=1, encoding=sys.stdout.encoding,  # noqa: SIM115
                      errors=sys.stdout.errors)  # fmt: skip


def share(n: int, index: int, count: int) -> range:
    """The items of `n` (frames' groups, images) process `index` of `count` takes:
    every `count`-th from its index, so slow and fast items spread evenly."""
    return range(index, n, count)


def _client():
    """The job's coordination-service client (JAX keeps it once `join` has run)."""
    from jax._src import distributed

    client = distributed.global_state.client
    if client is None:
        raise RuntimeError("not a process of a multi-process job (no jax.distributed client)")
    return client


def post(key: str, text: str) -> None:
    """Leave `text` under `key` in the job's key-value store (JAX's coordination
    service): a result for process 0, which need not be waiting for it."""
    _client().key_value_set(f"jaxlens/{key}", text)


def collect(key: str) -> str:
    """The text a process `post`ed under `key`, waiting for it as long as the job runs
    (a process that dies ends the job through the service's heartbeats). Unlike a
    collective, this has no deadline for the others to arrive: gloo gives up after
    30 s, and a fit can take minutes longer on one process than on another."""
    deadline = time.monotonic() + _WAIT
    while True:  # in slices: a SIGTERM or the launcher's end stops it between them
        try:
            return _client().blocking_key_value_get(f"jaxlens/{key}", int(_SLICE * 1000))
        except RuntimeError as e:  # jax.errors.JaxRuntimeError
            if "DEADLINE_EXCEEDED" not in str(e) or time.monotonic() > deadline:
                raise
        stop_if_orphaned()


def free_port() -> int:
    """A TCP port of this host that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def worker_argv(argv: list[str], command: str) -> list[str]:
    """The command line of each process `launch` starts: `argv` without its
    `--processes N` (`--processes=N`, or an abbreviation argparse took for it), with
    `--distributed` right after the command's name (before any `--`)."""
    out, skip, place = [], False, None
    for a in argv:
        name = a.split("=", 1)[0]
        if skip:
            skip = False
        elif len(name) > 3 and "--processes".startswith(name) and "--" not in out:
            skip = "=" not in a
        else:
            out.append(a)
            if place is None and a == command:
                place = len(out)
    place = len(out) if place is None else place
    return out[:place] + ["--distributed"] + out[place:]


def check_processes(processes: int) -> None:
    """`ValueError`, naming the numbers, unless this machine can hold `processes`
    processes of a job: 1 to `PER_CORE` times the CPU cores this process may use, and
    `PROCESS_MEMORY` each within the memory it can take (`_io.available_memory`)."""
    if processes < 1:
        raise ValueError(f"--processes {processes} is not valid: expected 1 or more")
    cores = _cores()
    if processes > PER_CORE * cores:
        raise ValueError(f"--processes {processes} is more than this machine can run: it has "
                         f"{cores} CPU core{'s' if cores > 1 else ''} for this command, "
                         f"expected at most {PER_CORE * cores} ({PER_CORE} a core)")  # fmt: skip
    # Against the least of what the system, the cgroup and this process's own limits
    # leave (the processes inherit those): a bound that errs on the side of refusing.
    _io._check_memory(processes * PROCESS_MEMORY, f"--processes {processes}: {processes} "
                      f"processes of {PROCESS_MEMORY >> 20} MiB each need",
                      ": run fewer processes")  # fmt: skip


def _cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def launch(command: str, argv: list[str], processes: int, on_failure=None) -> int:
    """Run `jaxlens ARGV` (`worker_argv`) as `processes` local processes joined by
    `jax.distributed` (a free port of this host as the coordinator) and wait for them.

    Process 0 shares this process's terminal (its progress and results); the others
    write to log files. When one fails or is killed, the others are stopped (SIGTERM:
    they unwind and remove their temporary files; SIGKILL after 10 s) and one line
    says which process ended how (the signal's name), with the last line it wrote, and
    `on_failure()` (what was kept). An error that process 0 reports itself (a bad
    argument, which every process finds) is passed through as it is. An interrupt
    (Ctrl-C; SIGTERM, which the caller's handler raises as `SystemExit(128 + 15)`)
    stops them all and one line says so, with `on_failure()`. The processes end with
    this one, also when it is killed (`join`). `processes`: 1 to 2 a CPU core, within
    the memory available (`check_processes`).

    **Returns:** the exit status: 0, process 0's own, 1 for another's failure, 130 for
    an interrupt, 128 + 15 for SIGTERM.
    """
    check_processes(processes)
    port = free_port()
    logs = Path(tempfile.mkdtemp(prefix="jaxlens-processes-"))
    done = logs / "done"
    procs, files, relay = [], [], None
    stop = threading.Event()
    try:
        for i in range(processes):
            env = dict(os.environ, **{COORDINATOR: f"127.0.0.1:{port}", DONE: str(done),
                                      PROCESSES: str(processes), PROCESS_ID: str(i),
                                      LAUNCHER: str(os.getpid())})  # fmt: skip
            log = open(logs / f"{i}.log", "wb")  # noqa: SIM115 - closed below
            files.append(log)
            first = i == 0
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "jaxlens", *argv], env=env,
                stdin=subprocess.DEVNULL, stdout=None if first else log,
                stderr=subprocess.PIPE if first else log, start_new_session=True))  # fmt: skip
        relay = _Relay(procs[0].stderr, files[0], stop)
        relay.start()
        failed = _wait(procs)
        if failed is not None and failed[0] != 0 and failed[1] > 0:
            # Another process's ordinary error: process 0 usually meets the same one (a
            # bad argument) and says it on the terminal; give it a moment to.
            deadline = time.monotonic() + 2.0
            while procs[0].poll() is None and time.monotonic() < deadline:
                time.sleep(0.02)
            if (procs[0].returncode or 0) > 0:
                failed = 0, procs[0].returncode
        if failed is not None and failed[0] != 0 and done.exists():
            failed = None  # after process 0 wrote the results (in JAX's shutdown)
        if failed is None or failed[0] == 0 and failed[1] > 0:
            relay.join(timeout=5.0)  # all process 0 said, its error line included
            _stop(procs)
            return 0 if failed is None else failed[1]
        _end(procs, relay, stop)
        i, code = failed
        how = f"ended with exit status {code}"
        if code < 0:
            with contextlib.suppress(ValueError):
                how = f"was killed by {signal.Signals(-code).name}"
        last = _last_line(logs / f"{i}.log")
        msg = f"process {i} of {processes} {how}" + (f" ({last})" if last else "")
        msg += "; the other was stopped" if processes == 2 else "; the others were stopped"
        if on_failure is not None:
            msg += f"; {on_failure()}"
        print(f"{_fresh_line(relay)}{command}: error: {msg}", file=sys.stderr, flush=True)
        return 1
    except (KeyboardInterrupt, SystemExit) as e:
        if not isinstance(e, KeyboardInterrupt) and not isinstance(e.code, int):
            raise
        _end(procs, relay, stop)
        if isinstance(e, KeyboardInterrupt):
            word, code = "interrupted", 130
        else:
            word, code = "terminated", e.code
        if on_failure is not None and not done.exists():
            word += f"; {on_failure()}"
        print(f"{_fresh_line(relay)}{command}: {word}", file=sys.stderr, flush=True)
        return code
    finally:  # also on a second interrupt: no process outlives this
        stop.set()
        _stop(procs)
        if relay is not None:
            # Process 0 has ended: its pipe reaches its end once the relay has copied
            # its last words (a stopped process's) to the log, which is closed after.
            relay.join(timeout=5.0)
        for f in files:
            f.close()
        for p in logs.iterdir():
            p.unlink()
        logs.rmdir()


def _end(procs, relay, stop) -> None:
    """Stop the processes, and the relay once it has copied process 0's last words (to
    the log only): our own line then comes after everything process 0 showed."""
    stop.set()
    _stop(procs)
    if relay is not None:
        relay.join(timeout=5.0)


def finished() -> None:
    """The end of a command that ran to its end in a job (exit status 0, or 2 for a
    fit's bad image): process 0 says that the results are written (to `launch`, and to
    the job), the others wait for that before they exit. So all reach JAX's shutdown
    barrier together: a process that came to it with its share done would otherwise
    wait there for process 0, and older JAX gives up after 5 minutes."""
    import jax

    if jax.process_index() == 0:
        if os.environ.get(DONE):
            Path(os.environ[DONE]).touch()
        post("done", "1")
    else:
        collect("done")


def _wait(procs) -> tuple[int, int] | None:
    """Wait until every process has ended well (`None`) or one has failed:
    `(index, exit status)`, negative for a signal. Of processes that end together,
    process 0's own error comes first (it says it on the terminal), then one killed by
    a signal: the others' exit statuses may be their end because of it (JAX ends a
    job's processes once one of them is gone)."""
    while True:
        codes = [p.poll() for p in procs]
        if any(c not in (None, 0) for c in codes):
            time.sleep(0.1)  # those that end with it
            codes = [p.poll() for p in procs]
            failed = [(i, c) for i, c in enumerate(codes) if c not in (None, 0)]
            return min(failed, key=lambda f: (not (f[0] == 0 and f[1] > 0), f[1] >= 0))
        if all(c == 0 for c in codes):
            return None
        time.sleep(0.02)


class _Relay(threading.Thread):
    """Copies process 0's stderr (its progress bar) to ours as it comes, and to its
    log; to the log only once `stop` is set (a stopped process's last words are not
    shown). `mid_line`: what was shown does not end a line (a progress bar)."""

    def __init__(self, pipe, log, stop):
        super().__init__(daemon=True)
        self.pipe, self.log, self.stop, self.mid_line = pipe, log, stop, False

    def run(self):
        err = sys.stderr.buffer
        while data := os.read(self.pipe.fileno(), 65536):
            self.log.write(data)
            self.log.flush()
            if not self.stop.is_set():
                err.write(data)
                err.flush()
                self.mid_line = not data.endswith(b"\n")


def _fresh_line(relay) -> str:
    """What starts our own line after a relayed progress bar: a line feed, or on a
    terminal a return and an erase of the bar."""
    if relay is None or not relay.mid_line:
        return ""
    return "\r\x1b[K" if sys.stderr.isatty() else "\n"


def _stop(procs) -> None:
    """SIGTERM every running process's group, SIGKILL what is left after `_GRACE` s."""
    running = [p for p in procs if p.poll() is None]
    for p in running:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
            os.killpg(p.pid, signal.SIGCONT)  # a stopped one (Ctrl-Z, SIGSTOP) unwinds too
    deadline = time.monotonic() + _GRACE
    for p in running:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=max(deadline - time.monotonic(), 0.0))
    for p in running:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def _last_line(path: Path) -> str:
    """The last non-empty line a process wrote (progress-bar redraws split at CR)."""
    try:
        text = path.read_bytes()[-4096:].decode(errors="replace")
    except OSError:
        return ""
    lines = [s.strip() for s in text.replace("\r", "\n").splitlines() if s.strip()]
    return lines[-1] if lines else ""


class Stage:
    """The folder beside an output where the processes of a distributed command put
    their shares (`NNNNN.npy`: one frame or block each, saved atomically by its owner),
    so that a rerun of a failed command finds what it finished.

    The folder is named for everything the items depend on (`key`): `settings` (the
    scene and the work's own values, JSON-able), the content of every input file they
    name (`input_files`), the versions of jaxlens and JAX and JAX's float64 mode. A rerun
    after any of them changed starts afresh. Process 0 holds the folder for its run
    (an exclusive `flock` on its `lock` file, which also records the run's launcher and
    the item count) and tells the others its name; a second run of the same work to
    the same output is refused (`ValueError`) and a folder is removed only by the run
    that holds it. `what`: the items' name ("frames", "blocks")."""

    def __init__(self, out: Path, what: str, settings):
        import json

        import jax

        self.out, self.what, self._lock = Path(out), what, None
        if jax.process_index() == 0:
            name = f".{self.out.name}.{what}-{key(settings)}"
            try:  # (an error is the others' too: they wait for the folder's name)
                self._lock = _hold(self.out.parent / name, wait=2.0)
                error = "" if self._lock is not None else _busy(self.out, self.out.parent / name)
                if self._lock is not None:
                    self._note()
            except OSError as e:
                error = f"the folder of finished {what} beside the output: {e}"
            if jax.process_count() > 1:
                post("stage", json.dumps([name, error]))
        else:  # the folder process 0 holds (or its refusal)
            name, error = json.loads(collect("stage"))
        if error:
            raise ValueError(error)
        self.folder = self.out.parent / name

    def _note(self, total: int | None = None) -> None:
        """Write the run's launcher (this process, where none) and the item count to
        the lock file."""
        import json

        pid = int(os.environ.get(LAUNCHER) or os.getpid())
        os.ftruncate(self._lock, 0)
        os.pwrite(self._lock, json.dumps({"pid": pid, "total": total}).encode(), 0)

    def path(self, i: int) -> Path:
        return self.folder / f"{i:05d}.npy"

    def has(self, i: int) -> bool:
        return self.path(i).exists()

    def save(self, i: int, array) -> None:
        with _io.atomic_output(self.path(i)) as tmp:
            np.save(tmp, np.asarray(array))

    def finished(self) -> int:
        """How many items are there (temporaries, hidden, not counted)."""
        return _items(self.folder)

    def fill(self, groups, make, index: int, count: int, bar) -> None:
        """Process `index` of `count`'s `share` of `groups` (each a range of item
        numbers): the arrays `make(g)` returns for group `g`, one an item, each saved by
        its owner; a group an earlier run finished is skipped. `bar` counts every
        process's items."""
        if self._lock is not None:
            self._note(sum(len(items) for items in groups))
        for g in share(len(groups), index, count):
            items = groups[g]
            if all(self.has(i) for i in items):
                continue
            for i, array in zip(items, make(g), strict=True):
                self.save(i, array)
            bar.update(self.finished() - bar.n)

    def wait(self, total: int, bar) -> None:
        """Until all `total` items are there, the progress bar counting them."""
        while (n := self.finished()) < total:
            bar.update(n - bar.n)
            stop_if_orphaned()
            time.sleep(0.1)
        bar.update(total - bar.n)

    def load(self, i: int):
        return np.load(self.path(i))

    def remove(self) -> None:
        """This folder (process 0, which holds it), and any that older commands for the
        same output left and no run holds now."""
        for folder in _folders(self.out, self.what):
            if folder == self.folder:
                lock, self._lock = self._lock, None
            else:
                lock = _hold(folder, create=False)
            if lock is not None:
                _remove_held(folder, lock)


# The file in a stage folder whose `flock` the run that uses the folder holds.
LOCK = "lock"


def key(settings) -> str:
    """The name of a stage folder's work: a hash of `settings` (JSON-able), of the
    content of the input files they name (`input_files`), of the jaxlens and JAX
    versions and of JAX's float64 mode."""
    import hashlib
    import json

    import jax

    from . import __version__

    parts = {"settings": settings, "inputs": input_files(settings), "jaxlens": __version__,
             "jax": jax.__version__, "x64": bool(jax.config.jax_enable_x64)}  # fmt: skip
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def input_files(settings) -> list[list[str]]:
    """`[path, SHA-256 of its content]` of every file `settings` name: each string in
    them (nested dicts and lists walked) that names an existing regular file, taken
    relative to the `_base` folder of the table that holds it (a scene file's folder)
    or the current folder. Content, not size and time: a copy that keeps the time
    (`cp -p`, `rsync -t`, an archive) or a rewrite within the file system's time step
    would pass for the same file; hashing costs about 2 ms a MB, once a run."""
    import hashlib

    found = []

    def walk(value, base):
        if isinstance(value, dict):
            base = value.get("_base", base)
            for k, v in value.items():
                if k != "_base":
                    walk(v, base)
        elif isinstance(value, list | tuple):
            for v in value:
                walk(v, base)
        elif isinstance(value, str) and value:
            path = Path(base) / value
            try:
                if not path.is_file():
                    return
                with open(path, "rb") as f:
                    digest = hashlib.file_digest(f, "sha256").hexdigest()
            except (OSError, ValueError):  # not a file name (too long, a NUL), unreadable
                return
            found.append([str(path), digest])

    walk(settings, ".")
    return found


def _hold(folder: Path, *, wait: float = 0.0, create: bool = True) -> int | None:
    """Hold `folder` for this process: an exclusive `flock` on its lock file (the
    folder and the file made where `create`). **Returns:** the descriptor that holds
    it, or `None` when another process holds it (still after `wait` seconds) or, not
    `create`, the folder is gone."""
    import fcntl

    deadline = time.monotonic() + wait
    while True:
        if create:
            folder.mkdir(exist_ok=True)
        try:
            fd = os.open(folder / LOCK, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except FileNotFoundError:  # removed meanwhile by the run that held it
            if not create:
                return None
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.05)
            continue
        try:  # still the folder's own: not one a removal unlinked before we locked it
            st, held = os.stat(folder / LOCK), os.fstat(fd)
            if (st.st_dev, st.st_ino) == (held.st_dev, held.st_ino):
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)
        if not create:
            return None


def _remove_held(folder: Path, lock: int) -> None:
    """Remove a stage folder this process holds (`lock`), then let it go."""
    try:
        _io.remove_temporary(folder)
    finally:
        os.close(lock)


def _info(folder: Path) -> dict:
    """What the lock file of a stage folder says: `pid` (the run's launcher), `total`."""
    import json

    try:
        info = json.loads((folder / LOCK).read_text())
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _busy(out: Path, folder: Path) -> str:
    """The refusal of a run whose stage folder another run holds."""
    pid = _info(folder).get("pid")
    who = f" (pid {pid})" if isinstance(pid, int) else ""
    return (f"another jaxlens run is writing {cut(out)}{who}; wait for it or choose another "
            "output")  # fmt: skip


def _items(folder: Path) -> int:
    """The finished items in a stage folder."""
    return sum(1 for _ in folder.glob("[0-9]*.npy"))


def _folders(out: Path, what: str) -> list[Path]:
    from glob import escape

    return sorted(out.parent.glob(f".{escape(out.name)}.{what}-*"))


def kept(out, what: str) -> str:
    """What a failed or interrupted distributed command left for the next, said by its
    launcher (after its processes ended): the finished items in the stage folder its
    run held (its lock file names this process). Folders with no item that no run
    holds are removed."""
    out = Path(out)
    mine = None
    for folder in _folders(out, what):
        n = _items(folder)
        if n == 0:
            lock = _hold(folder, create=False)
            if lock is not None:
                _remove_held(folder, lock)
        elif _info(folder).get("pid") == os.getpid():
            mine, total = (folder, n), _info(folder).get("total")
    if mine is None:
        return f"nothing was written to {cut(out)}"
    folder, n = mine
    of = f" of {total}" if isinstance(total, int) else ""
    return (f"nothing was written to {cut(out)}; {n}{of} {what} finished are kept in "
            f"{cut(folder)}: rerun the same command to continue")  # fmt: skip
