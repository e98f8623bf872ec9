"""The persistent compilation cache (`pj.enable_compilation_cache`): a second process with the same shapes loads
the compiled programs instead of compiling them; the cache can be disabled and never stops a computation."""

import os
import subprocess
import sys
import textwrap

import pytest

import piezojax as pj

SCRIPT = textwrap.dedent("""
    import os, sys, time
    from jax._src import monitoring
    hits = []
    monitoring.register_event_listener(lambda event, **kw: hits.append(event.endswith("/cache_hits")))
    import piezojax as pj
    folder = pj.enable_compilation_cache()
    import jax, jax.numpy as jnp, equinox as eqx
    jax.config.update("jax_enable_x64", True)
    act = pj.Actuator(pj.PrandtlIshlinskii(jnp.full(6, 0.02), jnp.linspace(0.0, 30.0, 6), w0=0.1),
                      pj.KelvinVoigtCreep(jnp.array([50.0]), jnp.array([0.05]), k0=None),
                      pj.StableTransferFunction(1e-6, omega=jnp.array([2e3]), zeta=jnp.array([0.1])))
    v = jnp.linspace(0.0, 40.0, 800)
    t0 = time.perf_counter()
    jac = eqx.filter_jit(jax.jacfwd(lambda a: a.simulate(v, 1e-4).displacement))(act)
    seconds = time.perf_counter() - t0
    files = sum(len(f) for _, _, f in os.walk(folder)) if folder else -1
    print(folder, files, float(jnp.sum(jac.hysteresis.weights)), sum(hits))
""")


def _run(env_dir):
    env = dict(os.environ, PIEZOJAX_CACHE_DIR=env_dir)
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    folder, files, value, hits = out.stdout.split()
    return folder, int(files), float(value), int(hits)


def test_a_second_process_loads_the_compiled_programs(tmp_path):
    cache = str(tmp_path / "xla")
    folder, files, value, hits = _run(cache)
    assert folder == cache and files > 0 and hits < files  # the programs were stored (a few reused at once)
    again, files_again, value_again, hits_again = _run(cache)
    # loaded (JAX may compile an odd small program anew, e.g. one keyed on the process)
    assert hits_again >= 0.9 * files > hits and files_again <= files + 0.1 * files
    assert value_again == value
    off, files_off, value_off, _ = _run("off")
    assert off == "None" and files_off == -1 and value_off == value


def test_the_cache_is_opt_in_and_never_fatal(tmp_path, monkeypatch):
    import jax

    before = jax.config.jax_compilation_cache_dir
    monkeypatch.setenv("PIEZOJAX_CACHE_DIR", "off")
    assert pj.enable_compilation_cache() is None and jax.config.jax_compilation_cache_dir == before
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.warns(UserWarning, match="cannot be created"):
        assert pj.enable_compilation_cache(blocker / "xla") is None
    assert jax.config.jax_compilation_cache_dir == before
