"""What a fit is doing while it runs: one line a stage (`fit: solving, pass 1: 4 steps,
chi2 6208 | 17.8 s`), to stderr in Python, on the status line of `jaxlens fit`.

The stages and their steps come from the host: the start's candidates are evaluated
one call each, and each solver pass is one compiled program whose steps and chi^2 are
known when it returns. A per-step line from inside the solver would need a host
callback in the compiled solve, which keeps that program out of the programs kept
between processes (`keep_programs`, the command line's cache); a warm solve of a ring
takes a second or two for all its steps, and the time a first fit takes is compiling,
which the lines name.
"""

import sys
import time
from collections.abc import Callable


def _default_on() -> bool:
    """Progress by default: where someone watches, stderr a terminal or a notebook
    (a Jupyter kernel), not in a test run, a pipe or a batch job's log."""
    try:
        if sys.stderr.isatty():
            return True
    except (AttributeError, ValueError):
        pass
    ipython = sys.modules.get("IPython")
    shell = ipython.get_ipython() if ipython is not None else None
    return type(shell).__name__ == "ZMQInteractiveShell"


class Progress:
    """A fit's progress: each stage's text given to `progress` where it is a callable,
    else as a line on stderr (`label`, the text, the seconds since the fit began); nothing
    where off (`progress` False, or None where no one watches: `_default_on`)."""

    def __init__(self, progress: "bool | None | Callable[[str], object]" = None, *,
                 label: str = "fit"):  # fmt: skip
        if callable(progress) and not isinstance(progress, bool):
            self.sink, self.on = progress, True
        elif progress is None or isinstance(progress, bool):
            self.sink, self.on = None, _default_on() if progress is None else progress
        else:
            raise TypeError(
                f"progress={progress!r} is not valid: expected True, False, None (on where "
                "stderr is a terminal or in a notebook) or a callable taking each line"
            )
        self.label, self.prefix = label, ""
        self.t0 = time.perf_counter()

    def __call__(self, text: str) -> None:
        """Report a stage."""
        if not self.on:
            return
        if self.sink is not None:
            self.sink(f"{self.prefix}{text}")
            return
        line = f"{self.label}: {self.prefix}{text} | {time.perf_counter() - self.t0:.1f} s"
        try:
            print(line, file=sys.stderr, flush=True)
        except (OSError, ValueError):  # stderr closed
            self.on = False


def progress_of(progress) -> Progress:
    """`progress` as a `Progress` (one given is used as it is)."""
    return progress if isinstance(progress, Progress) else Progress(progress)
