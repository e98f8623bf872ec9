"""Opt-in performance settings: XLA:CPU's loop compilation, and sequential or parallel-in-time recurrences. Nothing
here runs on import."""

import contextlib
import os
import sys
import warnings
from collections.abc import Iterator

from ._checks import PiezojaxValueError

# XLA:CPU compiles a `lax.scan`/while loop into one fused native loop only when its body touches less than
# `xla_cpu_small_while_loop_byte_threshold` bytes per iteration (default 1024). Above that every operation of the body
# is dispatched separately, at hundreds of ns per operation per sample. Batched (vmap) simulation and forward-mode
# Jacobians of hysteresis scans exceed 1 KiB per step, and measured 7–12x faster with the threshold raised
# (`python -m experiments.bench_hysteresis`). Numbers are unchanged: it only changes how the loop is compiled.
FAST_CPU_SCAN_FLAG = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000"


# glibc's malloc hands large freed blocks back to the kernel (`munmap`, heap trimming), so every call of a compiled
# function that allocates the same multi-megabyte buffers (scan outputs, Jacobian columns) faults its pages in again:
# the paper 001 observer's Jacobian (`python -m experiments.bench_observer`, 24000 samples x 40 directions) spent
# about a third of its time in page faults (277k minor faults per run against 145k with the settings below). Keeping
# freed memory in the process's heaps removes them. mallopt parameters (glibc <malloc.h>) and the values used:
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
_RETAINED_MALLOC = (
    (_M_MMAP_THRESHOLD, 32 << 20),  # blocks up to 32 MiB (64-bit glibc's maximum) from the heaps, not fresh mmaps
    (_M_TRIM_THRESHOLD, 1 << 30),  # the main heap is trimmed only above 1 GiB of free memory at its top
    (_M_TOP_PAD, 256 << 20),  # threads' heaps (64 MiB each) are never shrunk, and the main heap grows in 256 MiB
)
# The same from the shell, before the process starts (glibc tunables, one word):
# GLIBC_TUNABLES=glibc.malloc.mmap_threshold=33554432:glibc.malloc.trim_threshold=1073741824:
#                glibc.malloc.top_pad=268435456


def retain_freed_memory() -> bool:
    """Keep freed memory in the process (glibc `mallopt`) so repeated calls do not fault their buffers in again.

    Process-wide, until `release_freed_memory`: the price is a resident size that stays near the peak of every
    allocator heap. Call it before JAX starts its threads (`enable_fast_cpu_scans` does): called after JAX had
    compiled and run the 150 V fit's starts, the fit's steps took 20.7 s against 15.6 s called first (21.5 s never
    called). Does nothing and returns False where the C library is not glibc on Linux.

    **Returns:** True if every setting was accepted (each is tried).
    """
    return _mallopt(_RETAINED_MALLOC)


# glibc's defaults (<malloc.h>: 128 KiB each), which `release_freed_memory` restores; the mmap threshold then stays at
# 128 KiB instead of adapting to the blocks freed
_DEFAULT_MALLOC = ((_M_MMAP_THRESHOLD, 128 << 10), (_M_TRIM_THRESHOLD, 128 << 10), (_M_TOP_PAD, 128 << 10))


def _mallopt(settings) -> bool:
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # no mallopt in the process (a C library other than glibc)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    accepted = [mallopt(param, value) == 1 for param, value in settings]
    return all(accepted)


def release_freed_memory() -> bool:
    """Undo `retain_freed_memory`: glibc's default thresholds again (128 KiB; the threshold for mapping a block apart
    then stays fixed instead of adapting), and the free memory at the tops of its heaps returned to the system
    (`malloc_trim`).

    For long records, where retained memory costs more than it saves: measured on 2 cores, `piezojax fit` of one
    1e6-sample record (24 parameters) peaked at 2.24 GB resident with the memory retained throughout (95 s, of
    which 60 s Levenberg–Marquardt steps), 1.60-1.62 GB retained until the records were read and released then
    (101-106 s; 60-65 s), and 1.70 GB never retained (95 s; 59-61 s). Retaining only once the records are known to
    be short did not give the speed of retaining from the start (the 150 V fit's steps: 20.7 s against 15.6 s),
    hence retain early and release when the records turn out long.
    Does nothing and returns False where the C library is not glibc on Linux.

    **Returns:** True if every setting was accepted.
    """
    ok = _mallopt(_DEFAULT_MALLOC)
    if ok:
        import ctypes

        trim = ctypes.CDLL(None).malloc_trim
        trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
        trim(0)
    return ok


