"""Opt-in performance settings for XLA:CPU. Nothing here runs on import."""

import os
import warnings

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
