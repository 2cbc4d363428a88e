"""JAX's persistent compilation cache for jaxloc: compile once per machine, not once per process.

The command line turns the cache on for every command (:func:`enable_compilation_cache`); in a
notebook or script one call does the same::

    import jaxloc
    jaxloc.enable_compilation_cache()   # before the first jitted call

Where: ``$JAXLOC_CACHE_DIR`` when set, else ``xla/`` in the user's cache folder (platformdirs:
``~/.cache/jaxloc`` on Linux, ``~/Library/Caches/jaxloc`` on macOS,
``%LOCALAPPDATA%\\jaxloc\\Cache`` on Windows). ``JAXLOC_NO_CACHE=1`` (or the command line's
``--no-cache``) turns it off. The folder is bounded (:data:`DEFAULT_MAX_BYTES`, least recently used
entries go first) and can be cleared at any time (:func:`clear_compilation_cache`, ``jaxloc cache
--clear``): a missing entry is compiled again. Entries are keyed by JAX on the program, the JAX /
jaxlib version, the backend and the compile options, so a cache shared by versions or machines
never serves the wrong program; an unreadable or damaged entry is reported as a warning and the
program is compiled instead. Beside JAX's entries the folder keeps jaxloc's traced programs
(``programs/``, :func:`cached_call`) and described map folders (``maps/``, :func:`cache_entry`);
those are not counted in the size bound, and ``jaxloc cache --clear`` removes them too.

The SG2Loc commands also compile faster, with XLA:CPU's legacy fusion emitters
(:func:`prefer_fast_compilation`); a single program can ask for them too
(:func:`legacy_emitter_options`, :func:`cached_call`'s ``compiler_options``).

On some x86 CPUs (AMD Zen 4 here; Cascade Lake in jax-ml/jax#38445) jaxlib 0.9-0.10 logs two
``E ... cpu_aot_loader.cc] Loading XLA:CPU AOT result. Target machine feature +prefer-no-gather is
not supported ...`` lines for every program it loads from the cache: the compile-time features
include LLVM tuning preferences the host check does not list. The program loads and runs (a
second process of the same program skips compilation); only the log is wrong. The command line
hides XLA's C++ log below FATAL (:func:`quiet_xla_log`) unless ``TF_CPP_MIN_LOG_LEVEL`` is set;
in a notebook, set ``TF_CPP_MIN_LOG_LEVEL=3`` before importing jax to do the same.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from pathlib import Path

#: Environment variable that moves the cache.
ENV_DIR = "JAXLOC_CACHE_DIR"
#: Environment variable that turns the cache off (any value but "", "0", "false", "no").
ENV_OFF = "JAXLOC_NO_CACHE"
#: Size bound of the cache folder in bytes (2 GiB); JAX evicts the least recently used entries.
DEFAULT_MAX_BYTES = 2 * 1024**3
#: In this process: the exported programs by key, their compiled forms (or :func:`prepare_call`'s
#: futures of them) by ("compiled", key, options), the source digest ("source"), the folder
#: :func:`enable_compilation_cache` turned on ("folder") and the compiling thread ("compiler").
_PROGRAMS: dict[object, object] = {}


def cache_disabled() -> bool:
    """Whether :data:`ENV_OFF` turns the cache off."""
    return os.environ.get(ENV_OFF, "").strip().lower() not in ("", "0", "false", "no")


def quiet_xla_log() -> bool:
    """Hide XLA's C++ log below FATAL in this process (``TF_CPP_MIN_LOG_LEVEL=3``), where that
    can still take effect (jax not imported yet) and the user has not chosen a level.

    Why: the spurious ``cpu_aot_loader`` errors of every cached program (module docstring).
    XLA's real failures still reach the caller as Python exceptions. Returns whether it did.
    """
    if "jax" in sys.modules or "TF_CPP_MIN_LOG_LEVEL" in os.environ:
        return False
    os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"
    return True


#: The XLA flags :func:`prefer_fast_compilation` sets: XLA:CPU's legacy fusion emitters, and
#: LLVM's optimization level 1 for the generated code.
FAST_COMPILATION_FLAG = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=1"
#: The jaxlib versions (major, minor), inclusive, whose XLA has these flags; an unknown flag in
#: ``XLA_FLAGS`` aborts the process, so it is not set for any other version.
FAST_COMPILATION_JAXLIB = ((0, 7), (0, 10))
#: The same choice as one program's compile option (:func:`legacy_emitter_options`).
LEGACY_EMITTER_OPTION = "xla_cpu_use_fusion_emitters"


def prefer_fast_compilation() -> bool:
    """Compile with XLA:CPU's legacy fusion emitters and LLVM's optimization level 1 in this
    process (``XLA_FLAGS`` = :data:`FAST_COMPILATION_FLAG`), where that can still take effect
    (jax not imported yet), the user has not set ``XLA_FLAGS`` and the installed jaxlib is one of
    :data:`FAST_COMPILATION_JAXLIB`. The SG2Loc commands (``localize-camera``, ``demo``) call
    it first thing.

    Why: XLA:CPU compiles jaxloc's programs 20-40 % faster with the legacy emitters (an SG2Loc
    filter round 3.2 -> 2.6 s, the single-scale M2Loc query 4.0 -> 2.4 s), and the SG2Loc
    filter's three steps at the paper's scale another 16-22 % faster at optimization level 1
    (8.8 -> 7.4 s, 12.0 -> 9.4 s), running as fast (1.35 s per frame both ways) with
    bit-identical poses (benchmarks/results/startup_cpu.md). The filter rounds run as fast;
    the M2Loc query with three scales runs 20-30 % slower (paired reductions such as ``argmax``
    run ~2x slower with these emitters; the greedy clique loops avoid it), so the LiDAR commands
    do not use them, except for the query programs of one scale (:func:`legacy_emitter_options`;
    benchmarks/results/startup_cpu.md). Not the default either: the two
    emitters contract some fused float32 multiply-adds differently, so results can differ in the
    last bits (the SG2Loc rounds' and the M2Loc query's outputs were bit-identical in our
    comparisons; the JAX ray-triangle kernel's ``t`` moved by up to 5e-5, relative, on 9 % of
    random rays). In a notebook or script, call it before importing jax, or set the flag
    yourself. Returns whether it did.
    """
    if "jax" in sys.modules or "XLA_FLAGS" in os.environ or not _jaxlib_has_legacy_emitters():
        return False
    os.environ["XLA_FLAGS"] = FAST_COMPILATION_FLAG
    return True


def _jaxlib_has_legacy_emitters() -> bool:
    """Whether the installed jaxlib is one of :data:`FAST_COMPILATION_JAXLIB`."""
    release = _jaxlib_release()
    low, high = FAST_COMPILATION_JAXLIB
    return release is not None and low <= release <= high


@functools.cache
def _jaxlib_release() -> tuple[int, ...] | None:
    """(major, minor) of the installed jaxlib, None where unknown (read once: the query path
    asks on every call)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return tuple(int(part) for part in version("jaxlib").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return None


def legacy_emitter_options() -> dict[str, bool]:
    """The ``compiler_options`` that compile one program with XLA:CPU's legacy fusion emitters
    (:func:`prefer_fast_compilation` for a single program: ``{"xla_cpu_use_fusion_emitters":
    False}``), or ``{}`` where they do not apply: another backend, or a jaxlib outside
    :data:`FAST_COMPILATION_JAXLIB` (XLA refuses an option it does not know).

    For a program that compiles much faster with them and runs as fast, chosen by measurement
    (:func:`cached_call`'s ``compiler_options``; the M2Loc query of a small consistency graph).
    """
    import jax

    if jax.default_backend() != "cpu" or not _jaxlib_has_legacy_emitters():
        return {}
    return {LEGACY_EMITTER_OPTION: False}


def default_cache_dir() -> Path:
    """``$JAXLOC_CACHE_DIR``, else ``<user cache folder>/jaxloc/xla`` (platformdirs)."""
    if os.environ.get(ENV_DIR):
        return Path(os.environ[ENV_DIR]).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("jaxloc")) / "xla"


