"""Several processes for real: `jax.distributed` on localhost, two processes with two
CPU devices each (collectives through gloo), against one process with one device.
A ray batch split over the four devices, in chunks that end in padding, must come back
bit for bit the same, on every process."""

import os
import subprocess
import sys
import textwrap

import numpy as np

WORKER = textwrap.dedent(
    """
    import sys
    import numpy as np
    import jax

    pid, nproc, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    jax.config.update("jax_enable_x64", True)
    if nproc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=nproc, process_id=pid,
                                   initialization_timeout=120)
    import jaxlens as jl

    alpha = np.linspace(0.0, np.pi, 100_003)  # crosses the critical angle; odd count
    r = jl.trace_sharded(alpha, 20.0, chunk=40_000, method="exact", progress=False)
    np.savez(out, phi=r.phi, status=r.status, r_min=r.r_min,
             devices=jax.device_count(), processes=jax.process_count())
    """
)


def _env(devices: int) -> dict:
    return dict(os.environ, JAXLENS_CACHE_DIR="",
                XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")  # fmt: skip


def test_a_ray_batch_over_two_processes_is_bitwise_one_process(tmp_path, free_port):
    port = str(free_port)
    procs = [
        subprocess.Popen([sys.executable, "-c", WORKER, str(i), "2", port, str(tmp_path / f"p{i}")],
                         env=_env(2), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for i in range(2)
    ]  # fmt: skip
    try:
        logs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, log in zip(procs, logs, strict=True):
        assert p.returncode == 0, log[-3000:]
    one = subprocess.run([sys.executable, "-c", WORKER, "0", "1", "0", str(tmp_path / "one")],
                         env=_env(1), capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr[-3000:]

    ref = np.load(tmp_path / "one.npz")
    assert (int(ref["devices"]), int(ref["processes"])) == (1, 1)
    for i in range(2):
        got = np.load(tmp_path / f"p{i}.npz")
        assert (int(got["devices"]), int(got["processes"])) == (4, 2)
        for key in ("phi", "status", "r_min"):
            np.testing.assert_array_equal(got[key], ref[key], err_msg=f"process {i}: {key}")
    assert np.unique(ref["status"]).size == 2  # escaped and captured rays both present
