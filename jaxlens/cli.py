"""The `jaxlens` command. Parses, validates, and calls the public functions.

Errors in the input (bad values, unreadable files, unwritable outputs) end the
command with one line on stderr and exit code 2; no traceback, and no partial output
file (every file is written atomically). The line names the option (or scene key), the
value and what is valid; a long value is cut to its start and its length, and the line
to at most `LINE_MAX` (1000) characters.
"""

import argparse
import contextlib
import functools
import gc
import importlib
import os
import re
import signal
import sys
import threading
from pathlib import Path

from . import _io, _spinner

# Each subcommand lives in a module with `register(subparsers)`; the handler it sets
# with `set_defaults(run=...)` returns the exit code.
_COMMANDS = ("jaxlens._cli_render", "jaxlens._cli_animate", "jaxlens._cli_clean")
_OPTIONAL = ("jaxlens._cli_fit",)


_NEGATIVE_NUMBER = re.compile(r"^-(\d|\.\d|inf|nan)", re.IGNORECASE)


class UsageError(Exception):
    """Bad input from the command line: one line on stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (the usage text stays in --help), and an
    argument that looks like a negative number (`-inf`, `-1e300`, `-5x10`) is a value,
    not an option: `--distance -inf` is then refused by the check that names it, rather
    than by argparse's "expected one argument"."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse's own pattern matches `-5` and `-.5` only; no option of jaxlens
        # starts with a digit, a point, "inf" or "nan", so these are never options.
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see --help)\n")


# The longest error line printed, and the longest word in it: a value echoed whole (a
# path of megabytes, a list of a million numbers) is cut to its start and its length.
LINE_MAX = 1000
WORD_MAX = 200


def one_line(text: str) -> str:
    """A message on one line: whitespace runs (newlines too) become one space, a word
    longer than `WORD_MAX` characters is cut to its start and its length, and a line
    longer than `LINE_MAX` to its start and its end."""
    words = (w if len(w) <= WORD_MAX else f"{w[:WORD_MAX]}... ({len(w)} characters)"
             for w in str(text).split())  # fmt: skip
    line = " ".join(words)
    if len(line) > LINE_MAX:
        line = f"{line[: LINE_MAX - 300]} ... ({len(line)} characters) ... {line[-250:]}"
    return line


def status(text: str) -> None:
    """What the command does now, on its status line (a terminal only)."""
    _spinner.status(text)


def stop_status() -> None:
    """Clear the status line before printing a result (the next `status` brings it
    back)."""
    _spinner.pause()


def output_file(path) -> Path:
    """Check an output file's name as `_io.check_output_path` does, except that a missing
    folder is not an error: `make_output_folder` creates it once every argument is
    checked, so a refused command creates no folder.

    **Arguments:** `path`: the output file (str or Path).

    **Returns:** `path` as a `Path`. Raises `ValueError` naming it (an unsupported
    extension, a folder given as the file, an unwritable folder).
    """
    path = Path(path)
    if path.suffix.lower() not in _io.WRITE_FORMATS | _io.ANIMATION_FORMATS:
        return _io.check_output_path(path)  # raises: names the extension and the valid ones
    if not _missing(path.parent):
        return _io.check_output_path(path)
    return path


def make_output_folder(path, *, folder=None) -> Path:
    """Create the folder of an output file and its parents, as image tools do (`-o
    out/ring.png` makes `out/`); a folder that exists is left as it is, and nothing in
    it is touched. Call it once every argument is checked.

    **Arguments:** `path`: the output file (str or Path); `folder`: the folder to
    create, if not `path`'s (the parent of a frames folder, say).

    **Returns:** `path` as a `Path`, checked by `_io.check_output_path` (writable) when
    `folder` is not given. Raises `ValueError` naming the folder when it cannot be
    created (a file in its place, no permission).
    """
    path = Path(path)
    where = path.parent if folder is None else Path(folder)
    if _missing(where):
        try:
            where.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValueError(f"output folder {str(where)!r} of {str(path)!r} cannot be created: "
                             f"{e.strerror or e}") from None  # fmt: skip
    return _io.check_output_path(path) if folder is None else path


def _missing(folder: Path) -> bool:
    """Whether nothing (no folder, no file, no link) is at `folder`."""
    return not folder.exists() and not folder.is_symlink()


def enable_x64():
    """Turn on float64 in JAX (the ray map is built in it; pixels stay float32
    unless asked). Call before any JAX array is made."""
    import jax

    jax.config.update("jax_enable_x64", True)


class _Version(argparse.Action):
    """`--version`, looked up only when asked (the package metadata is slow to load)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest=argparse.SUPPRESS, nargs=0, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from . import __version__

        print(f"jaxlens {__version__}")
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxlens", description="Gravitational lensing by a Schwarzschild black hole."
    )
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMANDS:
        importlib.import_module(name).register(sub)
    for name in _OPTIONAL:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name != name:
                raise
            continue
        mod.register(sub)
    return parser


