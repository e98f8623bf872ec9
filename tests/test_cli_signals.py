"""SIGINT and SIGTERM at every phase of `piezojax fit` (imports, initial values, fitting, writing the figures):
exit 130 / 143, no crash, no traceback, the output folder complete or absent, and no temporary left behind.

Each trial is a real process; the phase is recognised from the progress lines on stderr, and the signal comes after
a random delay inside it. The processes share a persistent compilation cache, so only the first compiles.
"""

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import fitting

pytestmark = pytest.mark.slow

CONFIG = '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[fit]\nmax_steps = 3\n'
FILES = ("result.json", "model.eqx", "config.toml", "report.txt", ".piezojax")

# phase -> (stderr text that starts it, delay range after it [s], trials)
PHASES = {
    "imports": (None, (0.05, 1.5), 4),
    "initial values": ("initial values from the data", (0.0, 0.3), 3),
    "fitting": ("Levenberg", (0.0, 2.0), 3),
    "figures": ("writing", (0.0, 0.6), 10),  # each trial is a whole process (~7 s): the suite's budget
}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("signals")
    for i in range(4):
        t = np.arange(400) * 1e-3
        v = (20 + 5 * i) * np.sin(2 * np.pi * 4 * t)
        fitting.save_experiment(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=1e-8 * v + 1e-9 * abs(v)),
                                d / f"r{i}.csv")
    (d / "m.toml").write_text(CONFIG)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "JAX_COMPILATION_CACHE_DIR": str(d / "jax-cache"),
           "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0", "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0"}
    return d, env


def _trial(d, env, out, phase, signum, rng):
    marker, (lo, hi), _ = PHASES[phase]
    cmd = [sys.executable, "-m", "fitting.cli", "fit", str(d / "m.toml"), *(str(d / f"r{i}.csv") for i in range(4)),
           "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=d)
    seen = b""
    try:
        if marker is not None:
            deadline = time.monotonic() + 300
            while marker.encode() not in seen:
                chunk = os.read(proc.stderr.fileno(), 4096)
                if not chunk:
                    break  # ended before the phase: judged below like any other run
                seen += chunk
                assert time.monotonic() < deadline, seen.decode()
        time.sleep(rng.uniform(lo, hi))
        proc.send_signal(signum)
        _, rest = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, (seen + rest).decode(errors="replace")


@pytest.mark.parametrize("phase", list(PHASES))
def test_signals_at_every_phase(setup, phase):
    d, env = setup
    rng = random.Random(hash(phase) % 1000)
    outcomes = []
    for k in range(PHASES[phase][2]):
        signum = (signal.SIGINT, signal.SIGTERM)[k % 2]
        out = d / f"out_{phase.replace(' ', '_')}_{k}"
        rc, err = _trial(d, env, out, phase, signum, rng)
        where = f"{phase} trial {k} ({signal.Signals(signum).name}): rc {rc}\n{err}"
        if phase == "imports" and rc == -signum:
            # the signal came while the interpreter was still starting, before any project code (a loaded 2-core
            # machine can take longer than the shortest delay): the default action killed it, and nothing was written
            assert not out.exists() and not [p.name for p in d.iterdir() if ".tmp-" in p.name], where
            outcomes.append((128 + signum, False))
            continue
        assert rc in (0, 1, 128 + signum), where  # 0/1: it finished before the signal arrived
        for bad in ("Traceback", "Fatal Python error", "Exception ignored", "Segmentation"):
            assert bad not in err, where
        if out.exists():  # complete: every file, and a summary that says how it ended
            for name in FILES:
                assert (out / name).is_file(), where
            code = json.loads((out / "result.json").read_text())["code"]
            assert (code == "interrupted") == (rc == 128 + signum), where
        else:
            assert rc == 128 + signum, where
        assert not [p.name for p in d.iterdir() if ".tmp-" in p.name], where
        outcomes.append((rc, out.exists()))
    # the signal really landed in the phase: most trials were interrupted
    assert sum(rc >= 128 for rc, _ in outcomes) >= (len(outcomes) + 1) // 2, outcomes


def test_next_run_removes_what_a_killed_run_left(setup):
    d, env = setup
    out = d / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "fitting.cli", "fit", str(d / "m.toml"), str(d / "r0.csv"),
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=d)
    seen = b""
    while b"initial values" not in seen:
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, seen.decode()
        seen += chunk
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    left = [p for p in d.iterdir() if p.name.startswith(".killed.tmp-")]
    assert left  # kill -9 cannot be handled: the temporary folder stays
    r = subprocess.run([sys.executable, "-m", "fitting.cli", "fit", str(d / "m.toml"), str(d / "r0.csv"), "--out",
                        str(out), "--no-figures", "--quiet"], capture_output=True, text=True, env=env, cwd=d,
                       timeout=300)
    assert r.returncode in (0, 1), r.stderr
    assert not any(p.exists() for p in left)
    assert (out / "result.json").is_file()
