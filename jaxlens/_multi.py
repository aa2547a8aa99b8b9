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

# What `launch` tells each process: the coordinator's address, the process count and
# this process's index (read by `join`).
COORDINATOR = "JAXLENS_COORDINATOR"
PROCESSES = "JAXLENS_PROCESSES"
PROCESS_ID = "JAXLENS_PROCESS_ID"
# A file process 0 makes once its command has finished its work (results written):
# a process that fails after that has cost nothing.
DONE = "JAXLENS_DONE_FILE"

# Seconds a process waits for another's result or for process 0 to finish (`collect`):
# process 0 writes the results after everyone's share, and a long video takes a while to
# encode. A process that dies ends the others sooner: the coordination service notices
# its missing heartbeats within 100 s.
_WAIT = 24 * 3600

# Seconds a stopped process has to unwind (remove its temporary files) before it is
# killed.
_GRACE = 10.0


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
    address = os.environ.get(COORDINATOR)
    # JAX's runtime takes SIGTERM for its preemption notices (the process then goes on
    # as if nothing happened); the command's own handler, which unwinds and removes
    # temporary files, is put back.
    on_term = signal.getsignal(signal.SIGTERM)
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
    return jax.process_index(), jax.process_count()


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
    return _client().blocking_key_value_get(f"jaxlens/{key}", _WAIT * 1000)


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


def launch(command: str, argv: list[str], processes: int, on_failure=None) -> int:
    """Run `jaxlens ARGV` (`worker_argv`) as `processes` local processes joined by
    `jax.distributed` (a free port of this host as the coordinator) and wait for them.

    Process 0 shares this process's terminal (its progress and results); the others
    write to log files. When one fails or is killed, the others are stopped (SIGTERM:
    they unwind and remove their temporary files; SIGKILL after 10 s) and one line
    says which process ended how, with the last line it wrote, and `on_failure()` (what
    was kept). An error that process 0 reports itself (a bad argument, which every
    process finds) is passed through as it is. An interrupt (Ctrl-C, SIGTERM) stops them
    all and propagates.

    **Returns:** the exit status: 0, process 0's own, or 1 for another's failure.
    """
    if not 1 <= processes <= 256:
        raise ValueError(f"--processes {processes} is not valid: expected 1 to 256")
    port = free_port()
    logs = Path(tempfile.mkdtemp(prefix="jaxlens-processes-"))
    done = logs / "done"
    procs, files, relay = [], [], None
    stop = threading.Event()
    try:
        for i in range(processes):
            env = dict(os.environ, **{COORDINATOR: f"127.0.0.1:{port}", DONE: str(done),
                                      PROCESSES: str(processes), PROCESS_ID: str(i)})  # fmt: skip
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
        stop.set()
        _stop(procs)
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
    finally:  # also on Ctrl-C or SIGTERM (the caller says so): no process outlives this
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
    `(index, exit status)`, negative for a signal."""
    while True:
        codes = [p.poll() for p in procs]
        for i, c in enumerate(codes):
            if c not in (None, 0):
                return i, c
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
    named for the work's settings (`key`) so that a rerun of a failed command finds
    what it finished. `what`: the items' name ("frames", "blocks")."""

    def __init__(self, out: Path, what: str, settings: str):
        import hashlib

        key = hashlib.sha256(settings.encode()).hexdigest()[:16]
        self.out, self.what = Path(out), what
        self.folder = self.out.parent / f".{self.out.name}.{what}-{key}"
        self.folder.mkdir(exist_ok=True)

    def path(self, i: int) -> Path:
        return self.folder / f"{i:05d}.npy"

    def has(self, i: int) -> bool:
        return self.path(i).exists()

    def save(self, i: int, array) -> None:
        import numpy as np

        from . import _io

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
            time.sleep(0.1)
        bar.update(total - bar.n)

    def load(self, i: int):
        import numpy as np

        return np.load(self.path(i))

    def remove(self) -> None:
        """This folder, and any an older command for the same output left."""
        from . import _io

        for folder in _folders(self.out, self.what):
            _io.remove_temporary(folder)


def _items(folder: Path) -> int:
    """The finished items in a stage folder."""
    return sum(1 for _ in folder.glob("[0-9]*.npy"))


def _folders(out: Path, what: str) -> list[Path]:
    from glob import escape

    return sorted(out.parent.glob(f".{escape(out.name)}.{what}-*"))


def kept(out, what: str) -> str:
    """What a failed distributed command left for the next: the finished items in the
    stage folders of `out` (empty folders are removed)."""
    out = Path(out)
    folders = _folders(out, what)
    n = sum(_items(f) for f in folders)
    if n == 0:
        from . import _io

        for folder in folders:
            _io.remove_temporary(folder)
        return f"nothing was written to {out}"
    return (f"nothing was written to {out}; {n} finished {what} are kept in {folders[-1]} "
            "and the same command continues from them")  # fmt: skip
