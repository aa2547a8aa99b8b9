"""A status line for the command line: from the first second of a command, what it is
doing and for how long (`jaxlens render: compiling and rendering | 3 s`), until it
prints its result or ends. Only on a terminal (not into pipes, files or tests), and
silent while a progress bar (tqdm) is on the screen.

Commands say what they do with `status("...")`; a thread redraws the line. Nothing here
touches JAX: the line runs while JAX loads and compiles.
"""

import os
import sys
import threading
import time

_FRAMES = "|/-\\"
_current = None  # the running spinner, if any


def status(text: str) -> None:
    """What the command does now (shown on the status line, if there is one; after a
    `pause`, the line comes back once this has lasted a second)."""
    if _current is not None:
        _current.resume(text)


def _columns(stream) -> int:
    """The width of the terminal `stream` writes to (80 where it does not say)."""
    try:
        return os.get_terminal_size(stream.fileno()).columns or 80
    except (AttributeError, OSError, ValueError):
        return 80


def _line(head: str, tail: str, columns: int) -> str:
    """`head` and `tail` on one line of at most `columns - 1` characters, `head` cut
    (ending in "...") where it is longer: a line that wrapped would leave a row behind
    at every redraw, as the carriage return goes back to the start of the last one."""
    room = columns - 1 - len(tail)
    if len(head) > room:
        head = head[: max(room - 3, 0)] + "..."
    return (head + tail)[: max(columns - 1, 1)]


def _bar_on_screen() -> bool:
    std = sys.modules.get("tqdm.std")
    return bool(std is not None and getattr(std.tqdm, "_instances", None))


class Spinner:
    """The status line of `command` on `stream`, shown after `delay` seconds and redrawn
    every `interval`; `stop()` clears it. A context manager."""

    def __init__(self, command: str, stream=None, delay: float = 1.0, interval: float = 0.1):
        self.command, self.text = command, "starting"
        self.stream = stream if stream is not None else sys.stderr
        self.delay, self.interval = delay, interval
        self._stop = threading.Event()
        self._lock = threading.RLock()  # stop() may run in a signal handler
        self._shown = self._paused = False
        self._since = time.monotonic()
        self._thread = None

    def __enter__(self):
        global _current
        _current = self
        try:
            tty = self.stream.isatty()
        except (AttributeError, ValueError):
            tty = False
        if tty:
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def resume(self, text: str) -> None:
        with self._lock:
            if self._paused:
                self._paused, self._since = False, time.monotonic()
            self.text = text

    def pause(self) -> None:
        """Clear the line until the next `status` (a result is printed meanwhile)."""
        with self._lock:
            self._paused = True
            if self._shown:
                self._write("\r\x1b[K")
                self._shown = False

    def _run(self):
        i = 0
        while not self._stop.wait(self.interval):
            with self._lock:
                now = time.monotonic()
                due = not self._paused and now - self._since >= self.delay
                if due and not self._stop.is_set() and not _bar_on_screen():
                    tail = f" {_FRAMES[i % 4]} {now - self._since:.0f} s"
                    line = _line(f"{self.command}: {self.text}", tail, _columns(self.stream))
                    self._write(f"\r{line}\x1b[K")
                    self._shown = True
                elif self._shown:  # a progress bar took over: leave it the line
                    self._write("\r\x1b[K")
                    self._shown = False
            i += 1

    def _write(self, text):
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # the terminal went away
            self._stop.set()

    def stop(self) -> None:
        """Stop and clear the line (before the command prints its result)."""
        global _current
        with self._lock:
            self._stop.set()
            if self._shown:
                self._write("\r\x1b[K")
                self._shown = False
        if _current is self:
            _current = None


def stop() -> None:
    """Stop the running spinner, if any (the command ends)."""
    if _current is not None:
        _current.stop()


def pause() -> None:
    """Clear the status line until the next `status` (before printing a result)."""
    if _current is not None:
        _current.pause()
