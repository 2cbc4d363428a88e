"""A numpy function as a named XLA:CPU FFI target: programs that call it can be cached on disk.

``jax.pure_callback`` and ``buffer_callback`` put a Python object into the compiled program, and
JAX never writes such a program to its persistent compilation cache ("uses host callbacks"): every
process compiled the filter step, which calls Embree, again (~15 s of the demo's warm start). A
custom call names its target instead; each process registers the function behind the name when
this module's caller is imported, so a program loaded from the cache finds it.

The target is an XLA FFI handler (the typed API, ``XLA_FFI_Error* handler(XLA_FFI_CallFrame*)``
of ``xla/ffi/api/c_api.h``, which ``jax.ffi`` documents) implemented by a ctypes callback over the
C structs below: no compiled extension. Every buffer carries its dtype and dimensions, so one
target serves any shape, and a vmapped call reaches the function with its batch axes in front
(``vmap_method="expand_dims"``, the convention of ``jax.pure_callback``). The handler answers
XLA's metadata query with the API version of the running XLA, does nothing in the stages before
execution, and never returns an error object: every call has one more result, a status (0 done, 1
failed), and an exception is logged (``jaxloc`` logger, with its traceback) while the status turns
the results into :data:`FAILED_INT` / NaN in the program, never garbage.

Why not XLA's older custom-call convention (API version 0, the shapes in an opaque string, which
jaxloc used first): in programs loaded from the cache, jaxlib 0.10.1 handed a call inside a loop a
result buffer where the array of result pointers was due, and crashed on a one-result call. The
typed FFI is the convention ``jax.ffi`` and XLA's own CPU runtime are built on.
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

#: What an integer result holds after a failed call (float results hold NaN).
FAILED_INT = -1

#: XLA_FFI_DataType codes of the dtypes a target can exchange.
_DTYPES = {
    1: np.bool_,
    2: np.int8,
    3: np.int16,
    4: np.int32,
    5: np.int64,
    6: np.uint8,
    7: np.uint16,
    8: np.uint32,
    9: np.uint64,
    10: np.float16,
    11: np.float32,
    12: np.float64,
}
_METADATA_EXTENSION = 1  # XLA_FFI_Extension_Metadata
_EXECUTE = 3  # XLA_FFI_ExecutionStage_EXECUTE


class _Extension(ctypes.Structure):
    """XLA_FFI_Extension_Base: a linked list of extensions."""


_Extension._fields_ = [
    ("struct_size", ctypes.c_size_t),
    ("type", ctypes.c_int),
    ("next", ctypes.POINTER(_Extension)),
]


class _Version(ctypes.Structure):
    """XLA_FFI_Api_Version."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.c_void_p),
        ("major", ctypes.c_int),
        ("minor", ctypes.c_int),
    ]


class _Api(ctypes.Structure):
    """The head of XLA_FFI_Api (only its version is read)."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.c_void_p),
        ("version", _Version),
    ]


class _Metadata(ctypes.Structure):
    """XLA_FFI_Metadata: what XLA asks of a handler when it is registered."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("version", _Version),
        ("traits", ctypes.c_uint32),
        ("state_type_id", ctypes.c_int64),
    ]


class _MetadataExtension(ctypes.Structure):
    """XLA_FFI_Metadata_Extension."""

    _fields_ = [("base", _Extension), ("metadata", ctypes.POINTER(_Metadata))]


class _Buffer(ctypes.Structure):
    """XLA_FFI_Buffer: a dense row-major array."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.c_void_p),
        ("dtype", ctypes.c_int),
        ("data", ctypes.c_void_p),
        ("rank", ctypes.c_int64),
        ("dims", ctypes.POINTER(ctypes.c_int64)),
    ]


class _Buffers(ctypes.Structure):
    """XLA_FFI_Args and XLA_FFI_Rets (the same layout): buffers only, as ffi_call passes them."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.c_void_p),
        ("size", ctypes.c_int64),
        ("types", ctypes.POINTER(ctypes.c_int)),
        ("items", ctypes.POINTER(ctypes.POINTER(_Buffer))),
    ]


