"""Field converters and value checks shared by the configuration modules (traced scalars stay JAX
arrays; checks of values skip tracers, which a configuration holds inside a caller's trace)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc._traced import concrete


def _as_array(value, dtype) -> Array:
    if isinstance(value, jax.Array):  # tracers too
        return jnp.asarray(value, dtype)
    return jax.device_put(np.asarray(value, dtype))  # converted on the host: nothing compiled


def as_float32(value) -> Array:
    """A float32 JAX array (the converter of traced float config fields)."""
    return _as_array(value, np.float32)


def as_int32(value) -> Array:
    """An int32 JAX array (the converter of traced integer config fields)."""
    return _as_array(value, np.int32)


def finite_scalar(owner: str, name: str, value) -> float | None:
    """A scalar configuration field's value as a float, or None for a tracer (unchecked); a
    one-line ValueError naming ``owner.name`` unless it is a finite scalar."""
    if jnp.shape(value) != ():
        raise ValueError(f"{owner}.{name} must be a scalar, got {value!r}")
    if not concrete(value):
        return None
    number = float(np.asarray(value))
    if not np.isfinite(number):
        raise ValueError(f"{owner}.{name} must be finite, got {number}")
    return number


def finite_nonnegative(value) -> bool:
    """Whether every entry of ``value`` is finite and >= 0 (True for a tracer: unchecked)."""
    if not concrete(value):
        return True
    array = np.asarray(value)
    return bool(np.all(np.isfinite(array) & (array >= 0)))


def shown(value) -> str:
    """A configuration value for an error message: its numbers, or a tracer's shape."""
    if not concrete(value):
        return f"a traced array of shape {jnp.shape(value)}"
    array = np.asarray(value)
    if array.ndim == 0:
        return f"{array.item():.6g}"
    numbers = [f"{x:.6g}" for x in array.ravel().tolist()]
    return f"({numbers[0]},)" if len(numbers) == 1 else f"({', '.join(numbers)})"
