"""The native CPU ray engine (``native/embree_ffi.cc``): built on first use, loaded, self-tested.

The C++ source is compiled with the system C++ compiler the first time a process needs it, into
the user cache (``<user cache folder>/jaxloc/native/<key>/``, or ``$JAXLOC_NATIVE_DIR``). The key
hashes the source, the jaxlib version (whose FFI headers it is built against), the compiler's
version line and the Embree library's name and size, so any change builds anew. Parallel
processes (test workers) take a file lock; the library is written under a temporary name and
renamed into place, so nobody loads half a file. Why at first use rather than at install: jaxloc
installs as pure Python with hatchling (``pip install -e .`` needs no compiler), the FFI headers
come with the jaxlib that is installed at run time, and a machine without a compiler loses only
speed.

Embree itself is the library the embreex wheel ships (``embreex.libs/libembree4*.so*``), loaded
by path at run time; nothing is downloaded. After loading, the engine casts a small fixed scene
(packets and single rays, hits and misses) and must match a float64 reference, or it is not used.

``$JAXLOC_NATIVE``: unset, ``1`` or ``auto`` (the default) use the native engine where it builds
and passes its self-test, else warn once and keep the Python engine; ``0`` keeps the Python engine;
``require`` raises instead of falling back (CI runs so, that a broken build fails it).
``$JAXLOC_NATIVE_THREADS``:
threads that cast (the calling thread included; default: the CPUs this process may run on).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import importlib.util
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import numpy as np

ENV_MODE = "JAXLOC_NATIVE"
ENV_THREADS = "JAXLOC_NATIVE_THREADS"
ENV_DIR = "JAXLOC_NATIVE_DIR"
#: The source files of the engine (in ``jaxloc/raycasting/native/``).
SOURCES = ("embree_ffi.cc", "embree_api.h")
#: Symbol of the XLA FFI handler in the built library.
HANDLER = "jaxloc_embree_nearest_native"
_SOURCE_DIR = Path(__file__).resolve().parent / "native"
_LIBRARY_NAME = "jaxloc_embree_ffi.so"


class NativeUnavailable(RuntimeError):
    """The native engine cannot be built, loaded or trusted here (the message says why)."""


def mode() -> str:
    """``"auto"`` (the default), ``"off"`` or ``"require"``, from :data:`ENV_MODE`.

    Raises:
        ValueError: any other value.
    """
    value = os.environ.get(ENV_MODE, "auto").strip().lower()
    if value in ("", "auto", "1"):
        return "auto"
    if value in ("0", "off", "false", "no"):
        return "off"
    if value == "require":
        return "require"
    raise ValueError(f"{ENV_MODE} must be 0, 1 (auto) or require, got {value!r}")


def threads() -> int:
    """Threads of the native engine: :data:`ENV_THREADS`, else 0 (the CPUs of the affinity mask).

    Raises:
        ValueError: a value that is not a positive integer.
    """
    value = os.environ.get(ENV_THREADS, "").strip()
    if not value:
        return 0
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{ENV_THREADS} must be a positive integer, got {value!r}")
    return int(value)


def embree_library() -> Path:
    """The Embree 4 shared library of the installed embreex wheel."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        raise NativeUnavailable("embreex is not installed")
    package = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(package.parent.glob("embreex.libs/libembree4*.so*"))
    if not found:
        raise NativeUnavailable(f"no libembree4 next to {package} (embreex.libs/)")
    return found[0]


def compiler() -> str:
    """The C++ compiler: ``$CXX``, else ``c++``, ``g++`` or ``clang++`` on the PATH."""
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    raise NativeUnavailable("no C++ compiler (set CXX, or install g++ or clang++)")


