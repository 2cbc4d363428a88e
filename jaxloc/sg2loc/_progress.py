"""Progress bars that compiled filter passes tick from inside their ``lax.scan``.

A pass given a bar's int32 id (``run_pass(..., progress=id)``) ticks it after each frame through
:func:`tick_after`. The id is a traced operand and the host function is one module-level
function (:func:`tick`), so a compiled pass serves every bar: each run ticks the bar whose id it
was given, and the id of a closed bar ticks nothing.

On one CPU device the host function is the XLA FFI target :data:`TARGET`
(:mod:`jaxloc.raycasting._host_target`), which a program names rather than holds: programs with
the bar are written to JAX's persistent compilation cache like those without. Elsewhere (a GPU, a
device mesh) it is a ``jax.debug.callback`` (run once, on the first device, under a mesh), and
JAX caches those programs in memory only.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from tqdm.auto import tqdm

from jaxloc.raycasting._host_target import register_host_target

#: The CPU FFI target that ticks a bar (operand: the bar's int32 id).
TARGET = "jaxloc_progress_tick"

#: The open bars by id (ids are never reused).
_OPEN: dict[int, FrameBar] = {}
_IDS = itertools.count(1)


class FrameBar:
    """A tqdm bar over ``len(strides)`` rounds of ``num_frames`` frames, open while used as a
    context manager; ``id`` (an int32 NumPy scalar) names it to :func:`tick`."""

    def __init__(self, strides: tuple[int, ...], num_frames: int):
        self.strides = strides
        self.num_frames = num_frames
        self.id = np.int32(next(_IDS))
        self.bar = tqdm(total=len(strides) * num_frames, unit="frame")
        self._describe(0)

    def _describe(self, round_index: int) -> None:
        stride = self.strides[round_index]
        self.bar.set_description(f"round {round_index + 1}/{len(self.strides)} (stride {stride})")

    def tick(self) -> None:
        """One more frame filtered (the next round's label after a round's last frame)."""
        self.bar.update(1)
        done = self.bar.n
        if done % self.num_frames == 0 and done < self.bar.total:
            self._describe(done // self.num_frames)

    def __enter__(self) -> FrameBar:
        _OPEN[int(self.id)] = self
        return self

    def __exit__(self, *exc) -> None:
        del _OPEN[int(self.id)]
        self.bar.close()


def tick(bar_id: np.ndarray) -> None:
    """The host callback of a pass: frame done on the bar ``bar_id`` (int32 scalar), if open."""
    bar = _OPEN.get(int(bar_id))
    if bar is not None:
        bar.tick()


def _tick_target(inputs: list, outputs: list) -> None:
    """:func:`tick` as a host target (no results besides the target's status)."""
    tick(inputs[0])


def tick_after(bar_id: Array, done: Array, multi_device: bool) -> None:
    """Inside a traced pass: tick bar ``bar_id`` (int32 scalar) once ``done`` is computed.

    The barrier orders the tick after ``done``, and the id stays unbatched under ``jax.vmap``
    (one tick per frame, not per batch element). ``multi_device`` (static): the program runs on a
    device mesh, where a custom call would run on every device; a ``jax.debug.callback`` runs
    once there.
    """
    bar_id, _ = jax.lax.optimization_barrier((bar_id, done))
    on_cpu = jax.default_backend() == "cpu" and not multi_device
    if on_cpu and register_host_target(TARGET, _tick_target):
        status = jax.ShapeDtypeStruct((1,), jnp.int32)
        jax.ffi.ffi_call(TARGET, [status], has_side_effect=True, vmap_method="expand_dims")(bar_id)
    else:
        jax.debug.callback(tick, bar_id)