def enable_compilation_cache(
    path: str | os.PathLike | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    min_compile_time_s: float = 0.0,
) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`default_cache_dir`).

    Args:
        path: the cache folder (created if missing).
        max_bytes: the folder's size bound (JAX evicts the least recently used entries); -1 for
            no bound.
        min_compile_time_s: programs that compile faster than this are not cached (0: all; a
            warm start then loads every program instead of compiling the small ones).

    Returns:
        The folder in use, or None when :data:`ENV_OFF` turns the cache off (nothing changes).
    """
    if cache_disabled():
        return None
    import jax

    folder = Path(path).expanduser() if path is not None else default_cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", int(max_bytes))
    _PROGRAMS["folder"] = folder
    return folder


def cache_size(path: str | os.PathLike | None = None) -> tuple[int, int]:
    """(files, bytes) in the cache folder (0, 0 when it does not exist)."""
    folder = Path(path) if path is not None else default_cache_dir()
    if not folder.is_dir():
        return 0, 0
    files = [p for p in folder.rglob("*") if p.is_file()]
    return len(files), sum(p.stat().st_size for p in files)


def clear_compilation_cache(path: str | os.PathLike | None = None) -> int:
    """Delete every file of the cache folder; returns how many (programs compile again)."""
    folder = Path(path) if path is not None else default_cache_dir()
    if not folder.is_dir():
        return 0
    count = 0
    for file in folder.rglob("*"):
        if file.is_file():
            file.unlink()
            count += 1
    return count


# ------------------------------------------------------------------ traced programs, kept on disk


def _source_digest() -> str:
    """A hash of jaxloc's own source files: a stored program belongs to the code that traced it."""
    if "source" not in _PROGRAMS:
        digest = hashlib.sha256()
        for path in sorted(Path(__file__).parent.rglob("*.py")):
            digest.update(path.read_bytes())
        _PROGRAMS["source"] = digest.hexdigest()
    return _PROGRAMS["source"]


