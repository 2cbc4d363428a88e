"""The engines' acceleration structures: built once per map, cached by a fingerprint of its
triangles that the traced program computes (a 64-bit integer hash of their bits), so editing a
map's triangles gives a new key and a stale structure is never used."""

from __future__ import annotations

import collections
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

#: Acceleration structures kept per engine (least recently used first out).
CACHE_SIZE = 8


def fingerprint(triangles: Array) -> Array:
    """A 64-bit hash (2,) uint32 of ``triangles``' bits, computed in the traced program.

    Wrapping integer sums of the bits times per-position odd multipliers: exact and independent of
    the reduction order, so the same triangles always give the same key on any backend.
    """
    bits = jax.lax.bitcast_convert_type(triangles.reshape(-1).astype(jnp.float32), jnp.uint32)
    position = jnp.arange(bits.shape[0], dtype=jnp.uint32)
    bits = bits ^ (bits >> 16)
    first = jnp.sum(bits * (position * jnp.uint32(0x9E3779B1) | jnp.uint32(1)), dtype=jnp.uint32)
    second = jnp.sum(
        bits * ((position ^ jnp.uint32(0x5BD1E995)) * jnp.uint32(0x85EBCA77) | jnp.uint32(1)),
        dtype=jnp.uint32,
    )
    return jnp.stack([first, second])


class StructureCache:
    """A small thread-safe LRU of acceleration structures, keyed by (device, shape, fingerprint)."""

    def __init__(self, build):
        self._build = build
        self._items: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, triangles):
        with self._lock:
            item = self._items.get(key)
            if item is None:
                item = self._build(triangles)
                self._items[key] = item
                while len(self._items) > CACHE_SIZE:
                    self._items.popitem(last=False)
            self._items.move_to_end(key)
            return item

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def real_triangles(triangles: np.ndarray) -> np.ndarray:
    """Indices (K,) of the real rows of ``triangles`` (T, 3, 3): padding rows are all zero.

    Engines build on these only: thousands of degenerate padding triangles at the origin would
    make one leaf that every ray passing near the origin has to test.
    """
    return np.flatnonzero(np.any(triangles.reshape(triangles.shape[0], -1) != 0, axis=1))