class _Terminated(SystemExit):
    """SIGTERM, raised where the program is: it unwinds (temporary files are removed)."""


def _terminate(signum, frame):
    raise _Terminated(128 + signum)


def _redeliver(unraisable, hook=sys.unraisablehook):
    """`sys.unraisablehook`: an interrupt raised where Python ignores exceptions (a
    garbage-collector callback, as JAX installs) is sent again, so that Ctrl-C or
    SIGTERM stops the command instead of being lost; other reports go to `hook`."""
    exc = unraisable.exc_value
    if isinstance(exc, KeyboardInterrupt | _Terminated):
        sig = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        timer = threading.Timer(0.05, os.kill, (os.getpid(), sig))
        timer.daemon = True
        timer.start()
        return
    hook(unraisable)


def _exit_at_once(signum, frame, command="jaxlens"):
    """Handler while JAX loads: its native modules run Python code (enum classes, for
    one) where an exception cannot pass (the process aborts), so nothing is raised:
    the one line is printed and the process ends. Nothing is written yet."""
    word = "interrupted" if signum == signal.SIGINT else "terminated"
    _spinner.stop()
    print(f"{command}: {word}", file=sys.stderr, flush=True)
    os._exit(128 + signum)


@contextlib.contextmanager
def _signals_end_at_once(at_once):
    """Signals end the command at once (`_exit_at_once`) inside: for loading a native
    module (`_io.native_import`)."""
    previous = _set_handlers({signal.SIGINT: at_once, signal.SIGTERM: at_once})
    try:
        yield
    finally:
        _set_handlers(previous)


def _set_handlers(handlers: dict) -> dict:
    """Install signal handlers (where this is the main thread); return the old ones.
    A signal that is ignored (`nohup`, a background job) stays ignored."""
    old = {}
    for sig, handler in handlers.items():
        try:
            current = signal.getsignal(sig)
            if current is not signal.SIG_IGN:
                signal.signal(sig, handler)
                old[sig] = current
        except ValueError:  # not the main thread
            break
    return old


def _failed(args, code: int) -> int:
    """The exit status of a failed command; a process of a multi-process job ends at
    once (`os._exit`), instead of waiting in JAX's shutdown for the others to finish."""
    if getattr(args, "distributed", False):
        _exit_flushed(code)
    return code


