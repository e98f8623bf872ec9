"""Opt-in performance settings: XLA:CPU's loop compilation, and sequential or parallel-in-time recurrences. Nothing
here runs on import."""

import contextlib
import os
import warnings
from collections.abc import Iterator

# XLA:CPU compiles a `lax.scan`/while loop into one fused native loop only when its body touches less than
# `xla_cpu_small_while_loop_byte_threshold` bytes per iteration (default 1024). Above that every operation of the body
# is dispatched separately, at hundreds of ns per operation per sample. Batched (vmap) simulation and forward-mode
# Jacobians of hysteresis scans exceed 1 KiB per step, and measured 7–12x faster with the threshold raised
# (`python -m experiments.bench_hysteresis`). Numbers are unchanged: it only changes how the loop is compiled.
FAST_CPU_SCAN_FLAG = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000"


def enable_fast_cpu_scans() -> bool:
    """Raise XLA:CPU's small-loop threshold so long `lax.scan` bodies compile to a fused loop.

    Appends `FAST_CPU_SCAN_FLAG` to the `XLA_FLAGS` environment variable. It takes effect only if called before JAX
    initialises its backends (before the first computation); afterwards it warns and does nothing. Equivalent to
    `export XLA_FLAGS=--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000` in the shell.
    The command-line tools, experiments and tests call it; importing piezojax never does.

    **Returns:** True if the flag is (now) in `XLA_FLAGS` before backend initialisation, else False.
    """
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
            "enable_fast_cpu_scans() was called after JAX initialised its backends; it has no effect. "
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
        from ._checks import PiezojaxValueError

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
