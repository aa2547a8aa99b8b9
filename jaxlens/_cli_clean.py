"""`jaxlens clean`: remove the temporary files that killed commands left behind."""

from pathlib import Path


def register(sub):
    p = sub.add_parser(
        "clean",
        help="remove temporary files left by killed jaxlens commands",
        description="Every output is written to a hidden temporary file beside it and renamed "
        "when complete; a command killed outright (SIGKILL, power loss) leaves that file. "
        "Its name (.NAME.jaxlens-tmp.HOST.PID.RANDOM.EXT) says which process wrote it: this "
        "removes those of processes of this host that no longer run. The next write to the "
        "same output removes its own as well.",
    )
    p.add_argument("folders", nargs="*", default=["."], help="folders to clean (default .)")
    p.add_argument("-n", "--dry-run", action="store_true", help="list, do not remove")
    p.set_defaults(run=_run, uses_jax=False)


def _run(args) -> int:
    from ._io import remove_temporary, stale_temporaries

    for folder in args.folders:
        if not Path(folder).is_dir():
            raise ValueError(f"{folder!r} is not a folder")
    count = 0
    for folder in args.folders:
        for path in stale_temporaries(folder):
            if not args.dry_run:
                remove_temporary(path)
            print(f"{'would remove' if args.dry_run else 'removed'} {path}")
            count += 1
    if count == 0:
        print("no stale temporary files")
    return 0