def enable_fast_cpu_scans(retain_memory: bool = True) -> bool:
    """Raise XLA:CPU's small-loop threshold so long `lax.scan` bodies compile to a fused loop, and (unless
    `retain_memory=False`) keep freed memory in the process (`retain_freed_memory`) so the loops' output buffers are
    not faulted in on every call.

    Appends `FAST_CPU_SCAN_FLAG` to the `XLA_FLAGS` environment variable. The flag takes effect only if this is called
    before JAX initialises its backends (before the first computation); afterwards it warns, and only the memory
    retention (if asked for) takes effect. The flag alone is, in the shell,
    `export XLA_FLAGS=--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000`.
    The command-line tools, experiments and tests call it; importing piezojax never does.

    **Returns:** True if the flag is (now) in `XLA_FLAGS` before backend initialisation, else False.
    """
    if retain_memory:
        retain_freed_memory()
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_small_while_loop_byte_threshold" in flags:
        return True
    try:
        from jax._src import xla_bridge

        initialised = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # pragma: no cover - private API moved
        initialised = False
    if initialised:
        warnings.warn(
            "enable_fast_cpu_scans() was called after JAX initialised its backends; its loop flag has no effect. "
            "Call it before the first JAX computation, or set XLA_FLAGS in the shell.",
            stacklevel=2,
        )
        return False
    if "--xla_backend_extra_options=" in flags:
        # XLA accepts one extra-options list: extend it rather than adding a second flag.
        flags = flags.replace(
            "--xla_backend_extra_options=",
            "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000,",
            1,
        )
    else:
        flags = f"{flags} {FAST_CPU_SCAN_FLAG}".strip()
    os.environ["XLA_FLAGS"] = flags
    return True


# Parallel-in-time scans: the exact play/stop operators (a clamp monoid), the first-order lags and the discrete
# linear systems (affine maps) can run as `jax.lax.associative_scan` (log2(time) levels of elementwise work) instead of
# `lax.scan` (one dependent step per sample). On a GPU a sequential scan costs a few kernel launches per sample
# whatever the batch; on a CPU the associative form does several times the arithmetic and is slower (measured by
# `experiments.bench_fleet`). The choice is made when a function is traced.
PARALLEL_SCAN_MODES = ("auto", "always", "never")
PARALLEL_MIN_LENGTH = 1024
_parallel_scans = "auto"


def set_parallel_scans(mode: str) -> str:
    """Choose how long recurrences run: `"auto"` (default: parallel-in-time on an accelerator for signals of at
    least `PARALLEL_MIN_LENGTH` samples, sequential on the CPU), `"always"` or `"never"`.

    Affects the exact play/stop operators (and so PI), the first-order lags of the creep blocks and the discrete
    linear systems (dynamics), forward and derivatives. Both forms compute the same recursion; they differ by
    rounding (about 1e-15 relative). Decided when a function is traced: call it before the first `jit` of a model
    (a function already compiled keeps its form). **Returns:** the previous mode.
    """
    global _parallel_scans
    if mode not in PARALLEL_SCAN_MODES:
        raise PiezojaxValueError(f"`mode` must be one of {PARALLEL_SCAN_MODES}, got {mode!r}")
    previous, _parallel_scans = _parallel_scans, mode
    return previous


def scan_mode() -> str:
    """The current mode of `set_parallel_scans`."""
    return _parallel_scans


@contextlib.contextmanager
def parallel_scans(mode: str) -> Iterator[None]:
    """`set_parallel_scans(mode)` for the duration of a `with` block (the previous mode restored after it)."""
    previous = set_parallel_scans(mode)
    try:
        yield
    finally:
        set_parallel_scans(previous)


def use_parallel_scan(length: int) -> bool:
    """Whether a recurrence over `length` samples runs as an associative scan (see `set_parallel_scans`)."""
    if _parallel_scans == "never":
        return False
    if _parallel_scans == "always":
        return True
    import jax

    return jax.default_backend() != "cpu" and length >= PARALLEL_MIN_LENGTH


# The persistent compilation cache: compiled XLA programs kept on disk, so that a new process with the same shapes
# (a second `piezojax fit` of the same records' layout) loads them instead of compiling.
CACHE_ENV = "PIEZOJAX_CACHE_DIR"


