"""Test configuration: float64 everywhere except where a test module opts out.

The float32 path is checked in tests/test_float32.py, which runs its checks in a
subprocess with x64 disabled so that both precisions are exercised in one session.
"""

import jax

jax.config.update("jax_enable_x64", True)
