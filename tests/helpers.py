"""Helpers that several test files share: the command run in-process, and the
processes a `--processes` launcher started."""

import os

from jaxlens import cli


def run(args, capsys):
    """`jaxlens ARGS` in this process: `(exit status, stdout, stderr)`."""
    code = cli.main(args)
    out = capsys.readouterr()
    return code, out.out, out.err


def children(pid: int) -> dict[int, int]:
    """`{process index: pid}` of the processes `jaxlens ... --processes N` started."""
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid != pid:
                continue
            with open(f"/proc/{entry}/environ", "rb") as f:
                env = dict(v.split(b"=", 1) for v in f.read().split(b"\0") if b"=" in v)
        except (OSError, ValueError, IndexError):
            continue
        if b"JAXLENS_PROCESS_ID" in env:
            out[int(env[b"JAXLENS_PROCESS_ID"])] = int(entry)
    return out
