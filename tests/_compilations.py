"""Counting XLA compilations from outside the library, through ``jax.monitoring``.

JAX reports every backend compilation as the duration event
``/jax/core/compile/backend_compile_duration`` (a program found in the in-memory caches is none;
one loaded from the persistent cache still is, so tests that must see "no new program" count
inside one process after a first call).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import jax

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"

#: Every compilation of this process so far: "<thread>: <function name>".
COMPILED: list[str] = []
_LOCK = threading.Lock()


def _record(event: str, _duration: float, **kwargs) -> None:
    if event == COMPILE_EVENT:
        with _LOCK:
            COMPILED.append(f"{threading.current_thread().name}: {kwargs.get('fun_name', '?')}")


jax.monitoring.register_event_duration_secs_listener(_record)


@contextlib.contextmanager
def compilations() -> Iterator[list[str]]:
    """The compilations made while the block runs, as a list that fills in as they happen."""
    found: list[str] = []
    start = len(COMPILED)
    try:
        yield found
    finally:
        found.extend(COMPILED[start:])
