import atexit
import os
import shutil
import subprocess
import sys
import tempfile

import jax
import pytest
from hypothesis import HealthCheck, settings

from piezojax import enable_compilation_cache, enable_fast_cpu_scans

# One persistent compilation cache per test run, in a temporary folder removed at its end: a program compiles once
# per run instead of once per test module (the modules drop their compiled programs, below), per fitted closure and
# per command line the tests start. The test workers and those command lines inherit the folder through
# $PIEZOJAX_CACHE_DIR. `PIEZOJAX_CACHE_DIR=off` compiles everything afresh; a folder named there is used and kept.
# (tests/test_compilation_cache.py checks the cache itself with folders of its own.)
if "PIEZOJAX_CACHE_DIR" not in os.environ:
    _run_cache = tempfile.mkdtemp(prefix="piezojax-tests-xla-")
    os.environ["PIEZOJAX_CACHE_DIR"] = _run_cache
    atexit.register(shutil.rmtree, _run_cache, ignore_errors=True)
enable_compilation_cache()
# The suite is mostly compilation. XLA:CPU's classic loop emitters compile it in about two thirds of the time its
# default fusion emitters take (measured: notebook 03 32-37 s -> 22 s of compiling, `experiments.quant2009 --quick` 32
# -> 18 s), and the compiled fits ran as fast in `experiments.bench_calibration` (within its run-to-run spread). The
# flag goes into $XLA_FLAGS before any computation, so the test workers and the command lines the tests start inherit
# it. A jaxlib that does not know the flag would abort on it, so it is tried in a child process first; an $XLA_FLAGS
# that already names the flag (e.g. `=true`, to test the default emitters) is left as it is.
_EMITTERS = "xla_cpu_use_fusion_emitters"
if _EMITTERS not in os.environ.get("XLA_FLAGS", "") and "PIEZOJAX_TESTS_EMITTERS_TRIED" not in os.environ:
    _flags = f"{os.environ.get('XLA_FLAGS', '')} --{_EMITTERS}=false".strip()
    try:
        _accepted = subprocess.run(
            [sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(2).sum().block_until_ready()"],
            env={**os.environ, "XLA_FLAGS": _flags, "JAX_PLATFORMS": "cpu"}, capture_output=True, timeout=120,
        ).returncode == 0
    except (OSError, subprocess.SubprocessError):  # no answer: the default emitters
        _accepted = False
    if _accepted:
        os.environ["XLA_FLAGS"] = _flags
    os.environ["PIEZOJAX_TESTS_EMITTERS_TRIED"] = "1"  # once per run, not again in each worker
# Before any computation: long scan bodies (vmap, jacfwd) compile to fused loops (see piezojax/_config.py).
enable_fast_cpu_scans()
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

settings.register_profile(
    "default",
    deadline=None,
    max_examples=40,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "ci",
    deadline=None,
    max_examples=25,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile("ci" if os.environ.get("CI") else "default")


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module. Each XLA:CPU executable holds about 3 memory mappings;
    a test worker that compiles ~20000 programs over the suite reaches the kernel's limit (`vm.max_map_count`,
    65530) and XLA aborts or segfaults in its next compilation (seen in CI at 94 % of the suite)."""
    yield
    jax.clear_caches()


@pytest.fixture
def rng():
    import numpy as np

    return np.random.default_rng(12345)
