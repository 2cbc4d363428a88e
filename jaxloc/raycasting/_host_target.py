"""A numpy function as a named XLA:CPU custom call: programs that call it can be cached on disk.

``jax.pure_callback`` and ``buffer_callback`` put a Python object into the compiled program, and
JAX never writes such a program to its persistent compilation cache ("uses host callbacks"): every
process compiled the filter step, which calls Embree, again (~15 s of the demo's warm start). A
custom call names its target instead; each process registers the function behind the name when
this module's caller is imported, so a program loaded from the cache finds it.

The target follows XLA's original CPU custom-call convention (API version 3,
``void(void* out, const void** in, const char* opaque, size_t opaque_len, XlaCustomCallStatus*)``),
implemented by a ctypes callback: no compiled extension. The operands' and results' shapes and
dtypes travel in ``opaque`` (static, part of the program), so a call is made on the shapes it was
traced with; code that is vmapped folds its batch away first (``jax.custom_batching.custom_vmap``,
as :mod:`jaxloc.raycasting.embree` does). Every call has one more result, a one-element status
(0 done, 1 failed): the callback cannot fail the XLA call (the status API is not exported), so an
exception is logged (``jaxloc`` logger, with its traceback) and the status turns the results into
:data:`FAILED_INT` / NaN in the program, never garbage. The callback writes each result through an
operand aliased to it (``input_output_aliases``), never through ``out``: in programs loaded from
the cache, jaxlib 0.10.1 handed a call inside a loop a result buffer where the array of result
pointers was due, and a one-result call crashed the process.
"""

from __future__ import annotations

import ctypes
import json
import logging
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

#: What an integer result holds after a failed call (float results hold NaN).
FAILED_INT = -1

_SIGNATURE = ctypes.CFUNCTYPE(
    None,
    ctypes.c_void_p,  # out: the results (unused: they are written through their operands)
    ctypes.POINTER(ctypes.c_void_p),  # in: the operand buffers
    ctypes.c_void_p,  # opaque
    ctypes.c_size_t,  # opaque_len
    ctypes.c_void_p,  # status (unused: see the module docstring)
)
#: The registered targets: name -> the ctypes callback (kept alive for the whole process).
_TARGETS: dict[str, object] = {}
_LOG = logging.getLogger("jaxloc")


def _view(address: int, shape: tuple, dtype: str) -> np.ndarray:
    """A numpy array over XLA's buffer at ``address`` (no copy; row-major, XLA's default)."""
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    if size == 0:
        return np.empty(shape, dtype)
    raw = (ctypes.c_char * size).from_address(address)
    return np.frombuffer(raw, dtype=dtype).reshape(shape)


def register_host_target(name: str, fn: Callable[[list, list], None]) -> bool:
    """Register ``fn(inputs, outputs)`` as the CPU custom-call target ``name`` (once a process).

    ``fn`` reads the operand arrays ``inputs`` and writes every result array of ``outputs`` in
    place (numpy views of XLA's buffers). Returns whether the target is usable; False where this
    jaxlib refuses the registration (the caller then keeps a Python callback).
    """
    if name in _TARGETS:
        return True

    def handler(_out, inputs, opaque, opaque_len, _status) -> None:
        spec = json.loads(ctypes.string_at(opaque, opaque_len))
        outs = spec["out"]
        # The results are written through their aliased operands (after the inputs), not `out`.
        first = len(spec["in"])
        *results, status = [_view(inputs[first + i], tuple(s), d) for i, (s, d) in enumerate(outs)]
        status[0] = 1
        try:
            operands = [_view(inputs[i], tuple(s), d) for i, (s, d) in enumerate(spec["in"])]
            fn(operands, results)
            status[0] = 0
        except Exception:  # noqa: BLE001 - nowhere to raise to: log it, report it in the status
            _LOG.exception("jaxloc: the host target %s failed; its results are invalid", name)

    callback = _SIGNATURE(handler)
    try:
        jax.ffi.register_ffi_target(
            name, jax.ffi.pycapsule(callback), platform="cpu", api_version=0
        )
    except Exception:  # noqa: BLE001 - a jaxlib without the legacy convention
        return False
    _TARGETS[name] = callback
    return True


def host_call(name: str, results: Sequence[jax.ShapeDtypeStruct], *operands: jax.Array) -> tuple:
    """Call the registered target ``name`` on ``operands`` (traced or not) for ``results``.

    Returns a tuple of arrays shaped as ``results``, :data:`FAILED_INT` / NaN where the call
    failed. Not vmappable by itself (the shapes are fixed in the program); not differentiable.
    """
    shapes = [*results, jax.ShapeDtypeStruct((1,), jnp.int32)]  # the status last
    spec = {
        "in": [[list(x.shape), str(x.dtype)] for x in operands],
        "out": [[list(r.shape), str(np.dtype(r.dtype))] for r in shapes],
    }
    call = jax.ffi.ffi_call(
        name,
        shapes,
        input_output_aliases={len(operands) + i: i for i in range(len(shapes))},
        custom_call_api_version=3,
        legacy_backend_config=json.dumps(spec, separators=(",", ":")),
    )
    *values, status = call(*operands, *(jnp.zeros(r.shape, r.dtype) for r in shapes))
    failed = status[0] != 0
    return tuple(
        jnp.where(failed, jnp.nan if jnp.issubdtype(v.dtype, jnp.floating) else FAILED_INT, v)
        for v in values
    )