def _export(fn, leaves):
    """``jax.export`` of ``fn``, allowing the custom calls (LAPACK's, on CPU) that export refuses
    by default for want of a cross-version compatibility guarantee: a stored program is only ever
    loaded by the same JAX and jaxlib versions (they are part of its key)."""
    import re

    import jax.export

    try:
        return jax.export.export(fn)(*leaves)
    except ValueError as error:
        targets = sorted(set(re.findall(r"custom_call @(\w+)\(", str(error))))
        if not targets:
            raise
    allowed = [jax.export.DisabledSafetyCheck.custom_call(target) for target in targets]
    return jax.export.export(fn, disabled_checks=allowed)(*leaves)


def cache_enabled() -> bool:
    """Whether :func:`enable_compilation_cache` turned the cache on in this process."""
    return "folder" in _PROGRAMS and not cache_disabled()


def cache_entry(kind: str, suffix: str, *parts) -> Path | None:
    """The path (in ``<cache folder>/<kind>/``) of a file that keeps a value computed from
    ``parts`` (numpy arrays, keyed by dtype, shape and bytes; anything else by its ``repr``), or
    None when the cache is off. The key also covers jaxloc's source files, so a value computed
    by other code is never served. The caller writes the file atomically and validates what it
    reads back (a damaged file must cost only a recomputation)."""
    if not cache_enabled():
        return None
    import numpy as np

    digest = hashlib.sha256(_source_digest().encode())
    for part in parts:
        if isinstance(part, np.ndarray):
            digest.update(f"{part.dtype.str}{part.shape}".encode())
            digest.update(np.ascontiguousarray(part).tobytes())
        else:
            digest.update(repr(part).encode())
    return _PROGRAMS["folder"] / kind / f"{digest.hexdigest()[:32]}{suffix}"


def _is_dynamic(value) -> bool:
    """An argument leaf that is traced: an array, or a ``jax.ShapeDtypeStruct`` standing for one."""
    import equinox as eqx
    import jax

    return eqx.is_array(value) or isinstance(value, jax.ShapeDtypeStruct)


def _program(name: str, fn, args):
    """``(key, exported, leaves)`` of ``fn(*args)``: the exported program of its key (loaded from
    the cache folder, or traced and stored now) and the flat array (or shape) leaves of ``args``."""
    import equinox as eqx
    import jax
    import jax.export

    dynamic, static = eqx.partition(args, _is_dynamic)
    leaves, treedef = jax.tree.flatten(dynamic)
    spec = [(tuple(x.shape), str(x.dtype)) for x in leaves]
    device = jax.devices()[0]
    text = repr((name, jax.__version__, jax.lib.__version__, device.platform, device.device_kind,
                 _source_digest(), str(treedef), spec, static))  # fmt: skip
    key = hashlib.sha256(text.encode()).hexdigest()[:32]
    exported = _PROGRAMS.get(key)
    path = _PROGRAMS["folder"] / "programs" / f"{name}-{key}.jaxexport"
    if exported is None and path.is_file():
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # noqa: BLE001 - a damaged file: trace again
            exported = None
        if exported is not None and [(a.shape, str(a.dtype)) for a in exported.in_avals] != spec:
            exported = None  # another program's file under this name: trace again
    if exported is None:

        def flat(*values):
            call_args = eqx.combine(jax.tree.unflatten(treedef, values), static)
            return tuple(jax.tree.leaves(fn(*call_args)))

        exported = _export(jax.jit(flat), leaves)
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{os.getpid()}")
        temporary.write_bytes(exported.serialize())
        os.replace(temporary, path)  # atomic: a reader sees the old file or the whole new one
    _PROGRAMS[key] = exported
    return key, exported, leaves