def default_cache_dir() -> str | None:
    """`$PIEZOJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/piezojax/xla`, else `~/.cache/piezojax/xla`; None when
    `$PIEZOJAX_CACHE_DIR` is `off`, `0` or empty (the cache disabled)."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "false", "no") else value
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "piezojax", "xla")


def enable_compilation_cache(path: str | os.PathLike | None = None, min_compile_seconds: float = 0.0) -> str | None:
    """Keep compiled XLA programs on disk (JAX's persistent compilation cache), so that a later process running the
    same computations with the same shapes skips their compilation.

    The command line (`piezojax fit`, `predict`, `simulate`) and the experiments call it; a library user opts in by
    calling it once (best before the first computation). Nothing is cached otherwise. Programs that compiled in
    under `min_compile_seconds` are not stored. Programs with host callbacks (an `eqx.error_if` traced to raise,
    `jax.debug.print`) are never stored: `fitting` traces its residuals with `refusals_as_nan` for this reason.
    A program is keyed by its computation, shapes, dtypes and the backend, so new data of the same layout (record
    lengths, channels, model structure) reuse it, while a change of JAX version or machine simply compiles anew.
    The folder may be deleted at any time.

    **Arguments:**

    - `path`: the cache folder; default `default_cache_dir()` (`$PIEZOJAX_CACHE_DIR`, else
      `~/.cache/piezojax/xla`; `PIEZOJAX_CACHE_DIR=off` disables the cache).
    - `min_compile_seconds`: programs that compiled faster are not stored (default 0: all of them; JAX's own
      default is 1 s, but a fit also compiles dozens of small programs of 0.01–0.1 s, which add up to seconds).

    **Returns:** the folder used, or None when the cache is disabled or the folder cannot be created (with a warning
    then: computations run as usual, compiled in each process).
    """
    import jax

    folder = default_cache_dir() if path is None else os.fspath(path)
    if folder is None:
        return None
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        warnings.warn(f"the compilation cache folder {folder!r} cannot be created ({e}); compiling in every process",
                      stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    try:  # JAX decides whether to use the cache at its first compilation: decide again with this folder
        from jax.experimental.compilation_cache import compilation_cache

        compilation_cache.reset_cache()
    except (ImportError, AttributeError):  # pragma: no cover - moved in a later JAX: the folder applies from now on
        pass
    _replace_unreadable_entries()
    return folder


class _ReplacingCache:
    """JAX's file cache, except that a program compiled under a key already on disk replaces that entry (JAX keeps
    the old one): an entry is compiled anew only when it could not be read (damaged, or written by another build),
    so without this a damaged entry would be compiled again in every process and never repaired. The new entry is
    written beside the old one and renamed over it, so a concurrent reader sees one or the other."""

    def __init__(self, base):
        self._base = base

    def get(self, key: str):
        return self._base.get(key)

    def put(self, key: str, value: bytes) -> None:
        entry = self._base.path / f"{key}{self._suffix}"
        if not entry.exists():
            self._base.put(key, value)
            return
        temporary = entry.with_name(f".{entry.name}.tmp-{os.getpid()}")
        try:
            temporary.write_bytes(value)
            os.replace(temporary, entry)
        except OSError as e:
            warnings.warn(f"the compilation cache entry {str(entry)!r} could not be read and cannot be replaced "
                          f"({e}); delete it", stacklevel=2)
            with contextlib.suppress(OSError):
                temporary.unlink()

    def __getattr__(self, name):  # everything else (`path`, eviction, ...) is the file cache's
        return getattr(self._base, name)


def _replace_unreadable_entries() -> None:
    """Put `_ReplacingCache` around the file cache JAX has just been told to use (left as it is where JAX's cache is
    built differently, e.g. a remote one: there a damaged entry stays until the folder is deleted)."""
    try:
        from jax._src import compilation_cache, lru_cache

        compilation_cache._initialize_cache()
        if isinstance(compilation_cache._cache, lru_cache.LRUCache):
            _ReplacingCache._suffix = lru_cache._CACHE_SUFFIX
            compilation_cache._cache = _ReplacingCache(compilation_cache._cache)
    except (ImportError, AttributeError):  # pragma: no cover - JAX's cache moved: entries are kept as JAX keeps them
        pass