class _Attrs(ctypes.Structure):
    """XLA_FFI_Attrs (unused: the targets take no attributes)."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.c_void_p),
        ("size", ctypes.c_int64),
        ("types", ctypes.c_void_p),
        ("names", ctypes.c_void_p),
        ("attrs", ctypes.c_void_p),
    ]


class _CallFrame(ctypes.Structure):
    """XLA_FFI_CallFrame."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("extension_start", ctypes.POINTER(_Extension)),
        ("api", ctypes.POINTER(_Api)),
        ("ctx", ctypes.c_void_p),
        ("stage", ctypes.c_int),
        ("args", _Buffers),
        ("rets", _Buffers),
        ("attrs", _Attrs),
        ("future", ctypes.c_void_p),
    ]


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_CallFrame))
#: The registered targets: name -> the ctypes callback (kept alive for the whole process).
_TARGETS: dict[str, object] = {}
_LOG = logging.getLogger("jaxloc")


def _view(buffer: _Buffer) -> np.ndarray:
    """A numpy array over an XLA buffer (no copy)."""
    shape = tuple(buffer.dims[i] for i in range(buffer.rank))
    dtype = np.dtype(_DTYPES[buffer.dtype])
    size = int(np.prod(shape)) * dtype.itemsize
    if size == 0:
        return np.empty(shape, dtype)
    raw = (ctypes.c_char * size).from_address(buffer.data)
    return np.frombuffer(raw, dtype=dtype).reshape(shape)


def _answer_metadata(frame: _CallFrame) -> bool:
    """Fill in the metadata extension if XLA asks for it (at registration); whether it did."""
    extension = frame.extension_start
    while extension:
        if extension.contents.type == _METADATA_EXTENSION:
            metadata = ctypes.cast(extension, ctypes.POINTER(_MetadataExtension)).contents
            answer = metadata.metadata.contents
            answer.version.major = frame.api.contents.version.major
            answer.version.minor = frame.api.contents.version.minor
            answer.traits = 0
            return True
        extension = extension.contents.next
    return False


def register_host_target(name: str, fn: Callable[[list, list], None]) -> bool:
    """Register ``fn(inputs, outputs)`` as the CPU FFI target ``name`` (once a process).

    ``fn`` reads the operand arrays ``inputs`` and writes every result array of ``outputs`` in
    place (numpy views of XLA's buffers, with the batch axes of a vmapped call in front). Returns
    whether the target is usable; False where this jaxlib refuses the registration (the caller
    then keeps a Python callback).
    """
    if name in _TARGETS:
        return True

    def handler(frame_pointer) -> None:
        frame = frame_pointer.contents
        if _answer_metadata(frame) or frame.stage != _EXECUTE:
            return None
        rets = frame.rets.items
        status = _view(rets[frame.rets.size - 1].contents)
        status[...] = 1
        try:
            inputs = [_view(frame.args.items[i].contents) for i in range(frame.args.size)]
            outputs = [_view(rets[i].contents) for i in range(frame.rets.size - 1)]
            fn(inputs, outputs)
            status[...] = 0
        except Exception:  # noqa: BLE001 - nothing to raise to: log it, report it in the status
            _LOG.exception("jaxloc: the host target %s failed; its results are invalid", name)
        return None

    callback = _HANDLER(handler)
    try:
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(callback), platform="cpu")
    except Exception:  # noqa: BLE001 - a jaxlib without the typed FFI from Python
        return False
    _TARGETS[name] = callback
    return True


def host_call(name: str, results: Sequence[jax.ShapeDtypeStruct], *operands: jax.Array) -> tuple:
    """Call the registered target ``name`` on ``operands`` (traced or not) for ``results``.

    Returns a tuple of arrays shaped as ``results``, :data:`FAILED_INT` / NaN where the call
    failed. Under vmap the target sees every operand with the batch axes in front (size 1 where an
    operand is not batched) and writes the results of the whole batch. Not differentiable.
    """
    shapes = [*results, jax.ShapeDtypeStruct((1,), jnp.int32)]  # the status last
    call = jax.ffi.ffi_call(name, shapes, vmap_method="expand_dims")
    *values, status = call(*operands)
    failed = status[0] != 0
    return tuple(
        jnp.where(failed, jnp.nan if jnp.issubdtype(v.dtype, jnp.floating) else FAILED_INT, v)
        for v in values
    )