def cache_dir() -> Path:
    """Where built engines are kept: :data:`ENV_DIR`, else ``<user cache>/jaxloc/native``."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR]).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("jaxloc")) / "native"


def compile_flags() -> list[str]:
    """The compiler's options besides the include path, the source and the output (part of the
    build key). ``-fno-trapping-math`` lets the compiler vectorize the hit values' guarded
    divisions (no floating-point exception is ever inspected); no ``-march``: Embree picks its
    own kernels for the CPU at run time, and the library stays valid on any x86-64."""
    return ["-O3", "-fno-trapping-math", "-std=c++17", "-shared", "-fPIC", "-pthread"]


def build_key(cxx: str, library: Path) -> str:
    """Hash of everything the built engine depends on (see the module docstring)."""
    import jaxlib

    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update((_SOURCE_DIR / name).read_bytes())
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=60)
    parts = (jaxlib.__version__, version.stdout.splitlines()[:1], library.name, compile_flags())
    for part in parts:
        digest.update(repr(part).encode())
    digest.update(str(library.stat().st_size).encode())
    return digest.hexdigest()[:20]


def build() -> Path:
    """The built engine library, compiling it if this key has none yet (locked, atomic)."""
    import filelock
    import jax

    cxx, library = compiler(), embree_library()
    folder = cache_dir() / build_key(cxx, library)
    target = folder / _LIBRARY_NAME
    if target.exists():
        return target
    folder.mkdir(parents=True, exist_ok=True)
    with filelock.FileLock(str(folder / "build.lock"), timeout=600):
        if target.exists():  # another process built it while we waited
            return target
        with tempfile.TemporaryDirectory(dir=folder) as scratch:
            partial = Path(scratch) / _LIBRARY_NAME
            command = [
                cxx, *compile_flags(),
                "-isystem", jax.ffi.include_dir(),
                str(_SOURCE_DIR / "embree_ffi.cc"), "-o", str(partial), "-ldl",
            ]  # fmt: skip
            done = subprocess.run(command, capture_output=True, text=True, timeout=600)
            if done.returncode != 0:
                raise NativeUnavailable(f"the build failed: {done.stderr.strip()[-2000:]}")
            os.replace(partial, target)
    return target


class NativeEngine:
    """The loaded engine: its ctypes handle, packet width and thread count."""

    def __init__(self, path: Path):
        self.path = path
        self.lib = ctypes.CDLL(str(path))
        error = ctypes.create_string_buffer(512)
        lib = self.lib
        lib.jaxloc_native_init.argtypes = [
            ctypes.c_char_p,
            ctypes.c_int,
            ctypes.c_char_p,
            ctypes.c_int,
        ]
        if lib.jaxloc_native_init(str(embree_library()).encode(), threads(), error, 512):
            raise NativeUnavailable(f"Embree did not load: {error.value.decode()}")
        pointer = ctypes.POINTER
        lib.jaxloc_native_cast.argtypes = [
            pointer(ctypes.c_float), ctypes.c_int64, pointer(ctypes.c_float),
            pointer(ctypes.c_float), pointer(ctypes.c_uint8), ctypes.c_int64,
            pointer(ctypes.c_int32), pointer(ctypes.c_float), pointer(ctypes.c_float),
            pointer(ctypes.c_float), ctypes.c_char_p, ctypes.c_int,
        ]  # fmt: skip
        lib.jaxloc_native_packets_traced.restype = ctypes.c_int64
        lib.jaxloc_native_raster_bands.restype = ctypes.c_int64
        self.packet_width = lib.jaxloc_native_packet_width()
        self.threads = lib.jaxloc_native_threads()

    def set_packet_width(self, width: int) -> int:
        """Trace packets of ``width`` rays (16, 8, 4; 1: single rays only), at most the CPU's
        native width; returns the width in use (a benchmark knob)."""
        self.packet_width = self.lib.jaxloc_native_set_packet_width(int(width))
        return self.packet_width

    def cast(self, triangles, origins, directions, valid=None) -> tuple[np.ndarray, ...]:
        """The engine on numpy arrays, without XLA: ``(faces, t, u, v)`` of (R,) rays against
        (T, 3, 3) triangles (as the FFI target's values-only call; ``t`` meaningless on a miss)."""
        triangles = np.ascontiguousarray(triangles, np.float32)
        origins = np.ascontiguousarray(origins, np.float32)
        directions = np.ascontiguousarray(directions, np.float32)
        num = origins.shape[0]
        valid = np.ones(num, np.uint8) if valid is None else np.ascontiguousarray(valid, np.uint8)
        out = (np.empty(num, np.int32),) + tuple(np.empty(num, np.float32) for _ in range(3))
        error = ctypes.create_string_buffer(512)

        def ptr(a, kind):
            return a.ctypes.data_as(ctypes.POINTER(kind))

        f32 = ctypes.c_float
        failed = self.lib.jaxloc_native_cast(
            ptr(triangles, f32), triangles.shape[0], ptr(origins, f32), ptr(directions, f32),
            ptr(valid, ctypes.c_uint8), num, ptr(out[0], ctypes.c_int32), ptr(out[1], f32),
            ptr(out[2], f32), ptr(out[3], f32), error, 512,
        )  # fmt: skip
        if failed:
            raise NativeUnavailable(f"the native cast failed: {error.value.decode()}")
        return out

    def packets_traced(self) -> int:
        """Packets the engine has traced in this process (rays cast together; a test knob)."""
        return self.lib.jaxloc_native_packets_traced()

    def raster_bands(self) -> int:
        """Bands of two raster lines (a camera's rows of rays) the engine has cast in tiles in
        this process (a test knob)."""
        return self.lib.jaxloc_native_raster_bands()

    def clear_cache(self) -> None:
        """Drop the engine's cached Embree scenes."""
        self.lib.jaxloc_native_clear_cache()

    def cached_scenes(self) -> int:
        """How many Embree scenes the engine holds (at most 8)."""
        return self.lib.jaxloc_native_cached_scenes()

    def handler(self):
        """The XLA FFI handler as a PyCapsule, for ``jax.ffi.register_ffi_target``."""
        import jax

        return jax.ffi.pycapsule(getattr(self.lib, HANDLER))


def self_test_rays() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The fixed self-test: two unit squares (4 triangles, one shared diagonal each) at z = 2
    and z = 3 (the farther one offset), all-zero padding rows between; a raster of 8 lines of 16
    camera rays from one origin aimed at cell centres (cast in tiles, as packets), the same
    directions from scattered origins (single rays) and some invalid rays. Returns
    ``(triangles, origins, directions, valid)``."""
    near = np.array([[[0, 0, 2], [1, 0, 2], [1, 1, 2]], [[0, 0, 2], [1, 1, 2], [0, 1, 2]]], float)
    far = near + np.array([0.5, 0.0, 1.0])
    padding = np.zeros((2, 3, 3))
    triangles = np.concatenate([near, padding, far]).astype(np.float32)
    x_grid = (np.arange(16) + 0.5) / 16 * 2.0 - 0.4  # x in [-0.34, 1.54], y in [-0.275, 1.475]:
    y_grid = (np.arange(8) + 0.5) / 8 * 2.0 - 0.4  # hits and misses
    x, y = np.meshgrid(x_grid, y_grid + 0.013)  # 8 lines of 16
    target = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.5)], 1)
    origin = np.array([0.3, 0.4, -25.0])  # far enough for the raster's tiles to go as packets
    camera_d = target - origin
    scattered = origin + 0.01 * np.arange(camera_d.shape[0])[:, None] * np.array([1, -1, 0])
    origins = np.concatenate([np.repeat(origin[None], len(target), 0), scattered])
    directions = np.concatenate([camera_d, target - scattered])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    valid = np.ones(len(origins), bool)
    valid[5::7] = False
    return triangles, origins.astype(np.float32), directions.astype(np.float32), valid


def reference_hits(triangles, origins, directions, valid):
    """Nearest hits by a float64 brute force (Moller-Trumbore): faces (-1 on a miss or an
    invalid ray; padding rows never hit), t, u, v (t = inf where there is no hit)."""
    tri = np.asarray(triangles, np.float64)
    o, d = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d[:, None], e2[None])
    det = np.sum(e1[None] * p, -1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o[:, None] - v0[None]
    u = np.sum(s * p, -1) * inv
    q = np.cross(s, e1[None])
    v = np.sum(d[:, None] * q, -1) * inv
    t = np.sum(e2[None] * q, -1) * inv
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & np.asarray(valid)[:, None]
    t = np.where(inside, t, np.inf)
    face = np.argmin(t, 1)
    rows = np.arange(len(o))
    hit = np.isfinite(t[rows, face])
    return np.where(hit, face, -1), t[rows, face], u[rows, face], v[rows, face]


def self_test(engine: NativeEngine) -> None:
    """Cast :func:`self_test_rays` with the engine; raise :class:`NativeUnavailable` unless
    every face matches the float64 reference and t, u, v agree within 1e-5 (the camera raster in
    tiles, as packets, where the CPU has packet kernels)."""
    rays = self_test_rays()
    packets, bands = engine.packets_traced(), engine.raster_bands()
    faces, t, u, v = engine.cast(*rays)
    if engine.packet_width > 1 and engine.packets_traced() == packets:
        raise NativeUnavailable("the self-test's camera rays were not traced as packets")
    if engine.packet_width > 1 and engine.raster_bands() == bands:
        raise NativeUnavailable("the self-test's camera raster was not cast in tiles")
    ref_faces, ref_t, ref_u, ref_v = reference_hits(*rays)
    hit = ref_faces >= 0
    if not (np.array_equal(faces, ref_faces) and 0.2 < hit.mean() < 0.9):
        raise NativeUnavailable("the self-test's faces differ from the float64 reference")
    for got, want in ((t, ref_t), (u, ref_u), (v, ref_v)):
        if not np.allclose(got[hit], want[hit], atol=1e-5, rtol=0):
            raise NativeUnavailable("the self-test's t, u, v differ from the float64 reference")


@functools.cache
def engine() -> NativeEngine:
    """The native engine, built, loaded and self-tested whatever :data:`ENV_MODE` says; once per
    process.

    Raises:
        NativeUnavailable, OSError, subprocess.SubprocessError: it cannot be built or trusted.
        ValueError: a bad :data:`ENV_THREADS`.
    """
    threads()  # a bad value is the user's error, not a reason to fall back
    built = NativeEngine(build())
    self_test(built)
    return built


@functools.cache
def load() -> NativeEngine | None:
    """The native engine, or None where :data:`ENV_MODE` is 0 or it is unavailable (one warning
    says why). Once per process.

    Raises:
        NativeUnavailable: unavailable while :data:`ENV_MODE` is ``require``.
        ValueError: a bad :data:`ENV_MODE` or :data:`ENV_THREADS`.
    """
    wanted = mode()
    if wanted == "off":
        return None
    try:
        return engine()
    except (NativeUnavailable, OSError, subprocess.SubprocessError) as error:
        if wanted == "require":
            raise NativeUnavailable(f"{ENV_MODE}=require, but: {error}") from error
        warnings.warn(
            f"jaxloc: the native Embree engine is unavailable ({error}); using the Python "
            f"Embree engine. Set {ENV_MODE}=0 to silence this.",
            RuntimeWarning,
            stacklevel=2,
        )
        return None
