"""`--processes N` runs that do not harm each other or the machine: a run's folder of
finished frames is its own while it runs (another run of the same work is refused,
one of other work leaves it alone), an interrupted launcher says what it kept, the
processes of a killed launcher end with it, and N is bounded by the machine."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
from helpers import children as _children

from jaxlens import cli


def _env(cache) -> dict:
    # Two CPU devices a process, and one persistent cache for the runs of the test.
    return dict(os.environ, JAXLENS_CACHE_DIR=str(cache),
                XLA_FLAGS="--xla_force_host_platform_device_count=2")  # fmt: skip


def _start(args, env):
    return subprocess.Popen([sys.executable, "-m", "jaxlens", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, ended and not yet reaped, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _until(done, what, timeout=120.0):
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def _last_line(err: str) -> str:
    return err.replace("\r", "\n").strip().splitlines()[-1]


def test_runs_to_one_output_keep_off_each_others_work_and_end_with_their_launcher(tmp_path):
    env = _env(tmp_path / "cache")
    out = tmp_path / "run" / "a.gif"
    out.parent.mkdir()
    anim = ["animate", "--size", "32x16", "--frames", "4", "--path", "orbit", "-o", str(out),
            "--processes", "2"]  # fmt: skip

    # Run X: process 1 held once it has joined, process 0 finishes its 2 frames and
    # waits for the others.
    x = _start(anim, env)
    other = same = x
    try:
        _until(lambda: list(out.parent.glob(".a.gif.frames-*")), "the stage folder")
        (stage,) = out.parent.glob(".a.gif.frames-*")
        workers = _children(x.pid)
        os.kill(workers[1], signal.SIGSTOP)
        _until(lambda: len(list(stage.glob("0*.npy"))) >= 2, "process 0's frames")

        # Meanwhile (both at once) another animation to the same file finishes and
        # leaves X's folder alone, and the same animation to it is refused at once,
        # naming X's launcher.
        other = _start([*anim, "--exposure", "1"], env)
        same = _start(anim, env)
        other_err, same_err = (run.communicate(timeout=300)[1] for run in (other, same))
        assert other.returncode == 0, other_err[-3000:]
        assert sorted(p.name for p in stage.glob("0*.npy")) == ["00000.npy", "00001.npy"]
        assert same.returncode == 2, same_err[-3000:]
        assert _last_line(same_err) == (
            f"jaxlens animate: error: another jaxlens run is writing {out} (pid {x.pid}); "
            "wait for it or choose another output")  # fmt: skip
        assert stage.is_dir()

        # SIGTERM to X: one line that says what is kept and that a rerun continues,
        # and the exit status of a terminated single-process command.
        os.kill(x.pid, signal.SIGTERM)
        err = x.communicate(timeout=60)[1]
    finally:
        for run in (x, other, same):
            run.kill()
    assert x.returncode == 128 + signal.SIGTERM, err
    assert _last_line(err) == (
        f"jaxlens animate: terminated; nothing was written to {out}; 2 of 4 frames finished "
        f"are kept in {stage}: rerun the same command to continue")  # fmt: skip
    assert not any(_alive(pid) for pid in workers.values())

    # Run W takes the folder over; SIGKILLed once it holds it (process 0 has joined and
    # the others work), its processes end within seconds.
    w = _start(anim, env)
    try:
        lock = stage / "lock"
        _until(lambda: json.loads(lock.read_text() or "{}").get("pid") == w.pid, "run W")
        workers = _children(w.pid)
        assert sorted(workers) == [0, 1]
        w.kill()
        w.wait()
        deadline = time.monotonic() + 15.0
        while any(_alive(pid) for pid in workers.values()):
            assert time.monotonic() < deadline, "the processes outlived their launcher"
            time.sleep(0.05)
    finally:
        w.kill()
        for pid in _children(w.pid).values():
            os.kill(pid, signal.SIGKILL)
    assert sorted(p.name for p in stage.glob("0*.npy"))[:2] == ["00000.npy", "00001.npy"]

    # The same command again continues from the frames kept, and leaves only its output.
    again = subprocess.run([sys.executable, "-m", "jaxlens", *anim], env=env,
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    assert again.returncode == 0, again.stderr[-3000:]
    assert "frames from an earlier run" in again.stdout, again.stdout
    assert [p.name for p in out.parent.iterdir()] == ["a.gif"]


def test_processes_are_bounded_by_the_cores_and_the_memory(tmp_path, capsys):
    cores = len(os.sched_getaffinity(0))
    n = 2 * cores + 1
    out = tmp_path / "a.png"
    code = cli.main(["render", "--size", "16x12", "-o", str(out), "--processes", str(n)])
    err = capsys.readouterr().err
    assert code == 2
    assert err == (f"jaxlens render: error: --processes {n} is more than this machine can "
                   f"run: it has {cores} CPU core{'s' if cores > 1 else ''} for this command, "
                   f"expected at most {2 * cores} (2 a core)\n")  # fmt: skip
    assert list(tmp_path.iterdir()) == []
    code = cli.main(["render", "--size", "16x12", "-o", str(out), "--processes", "0"])
    assert code == 2 and "--processes 0 is not valid: expected 1 or more" in capsys.readouterr().err


def test_processes_are_bounded_by_the_memory_this_command_can_take(tmp_path, capsys):
    import resource

    # An address-space limit that leaves this process 600 MiB: 2 processes of 400 MiB
    # do not fit (set only while the command checks its options: nothing is launched).
    with open("/proc/self/status") as f:
        mapped = next(int(s.split()[1]) for s in f if s.startswith("VmSize:")) * 1024
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = mapped + (600 << 20)
    if hard != resource.RLIM_INFINITY and hard < limit:
        pytest.skip(f"the hard address-space limit ({hard} bytes) is below {limit}")
    out = tmp_path / "a.png"
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        code = cli.main(["render", "--size", "16x12", "-o", str(out), "--processes", "2"])
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("jaxlens render: error: --processes 2: 2 processes of 400 MiB each "
                          "need about 0.8 GiB, and this process can take 0.")  # fmt: skip
    assert err.endswith(" GiB (address-space limit): run fewer processes\n"), err
    assert list(tmp_path.iterdir()) == []
