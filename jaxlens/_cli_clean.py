"""`jaxlens clean`: remove the temporary files that killed commands left behind."""

import sys
from pathlib import Path

from ._io import remove_temporary, stale_temporaries


def register(sub):
    p = sub.add_parser(
        "clean",
        help="remove temporary files left by killed jaxlens commands",
        description="Every output is written to a hidden temporary file beside it and renamed "
        "when complete; a command killed outright (SIGKILL, power loss) leaves that file. "
        "Its name is .NAME.jaxlens-tmp.HOST.PID.RANDOM.EXT, and a command holds a lock on it "
        "while it writes: this removes those named for this host whose lock no process "
        "holds (whatever the PID: a command in a container has ids of its own). The next "
        "write to the same output removes its own as well. A file that cannot be removed "
        "(a read-only folder) is named with the reason, and the exit status is then 2.",
    )
    p.add_argument("folders", nargs="*", default=["."], help="folders to clean (default .)")
    p.add_argument("-n", "--dry-run", action="store_true", help="list, do not remove")
    p.set_defaults(run=_run, uses_jax=False)


def _run(args) -> int:
    for folder in args.folders:
        if not Path(folder).is_dir():
            raise ValueError(f"{folder!r} is not a folder")
    count = failed = 0
    for folder in args.folders:
        for path in stale_temporaries(folder):
            count += 1
            if args.dry_run:
                print(f"would remove {path}")
                continue
            try:
                remove_temporary(path, quiet=False)
            except OSError as e:
                print(f"jaxlens clean: could not remove {path}: {e.strerror or e}",
                      file=sys.stderr)  # fmt: skip
                failed += 1
            else:
                print(f"removed {path}")
    if count == 0:
        print("no stale temporary files")
    return 2 if failed else 0
