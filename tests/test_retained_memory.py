"""`pj.retain_freed_memory` (called by `pj.enable_fast_cpu_scans`): freed multi-megabyte blocks stay in the process,
so allocating the same buffers again (as every call of a compiled function does) faults no pages in."""

import platform
import subprocess
import sys
import textwrap

import pytest

import piezojax as pj

_GLIBC = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"

# In a fresh process (the tests' own heaps are already retained by conftest): minor page faults of three rounds of
# allocating, filling and freeing eight 8 MiB arrays, first with glibc's defaults (64 MiB freed at once is more than
# its dynamic trim threshold, so the heap is trimmed and faulted in again), then with the memory retained.
SCRIPT = textwrap.dedent("""
    import resource
    import numpy as np

    def faults(rounds=3):
        def one():
            arrays = [np.ones(1 << 20) for _ in range(8)]
            del arrays
        one()
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(rounds):
            one()
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    fresh = faults()
    import piezojax
    ok = piezojax.retain_freed_memory()
    print(fresh, faults(), ok)
""")


@pytest.mark.skipif(not _GLIBC, reason="the settings are glibc's (mallopt)")
def test_freed_blocks_are_reused_without_page_faults():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    fresh, retained, ok = out.stdout.split()
    assert ok == "True"
    assert int(fresh) >= 100, out.stdout  # 3 x 64 MiB faulted in (12k faults here: numpy asks for huge pages)
    assert int(retained) <= int(fresh) // 20, out.stdout


def test_enable_fast_cpu_scans_retains_memory_and_keeps_its_flag(monkeypatch):
    calls = []
    monkeypatch.setattr(pj._config, "retain_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.setenv("XLA_FLAGS", pj._config.FAST_CPU_SCAN_FLAG)
    assert pj.enable_fast_cpu_scans()  # the flag is already there (the tests' conftest set it)
    assert calls == [1]
    assert pj.enable_fast_cpu_scans(retain_memory=False)
    assert calls == [1]


@pytest.mark.skipif(not _GLIBC, reason="the settings are glibc's (mallopt)")
def test_released_memory_faults_in_again():
    # retained, then released: the same rounds fault their pages in again, as with glibc's defaults
    script = SCRIPT.replace("print(fresh, faults(), ok)",
                            "retained = faults()\nreleased = piezojax.release_freed_memory()\n"
                            "print(fresh, retained, faults(), ok, released)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    fresh, retained, again, ok, released = out.stdout.split()
    assert ok == released == "True"
    assert int(retained) <= int(fresh) // 20, out.stdout
    assert int(again) >= int(fresh) // 2, out.stdout


def test_fit_command_releases_memory_for_long_records_only(monkeypatch):
    # the command line returns the retained memory when the longest record's Jacobian is above glibc's threshold
    # for mapping blocks apart (on 1e6 samples retaining raised the peak from 1.70 to 2.24 GB for no speed)
    import types

    from fitting import _calibrate as pipeline

    calls = []
    monkeypatch.setattr(pj, "release_freed_memory", lambda: calls.append(1) or True)
    config = types.SimpleNamespace(outputs=("displacement",))

    def records(*lengths):
        return [types.SimpleNamespace(n=n) for n in lengths]

    limit = pipeline.RETAIN_MEMORY_BELOW // (8 * 24)  # samples of a 24-parameter fit's record at the limit
    assert pipeline.release_memory_if_long(config, records(1000, limit), 24) is False
    assert calls == []
    assert pipeline.release_memory_if_long(config, records(1000, limit + 1), 24) is True
    assert pipeline.release_memory_if_long(config, records(1_000_000), 24) is True
    two = types.SimpleNamespace(outputs=("displacement", "charge"))
    assert pipeline.release_memory_if_long(two, records(limit // 2 + 1), 24) is True  # two channels: twice the rows
    assert calls == [1, 1, 1]
