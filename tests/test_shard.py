"""Sharded and chunked tracing give the same numbers as one unsharded call.

The four-device case runs in a subprocess, because
`XLA_FLAGS=--xla_force_host_platform_device_count=4` only takes effect before JAX
starts. Tolerance: none. A ray's result depends on that ray alone and every device
runs the same compiled elementwise program, so the results must agree bit for bit
with `jax.jit(trace)` on the same flat batch on one device. (The reference is a flat
1-D batch and receives the distance as an argument, as the sharded call does: XLA
may round differently, by an ulp, when a constant is folded at compile time or when
the same rays come as a 2-D array.)
"""

import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlens
from jaxlens import ray_mesh, shard_map_rays, trace_sharded

ROOT = pathlib.Path(__file__).resolve().parents[1]

# The child: four CPU devices, float64; saves every result next to its reference.
_CHILD = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxlens
    from jaxlens import ray_mesh, shard_map_rays, trace_sharded

    out = sys.argv[1]
    rng = np.random.default_rng(5)
    d = 20.0
    crit = float(jaxlens.shadow_angle(d))
    alpha = np.concatenate([
        rng.uniform(0.001, 0.5, 600),                                  # moderate, escaping
        crit * (1.0 + rng.choice([-1, 1], 200) * 10 ** rng.uniform(-9, -2, 200)),
        rng.uniform(0.0, np.pi, 203),                                  # captured, outward
    ])                                                                 # 1003: not 4k
    dist = rng.uniform(1.2, 1e4, alpha.size)
    res = {}
    full = jax.jit(jaxlens.trace, static_argnames=("accuracy", "method"))
    cases = [
        ("exact", alpha, d, {"accuracy": 1e-9}, [None, 250]),
        ("exact_dist", alpha, dist, {"accuracy": 1e-9}, [64]),
        ("rk4", alpha[::5], d, {"accuracy": 1e-4, "method": "rk4"}, [None, 48]),
    ]
    for name, a, dd, kw, chunks in cases:
        ref = full(a, dd, **kw)
        for f in ("phi", "status", "r_min"):
            res[f"{name}/ref/{f}"] = np.asarray(getattr(ref, f))
        for c in chunks:
            got = trace_sharded(a, dd, chunk=c, progress=False, **kw)
            for f in ("phi", "status", "r_min"):
                res[f"{name}/{c}/{f}"] = np.asarray(getattr(got, f))

    # Which device computed which ray: blocks of ceil(n / 4) rays, in order.
    def where(a):
        return jnp.full(a.shape, jax.lax.axis_index("rays"), jnp.int32)

    res["device_of_ray"] = shard_map_rays(where, alpha)
    res["device_of_ray_chunked"] = shard_map_rays(where, alpha, chunk=100, progress=False)

    # One compilation for all chunks, the padded last one included; trailing axes kept.
    traces = []

    def pair(a, k):
        traces.append(a.shape)
        return jnp.stack([jnp.sin(a) * k, jnp.cos(a)], axis=-1)

    res["pair"] = shard_map_rays(pair, alpha.reshape(17, 59), 3.0, chunk=96)
    n_traces = list(traces)
    res["pair_ref"] = np.asarray(jax.jit(pair)(alpha, 3.0)).reshape(17, 59, 2)
    np.savez(out, **res)
    info = {"devices": jax.device_count(), "mesh": int(ray_mesh().devices.size),
            "traces": [list(s) for s in n_traces]}
    print(json.dumps(info))
    """
)


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory):
    """Results of the child run on four forced host devices."""
    out = tmp_path_factory.mktemp("shard") / "res.npz"
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    ).strip()
    env["JAX_PLATFORMS"] = "cpu"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    info = json.loads(proc.stdout.strip().splitlines()[-1])
    return info, dict(np.load(out))


def test_child_sees_four_devices(four_devices):
    info, _ = four_devices
    assert info["devices"] == 4
    assert info["mesh"] == 4


@pytest.mark.parametrize(
    "name, chunks",
    [
        ("exact", [None, 250]),
        ("exact_dist", [64]),
        ("rk4", [None, 48]),
    ],
)
def test_sharded_equals_unsharded_bitwise(four_devices, name, chunks):
    # 1003 rays (201 for RK4): padding to a multiple of 4 devices, and chunks that are
    # not a multiple of 4 (250 -> 252) or do not divide the batch (64, 48).
    _, res = four_devices
    for c in chunks:
        for f in ("phi", "status", "r_min"):
            ref, got = res[f"{name}/ref/{f}"], res[f"{name}/{c}/{f}"]
            assert got.dtype == ref.dtype and got.shape == ref.shape, (name, c, f)
            np.testing.assert_array_equal(got, ref, err_msg=f"{name}, chunk={c}, {f}")


def test_rays_are_split_in_blocks_over_devices(four_devices):
    _, res = four_devices
    # One call: 1003 rays padded to 1004, 251 per device.
    expected = np.repeat(np.arange(4), 251)[:1003]
    np.testing.assert_array_equal(res["device_of_ray"], expected)
    # Chunks of 100 rays: 25 per device within each chunk.
    expected = np.tile(np.repeat(np.arange(4), 25), 11)[:1003]
    np.testing.assert_array_equal(res["device_of_ray_chunked"], expected)


def test_chunks_compile_once_and_keep_shape(four_devices):
    info, res = four_devices
    # 1003 rays in chunks of 96: 11 chunks, the last padded; 24 rays per device.
    assert info["traces"] == [[24]]
    assert res["pair"].shape == (17, 59, 2)
    np.testing.assert_array_equal(res["pair"], res["pair_ref"])


# --- In this process: whatever devices the test run has (one CPU by default).


def test_one_device_chunked_matches_unsharded():
    rng = np.random.default_rng(1)
    alpha = rng.uniform(0.001, 3.0, 301)
    ref = jax.jit(jaxlens.trace)(alpha, 20.0)
    for chunk in (None, 7, 10_000):
        got = trace_sharded(alpha, 20.0, chunk=chunk, progress=False)
        for f in ("phi", "status", "r_min"):
            np.testing.assert_array_equal(getattr(got, f), np.asarray(getattr(ref, f)))


def test_dtype_follows_inputs():
    # float32 rays with a Python-float distance stay float32, as in `trace`.
    alpha = np.linspace(0.01, 0.5, 10, dtype=np.float32)
    got = trace_sharded(alpha, 20.0)
    assert got.phi.dtype == jnp.asarray(jaxlens.trace(alpha, 20.0).phi).dtype == np.float32


def test_scalar_and_empty_batches():
    one = trace_sharded(0.3, 20.0)
    assert one.phi.shape == ()
    ref = jax.jit(jaxlens.trace)(np.array([0.3]), 20.0)  # a flat batch of one ray
    np.testing.assert_array_equal(one.phi, np.asarray(ref.phi)[0])
    empty = trace_sharded(np.zeros((0, 3)), 20.0)
    assert empty.phi.shape == (0, 3)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="distance"):
        trace_sharded(np.linspace(0.1, 1.0, 10), np.array([20.0] * 9 + [0.5]))
    with pytest.raises(ValueError, match="chunk"):
        trace_sharded(np.linspace(0.1, 1.0, 10), 20.0, chunk=0)
    with pytest.raises(ValueError, match="dimension"):
        shard_map_rays(jnp.sin, 1.0)
    with pytest.raises(ValueError, match="axis"):
        shard_map_rays(jnp.sin, np.ones(3), mesh=jax.make_mesh((1,), ("x",)))
    assert ray_mesh().devices.size == jax.device_count()
