"""Field converters shared by the configuration modules (traced scalars stay JAX arrays)."""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


def as_float32(value) -> Array:
    """A float32 JAX array (the converter of traced float config fields)."""
    return jnp.asarray(value, jnp.float32)


def as_int32(value) -> Array:
    """An int32 JAX array (the converter of traced integer config fields)."""
    return jnp.asarray(value, jnp.int32)