def _compiled_key(key: str, options: dict) -> tuple:
    """The :data:`_PROGRAMS` key of the program ``key`` compiled with ``options``."""
    return ("compiled", key, *sorted(options.items()))


def _compile(exported, leaves, options: dict):
    """The compiled program of ``exported`` for arguments shaped like ``leaves``, with XLA
    compile ``options`` (through JAX's persistent cache, whose key covers them: the same lowering
    whether the leaves are arrays or shapes)."""
    import jax

    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    return jax.jit(exported.call).lower(*shapes).compile(options or None)


def prepare_call(name: str, fn, *args, compiler_options: dict | None = None) -> tuple | None:
    """Trace ``fn(*args)`` now and compile it in a background thread, for a later
    :func:`cached_call` with arguments of the same shapes (and equal static parts) to find ready.

    ``args`` and ``compiler_options`` are as :func:`cached_call`'s, with
    ``jax.ShapeDtypeStruct`` leaves allowed in place of arrays: a caller that knows the shapes
    before it has the values (a map's size before it is described) overlaps XLA's compilation
    (C++, without the GIL) with that work. The compilation takes both cores while it runs. Without
    the cache, nothing is done (``fn`` then compiles at its first call, as usual).

    Returns:
        The shapes of ``fn``'s output leaves (a tuple of ``jax.ShapeDtypeStruct``, in
        ``jax.tree.leaves`` order, to chain a program that takes them), None without the cache.
    """
    if not cache_enabled():
        return None
    from concurrent.futures import ThreadPoolExecutor

    import jax

    key, exported, leaves = _program(name, fn, args)
    options = dict(compiler_options or {})
    compiled_key = _compiled_key(key, options)
    if compiled_key not in _PROGRAMS:
        if "compiler" not in _PROGRAMS:
            _PROGRAMS["compiler"] = ThreadPoolExecutor(1, thread_name_prefix="jaxloc-compile")
        _PROGRAMS[compiled_key] = _PROGRAMS["compiler"].submit(_compile, exported, leaves, options)
    return tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.out_avals)


def cached_call(name: str, fn, rebuild, *args, compiler_options: dict | None = None):
    """``fn(*args)`` through a traced program kept in the cache folder (``jax.export``).

    With the compilation cache on, the first call of a key traces ``fn`` once and stores the
    exported program (``programs/<name>-<key>.jaxexport``); a later process loads it instead of
    tracing again, and JAX's persistent cache then loads its compiled form: a warm start neither
    traces nor compiles. The key covers the JAX and jaxlib versions, the backend, jaxloc's source
    files, the arguments' tree structure, shapes and dtypes and their static (non-array) parts.
    A program :func:`prepare_call` compiles in the background is waited for, not compiled again.
    Without the cache, or for a file that does not load, ``fn`` is called (and traced) as usual.

    Args:
        name: the program's name (file names and errors).
        fn: a function of pytrees of arrays and static values (jitted or not).
        rebuild: builds ``fn``'s output from the flat tuple of its array leaves, in
            ``jax.tree.leaves`` order (e.g. ``tuple``, or an ``eqx.Module`` class's constructor).
        args: the arguments.
        compiler_options: XLA compile options of the program (e.g.
            :func:`legacy_emitter_options`; part of the persistent cache's key). Without the
            cache they do not apply: ``fn`` compiles as it would anyway.
    """
    if not cache_enabled():
        return fn(*args)
    from concurrent.futures import Future

    key, exported, leaves = _program(name, fn, args)
    options = dict(compiler_options or {})
    compiled_key = _compiled_key(key, options)
    compiled = _PROGRAMS.get(compiled_key)
    if compiled is None:
        compiled = _PROGRAMS[compiled_key] = _compile(exported, leaves, options)
    elif isinstance(compiled, Future):  # prepare_call's, compiling or done
        compiled = _PROGRAMS[compiled_key] = compiled.result()
    return rebuild(compiled(*leaves))