def main(argv=None) -> int:
    # The handlers hold from the start: a signal while JAX loads (the first seconds)
    # ends the command with its one line too, not a traceback or an abort.
    command = "jaxlens"
    at_once = functools.partial(_exit_at_once, command=command)
    previous = _set_handlers({signal.SIGINT: at_once, signal.SIGTERM: at_once})
    hook, sys.unraisablehook = (
        sys.unraisablehook,
        functools.partial(_redeliver, hook=sys.unraisablehook),
    )
    spinner = args = None
    frozen = False
    native, _io.native_import = _io.native_import, functools.partial(_signals_end_at_once,
                                                                      at_once)  # fmt: skip
    try:
        argv = sys.argv[1:] if argv is None else list(argv)
        args = build_parser().parse_args(argv)
        command = f"jaxlens {args.command}"
        at_once.keywords["command"] = command
        if getattr(args, "processes", None) is not None:
            if args.distributed:
                raise UsageError("--processes and --distributed exclude each other: "
                                 "--processes starts the processes itself")  # fmt: skip
            if args.processes != 1:
                from . import _multi

                # Interrupts unwind from here: the processes started are stopped.
                _set_handlers({signal.SIGINT: signal.default_int_handler,
                               signal.SIGTERM: _terminate})  # fmt: skip

                kept = getattr(args, "kept", None)  # what a failed run leaves for a rerun
                return _multi.launch(command, _multi.worker_argv(argv, args.command),
                                     args.processes, kept and (lambda: kept(args)))  # fmt: skip
        spinner = _spinner.Spinner(command).__enter__()  # on a terminal: a status line
        if getattr(args, "uses_jax", True):
            _spinner.status("loading JAX")
            import jax  # (under the handler above)

            if not getattr(args, "distributed", False):  # a job's process joins it first
                # JAX's backends start under it too: a signal raised in their set-up
                # left JAX's TPU-plugin timer running, and its warning followed the
                # command's last line.
                jax.devices()
            # Compiled programs kept between runs (`keep_programs`: the folder is
            # $JAXLENS_CACHE_DIR, else $JAX_COMPILATION_CACHE_DIR, else
            # ~/.cache/jaxlens/xla; empty: none kept): later runs start at once.
            from ._compile import keep_programs

            keep_programs()
            # The objects alive now (JAX's modules, most of them) are left out of the
            # garbage collector's passes while the command runs (each full pass would
            # walk them all). Given back at the end.
            if gc.get_freeze_count() == 0:
                gc.freeze()
                frozen = True
        # From here an interrupt unwinds (temporary files are removed on the way).
        sigint = previous.get(signal.SIGINT)
        _set_handlers({
            signal.SIGINT: sigint if callable(sigint) else signal.default_int_handler,
            signal.SIGTERM: _terminate,
        })  # fmt: skip
        _spinner.status("working")
        code = int(args.run(args) or 0)
        if getattr(args, "distributed", False):  # its results written (or said): 0, 2
            from . import _multi

            _multi.finished()
        return code
    except (UsageError, ValueError, OSError) as e:
        _spinner.stop()
        print(f"{command}: error: {one_line(e)}", file=sys.stderr)
        return _failed(args, 2)
    except KeyboardInterrupt:
        _spinner.stop()
        print(f"{command}: interrupted", file=sys.stderr)
        return _failed(args, 130)
    except _Terminated as e:
        _spinner.stop()
        print(f"{command}: terminated", file=sys.stderr)
        return _failed(args, int(e.code))
    finally:
        if spinner is not None:
            spinner.stop()
        sys.unraisablehook = hook
        _set_handlers(previous)
        _io.native_import = native
        if frozen:
            gc.unfreeze()


def finish(code: int) -> None:
    """End the process with exit status `code` once its work is done, the quick way: the
    exit handlers run (JAX's backends and `jax.distributed` shut down, logs flushed),
    the output streams are flushed, and the interpreter then exits without freeing its
    modules one by one."""
    import atexit

    atexit._run_exitfuncs()
    _exit_flushed(code)


def _exit_flushed(code: int) -> None:
    """`os._exit(code)` once stdout and stderr are flushed."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe or stream: nothing more to say
            pass
    os._exit(code)


def console() -> None:
    """The `jaxlens` command (its console script, and `python -m jaxlens`)."""
    finish(main())


if __name__ == "__main__":
    console()
