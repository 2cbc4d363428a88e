"""Traced configuration leaves: the converters of continuous config fields and the test that tells a
concrete value (checked on construction) from a tracer (a config built or stacked under a trace).

A Python float reaching ``eqx.filter_jit`` is a static value: every new value compiles a new
program. Continuous settings are therefore stored as 0-d arrays: numpy on the host (building a
config touches no device and compiles nothing), JAX arrays and tracers kept as JAX values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_leaf(value, dtype):
    """``value`` as a strongly typed array of ``dtype``: numpy on the host (no device dispatch),
    JAX values and tracers through ``jnp.asarray`` (returned as they are when they already are
    one), so a jitted function sees one signature whatever form the caller used."""
    if isinstance(value, jax.Array):  # tracers too
        if value.dtype == dtype and not getattr(value, "weak_type", False):
            return value
        return jnp.asarray(value, dtype)
    return np.asarray(value, dtype)


def float32_leaf(value):
    """``value`` as a float32 array leaf (numpy on the host, JAX for JAX values and tracers)."""
    return as_leaf(value, np.float32)


def int32_leaf(value):
    """``value`` as an int32 array leaf (numpy on the host, JAX for JAX values and tracers)."""
    return as_leaf(value, np.int32)


def optional_float32_leaf(value):
    """None, or ``value`` as a float32 array leaf (a switch kept by None-ness, a traced value)."""
    return None if value is None else float32_leaf(value)


def concrete(*values) -> bool:
    """Whether every value is known on the host (not a tracer): only those are range-checked."""
    return not any(isinstance(v, jax.core.Tracer) for v in values)
