"""Table-driven robustness of the `piezojax` command line: every bad input is one line naming the culprit, exit 2,
and nothing is written or replaced.

Each row builds its arguments in a folder of small files (`bench`); the assertions are the same for all: the exit
status, one line `piezojax: error: ...` (or argparse's `piezojax CMD: error: ...`) containing every expected
fragment (the file, column, key or option at fault and what is allowed), no traceback, the output absent (or, if it
existed, unchanged) and no temporary left behind.
"""

import json
import shutil
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

import fitting
import piezojax as pj
from fitting.cli import main

DT = 1e-3
N = 300

PI = '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[fit]\nmax_steps = 2\n'
KNOWN = '[hysteresis]\nkind = "prandtl_ishlinskii"\nweights = [1e-9, 1e-9]\nthresholds = [1.0, 5.0]\nw0 = 1e-8\n'
OBSERVER = """\
[observer]
kind = "current_integration"
integrator_capacitance = 10e-9
reference_capacitance = 1.5e-9
leakage_resistance = 1e11
force_sensitivity = 1e-6
displacement_coefficient = -4e-3
stiffness = 150.0
"""


def _csv(path, header, cols, comments=""):
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(header), comments=comments)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A folder with good and bad data files, configurations, and one fitted folder (for `predict`)."""
    d = tmp_path_factory.mktemp("robust")
    t = np.arange(N) * DT
    v = 30 * np.sin(2 * np.pi * 3 * t)
    x = 1e-8 * v + 2e-9 * np.abs(v)
    h = ["t", "v_in", "displacement"]
    _csv(d / "ok.csv", h, [t, v, x])
    _csv(d / "ok2.csv", h, [t, 0.5 * v, 0.5 * x])
    _csv(d / "slow.csv", h, [2 * t, v, x])
    _csv(d / "tiny.csv", h, [t, v, 1e-200 * x])
    _csv(d / "denormal.csv", h, [t, 1e-310 * v, x])
    (d / "linked").symlink_to(d / "sub")
    (d / "dangling").symlink_to(d / "nowhere" / "deeper")
    (d / "loop").symlink_to(d / "loop")
    _csv(d / "nov.csv", ["t", "displacement"], [t, x])
    _csv(d / "inputonly.csv", ["t", "v_in"], [t, v])
    _csv(d / "not.csv", ["v_in", "displacement"], [v, x])
    _csv(d / "nan.csv", h, [t, v, np.where(np.arange(N) == 17, np.nan, x)])
    _csv(d / "inf.csv", h, [t, np.where(np.arange(N) == 5, np.inf, v), x])
    t2 = t.copy()
    t2[100:] += 0.4 * DT
    _csv(d / "gap.csv", h, [t2, v, x])
    _csv(d / "backwards.csv", h, [t[::-1], v, x])
    _csv(d / "dup.csv", ["t", "v_in", "v_in"], [t, v, v])
    (d / "empty.csv").write_text("")
    (d / "comments.csv").write_text("# only\n# comments\n")
    (d / "headeronly.csv").write_text("t,v_in,displacement\n")
    (d / "ragged.csv").write_text("t,v_in,displacement\n0,1,2\n0.001,2\n")
    (d / "word.csv").write_text("t,v_in,displacement\n0,1,2\n0.001,abc,3\n")
    _csv(d / "strain.csv", ["t", "v_in", "strain"], [t, v, x])
    _csv(d / "noheader.csv", h, [t, v, x], comments="# note: ")  # header names behind '# note:' do not match
    (d / "noheader.csv").write_text("\n".join((d / "noheader.csv").read_text().splitlines()[1:]))
    (d / "text.npz").write_text("t,v_in\n0,1\n")
    np.save(d / "array.npy", v)
    (d / "array.npy").rename(d / "array.npz")
    np.savez(d / "bool.npz", t=t, v_in=v > 0, displacement=x)
    np.savez(d / "complex.npz", t=t, v_in=v + 1j, displacement=x)
    np.savez(d / "twod.npz", t=t, v_in=np.stack([v, v, v]), displacement=x)
    np.savez(d / "unequal.npz", t=t, v_in=v[:-3], displacement=x)
    with h5py.File(d / "nov.h5", "w") as f:
        f["t"], f["displacement"] = t, x
    fitting.save_experiment(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=x), d / "trunc.h5")
    data = (d / "trunc.h5").read_bytes()
    (d / "trunc.h5").write_bytes(data[: len(data) // 3])
    (d / "text.mat").write_text("not a MATLAB file\n")
    (d / "data.txt").write_text("t,v_in\n0,1\n")
    (d / "adir.csv").mkdir()
    _csv(d / "index.csv", h, [np.arange(N, dtype=float), v, x])
    _csv(d / "huge.csv", h, [t, 1e305 * v, x])
    _csv(d / "short.csv", h, [t[:8], v[:8], x[:8]])
    _csv(d / "one.csv", h, [t[:1], v[:1], x[:1]])
    _csv(d / "flat.csv", h, [t, v, np.full(N, 3e-6)])
    _csv(d / "zero.csv", h, [t, np.zeros(N), x])
    _csv(d / "force.csv", ["t", "v_in", "force"], [t, v, 1e-3 * v])
    configs = {
        "pi.toml": PI,
        "known.toml": KNOWN,
        "observer.toml": OBSERVER,
        "observer_cp.toml": OBSERVER + "capacitance_p = 1.7e-9\n",
        "badtoml.toml": "[hysteresis\nkind = 1\n",
        "table.toml": PI + "[motor]\norder = 2\n",
        "key.toml": '[creep]\nkind = "kelvin_voigt"\ntau = [1.0]\n',
        "kind.toml": '[hysteresis]\nkind = "preisachh"\n',
        "nokind.toml": "[hysteresis]\nplays = 3\n",
        "plays_huge.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 99999999999999999\n',
        "plays_1000.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 1000\n',
        "plays0.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 0\n',
        "playsstr.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = "ten"\n',
        "thresholds101.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nthresholds = ['
        + ", ".join(str(float(i + 1)) for i in range(101)) + "]\n",
        "elements.toml": '[hysteresis]\nkind = "maxwell_slip"\nelements = 500\n',
        "creep_order.toml": '[creep]\nkind = "kelvin_voigt"\norder = 40\n',
        "substeps.toml": '[hysteresis]\nkind = "bouc_wen"\nmethod = "rk4"\nsubsteps = 100000\n',
        "substeps0.toml": '[hysteresis]\nkind = "bouc_wen"\nmethod = "rk4"\nsubsteps = 0\n',
        "maxsteps.toml": PI.replace("max_steps = 2", "max_steps = 10000000"),
        "maxsteps0.toml": PI.replace("max_steps = 2", "max_steps = 0"),
        "tlen.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 3\nthresholds = [1.0, 2.0]\n',
        "tdesc.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nthresholds = [2.0, 1.0]\n',
        "wneg.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nweights = [1e-9, -1e-9]\n',
        "wnan.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nweights = [1e-9, nan]\n',
        "w0inf.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nw0 = inf\n',
        "order.toml": "[dynamics]\norder = 9\n",
        "poles.toml": "[dynamics]\norder = 1\npoles = [10.0]\n",
        "omega.toml": "[dynamics]\norder = 2\nomega = [-5.0]\n",
        "free.toml": PI + 'free = ["hysteresis.wieghts"]\n',
        "freeempty.toml": PI + "free = []\n",
        "weights.toml": PI + 'weights = "max"\n',
        "weightneg.toml": PI + "weights = {displacement = -1.0}\n",
        "smoothneg.toml": PI + "smoothing = [-0.1, 0.0]\n",
        "levels.toml": PI + "smoothing = [" + ", ".join(["0.1"] * 20) + "]\n",
        "method.toml": PI + 'method = "bfgs"\n',
        "targets.toml": PI + 'targets = ["force"]\n',
        "unit.toml": PI + '[data]\nunits = {displacement = "uV"}\n',
        "unitcol.toml": PI + '[data]\nunits = {strain = "um"}\n',
        "unittable.toml": PI + '[data]\nunits = "um"\n',
        "datakey.toml": PI + "[data]\nheader = false\n",
        "datagroup.toml": PI + "[data]\ngroup = 3\n",
        "datarate.toml": PI + "[data]\nsample_rate = -750.0\n",
        "datacolumns.toml": PI + '[data]\ncolumns = {u = "voltage"}\n',
        "obsmissing.toml": '[observer]\nkind = "current_integration"\nstiffness = 1.0\n',
        "closedform.toml": '[hysteresis]\nkind = "bouc_wen"\nmethod = "closed_form"\nsmoothing = 0.1\n',
        "noblocks.toml": "[fit]\nmax_steps = 3\n",
        "bigint.toml": '[hysteresis]\nkind = "prandtl_ishlinskii"\nw0 = 1' + "0" * 400 + "\n",
        "bigsmooth.toml": PI + "smoothing = [1" + "0" * 400 + ", 0.0]\n",
        "bigrate.toml": PI + "[data]\nsample_rate = 1" + "0" * 400 + "\n",
        "bigweight.toml": PI + "weights = {displacement = 1e300}\n",
        "forceweight.toml": PI + "weights = {force = 1.0}\n",
    }
    for name, text in configs.items():
        (d / name).write_text(text)
    (d / "latin1.toml").write_bytes('[hysteresis]\nkind = "prandtl_ishlinskii"\n# \xe9\n'.encode("latin-1"))
    (d / "confdir.toml").mkdir()
    (d / "afile").write_text("a file\n")
    (d / "existing").mkdir()
    (d / "existing" / "notes.txt").write_text("a user's folder, not empty (an empty one is replaced)\n")
    (d / "sub" / "deeper").mkdir(parents=True)
    _csv(d / "sub" / "inner.csv", h, [t, v, x])
    (d / "fits").mkdir()
    assert main(["fit", str(d / "pi.toml"), str(d / "ok.csv"), "--out", str(d / "fits" / "fit"), "--quiet",
                 "--no-figures"]) in (0, 1)
    assert main(["predict", str(d / "fits" / "fit"), str(d / "ok.csv"), "--out", str(d / "pred")]) == 0
    (d / "fitlink").symlink_to(d / "fits" / "fit")
    shutil.copytree(d / "fits" / "fit", d / "fits" / "edited")
    cfg = (d / "fits" / "edited" / "config.toml").read_text()
    assert "plays = 2" in cfg
    (d / "fits" / "edited" / "config.toml").write_text(cfg.replace("plays = 2", "plays = 3"))
    assert main(["simulate", str(d / "known.toml"), "--input", str(d / "ok.csv"), "--out", str(d / "sim.csv")]) == 0
    return d


def _fit(cfg, *data, out="out"):
    return lambda d: (["fit", str(d / cfg), *[str(d / f) for f in data], "--out", str(d / out)], d / out)


def _fit_opts(*opts, cfg="pi.toml", data=("ok.csv",), out="out"):
    return lambda d: (["fit", str(d / cfg), *[str(d / f) for f in data], "--out", str(d / out), *opts], d / out)


def _predict(model, *data, out="pout", opts=()):
    return lambda d: (["predict", str(d / model), *[str(d / f) for f in data], "--out", str(d / out),
                       *[o.replace("{d}", str(d)) for o in opts]], d / out)


def _simulate(cfg, inp, out="sout.csv", opts=()):
    return lambda d: (["simulate", str(d / cfg), "--input", str(d / inp), "--out", f"{d}/{out}", *opts], d / out)


def _raw(*argv, out=None, cwd=None):
    return lambda d: ([a.replace("{d}", str(d)) for a in argv], None if out is None else d / out,
                      None if cwd is None else d / cwd)


# id -> (builder, expected exit status, fragments the one error line must contain)
CASES = {
    # ---- data files (fit)
    "no v_in column": (_fit("pi.toml", "nov.csv"), 2, ["nov.csv", "required column(s) ['v_in'] missing"]),
    "no t column": (_fit("pi.toml", "not.csv"), 2, ["not.csv", "['t'] missing", "sample_rate"]),
    "NaN in a column": (_fit("pi.toml", "nan.csv"), 2, ["nan.csv", "line 19, column 'displacement' holds"]),
    "inf in a column": (_fit("pi.toml", "inf.csv"), 2, ["inf.csv", "line 7, column 'v_in' holds a non-finite"]),
    "gap in t": (_fit("pi.toml", "gap.csv"), 2, ["gap.csv", "'t' is not uniformly sampled"]),
    "t decreasing": (_fit("pi.toml", "backwards.csv"), 2, ["backwards.csv",
                                                             "column 't' (the time) must increase", "line 3"]),
    "duplicate column": (_fit("pi.toml", "dup.csv"), 2, ["dup.csv", "duplicate column(s) ['v_in']"]),
    "empty csv": (_fit("pi.toml", "empty.csv"), 2, ["empty.csv", "no header row"]),
    "comments only": (_fit("pi.toml", "comments.csv"), 2, ["comments.csv", "no header row"]),
    "header only": (_fit("pi.toml", "headeronly.csv"), 2, ["headeronly.csv", "0 sample(s)"]),
    "ragged line": (_fit("pi.toml", "ragged.csv"), 2, ["ragged.csv", "line 3 has 2 fields"]),
    "word in numbers": (_fit("pi.toml", "word.csv"), 2, ["word.csv", "cannot parse numbers"]),
    "unknown column": (_fit("pi.toml", "strain.csv"), 2, ["strain.csv", "unknown column(s) ['strain']"]),
    "numbers but no header": (_fit("pi.toml", "noheader.csv"), 2, ["noheader.csv", "no header row", "line 1"]),
    "rename to a name that is no column": (_fit_opts("--columns", "t=time"), 2, ["--columns", "'time'"]),
    "text file named npz": (_fit("pi.toml", "text.npz"), 2, ["text.npz", "not an .npz archive", "looks like text"]),
    "npy named npz": (_fit("pi.toml", "array.npz"), 2, ["array.npz", "single .npy array"]),
    "boolean column": (_fit("pi.toml", "bool.npz"), 2, ["bool.npz", "'v_in' is boolean"]),
    "complex column": (_fit("pi.toml", "complex.npz"), 2, ["complex.npz", "'v_in' is complex"]),
    "2-D column": (_fit("pi.toml", "twod.npz"), 2, ["twod.npz", "'v_in' must be 1-D"]),
    "unequal lengths": (_fit("pi.toml", "unequal.npz"), 2, ["unequal.npz", "'v_in' has 297 samples"]),
    "hdf5 without v_in": (_fit("pi.toml", "nov.h5"), 2, ["nov.h5", "['v_in'] missing"]),
    "truncated hdf5": (_fit("pi.toml", "trunc.h5"), 2, ["trunc.h5", "cannot read it as .h5"]),
    "text named mat": (_fit("pi.toml", "text.mat"), 2, ["text.mat", "cannot read it as .mat"]),
    "unsupported suffix": (_fit("pi.toml", "data.txt"), 2, ["data.txt", "unsupported suffix '.txt'"]),
    "directory as data": (_fit("pi.toml", "adir.csv"), 2, ["adir.csv", "is a directory"]),
    "missing data file": (_fit("pi.toml", "absent.csv"), 2, ["absent.csv", "does not exist"]),
    "sample-index t": (_fit("pi.toml", "index.csv"), 2, ["index.csv", "sample indices", "--units t="]),
    "overflowing values": (_fit("pi.toml", "huge.csv"), 2, ["huge.csv", "'v_in'", "overflow"]),
    "record too short": (_fit("pi.toml", "short.csv"), 2, ["short.csv", "8 samples", "at least 20"]),
    "one-sample record": (_fit("pi.toml", "one.csv"), 2, ["one.csv", "1 sample(s)"]),
    "constant target": (_fit("pi.toml", "flat.csv"), 2, ["'displacement' is constant", "flat.csv"]),
    "zero excitation": (_fit("pi.toml", "zero.csv"), 2, ["'v_in' is zero in every data file"]),
    "no predicted channel": (_fit("pi.toml", "force.csv"), 2, ["none of the channels the model predicts",
                                                                "displacement"]),
    "observer without v_out": (_fit("observer.toml", "ok.csv"), 2, ["'v_out'", "ok.csv"]),
    "same file twice": (_fit("pi.toml", "ok.csv", "ok.csv"), 2, ["the data file", "ok.csv' is given twice"]),
    "a file without a fitted channel": (_fit("pi.toml", "ok.csv", "inputonly.csv"), 2,
                                        ["inputonly.csv", "none of the fitted channels (displacement)"]),
    # ---- CONFIG
    "config missing": (_fit("absent.toml", "ok.csv"), 2, ["absent.toml", "does not exist"]),
    "config is a folder": (_fit("confdir.toml", "ok.csv"), 2, ["confdir.toml", "is a directory"]),
    "config not TOML": (_fit("badtoml.toml", "ok.csv"), 2, ["badtoml.toml", "not valid TOML"]),
    "config not UTF-8": (_fit("latin1.toml", "ok.csv"), 2, ["latin1.toml", "cannot read configuration file"]),
    "unknown table": (_fit("table.toml", "ok.csv"), 2, ["table.toml", "[motor]", "allowed tables"]),
    "unknown key": (_fit("key.toml", "ok.csv"), 2, ["key.toml", "[creep]", "'tau'", "allowed keys"]),
    "unknown kind": (_fit("kind.toml", "ok.csv"), 2, ["kind.toml", "'preisachh'", "allowed kinds"]),
    "missing kind": (_fit("nokind.toml", "ok.csv"), 2, ["nokind.toml", "[hysteresis] kind: missing"]),
    "plays astronomically many": (_fit("plays_huge.toml", "ok.csv"), 2, ["plays_huge.toml", "plays", "<= 100"]),
    "plays 1000": (_fit("plays_1000.toml", "ok.csv"), 2, ["plays_1000.toml", "[hysteresis] plays", "<= 100"]),
    "plays 0": (_fit("plays0.toml", "ok.csv"), 2, ["plays0.toml", "plays: must be >= 1"]),
    "plays not an integer": (_fit("playsstr.toml", "ok.csv"), 2, ["playsstr.toml", "plays: must be an integer"]),
    "101 thresholds": (_fit("thresholds101.toml", "ok.csv"), 2, ["thresholds101.toml", "thresholds",
                                                                 "at most 100"]),
    "too many elements": (_fit("elements.toml", "ok.csv"), 2, ["elements.toml", "elements", "<= 100"]),
    "creep order": (_fit("creep_order.toml", "ok.csv"), 2, ["creep_order.toml", "[creep] order", "<= 10"]),
    "substeps unbounded": (_fit("substeps.toml", "ok.csv"), 2, ["substeps.toml", "substeps", "<= 64"]),
    "substeps 0": (_fit("substeps0.toml", "ok.csv"), 2, ["substeps0.toml", "substeps: must be >= 1"]),
    "max_steps too many": (_fit("maxsteps.toml", "ok.csv"), 2, ["maxsteps.toml", "max_steps", "<= 100000"]),
    "max_steps 0": (_fit("maxsteps0.toml", "ok.csv"), 2, ["maxsteps0.toml", "max_steps: must be >= 1"]),
    "thresholds length": (_fit("tlen.toml", "ok.csv"), 2, ["tlen.toml", "thresholds: must have 3 entries"]),
    "thresholds descending": (_fit("tdesc.toml", "ok.csv"), 2, ["tdesc.toml", "strictly ascending"]),
    "negative weight": (_fit("wneg.toml", "ok.csv"), 2, ["wneg.toml", "[hysteresis] weights", "> 0"]),
    "NaN weight": (_fit("wnan.toml", "ok.csv"), 2, ["wnan.toml", "[hysteresis] weights", "finite"]),
    "infinite w0": (_fit("w0inf.toml", "ok.csv"), 2, ["w0inf.toml", "[hysteresis] w0", "finite"]),
    "dynamics order": (_fit("order.toml", "ok.csv"), 2,
                       ["order.toml", "order: must be one of 0, 1, 2, 3, 4, 5, 6, 7, 8"]),
    "unstable pole": (_fit("poles.toml", "ok.csv"), 2, ["poles.toml", "poles", "< 0"]),
    "negative omega": (_fit("omega.toml", "ok.csv"), 2, ["omega.toml", "omega", "> 0"]),
    "unknown free path": (_fit("free.toml", "ok.csv"), 2, ["free.toml", "[fit] free", "'hysteresis.wieghts'",
                                                           "hysteresis.weights"]),
    "empty free list": (_fit("freeempty.toml", "ok.csv"), 2, ["freeempty.toml", "[fit] free"]),
    "weights mode": (_fit("weights.toml", "ok.csv"), 2, ["weights.toml", "[fit] weights", "'max'"]),
    "negative channel weight": (_fit("weightneg.toml", "ok.csv"), 2, ["weightneg.toml", "weight of 'displacement'"]),
    "negative smoothing": (_fit("smoothneg.toml", "ok.csv"), 2, ["smoothneg.toml", "[fit] smoothing"]),
    "too many levels": (_fit("levels.toml", "ok.csv"), 2, ["levels.toml", "[fit] smoothing", "at most 10"]),
    "unknown method": (_fit("method.toml", "ok.csv"), 2, ["method.toml", "[fit] method", "'bfgs'"]),
    "target not predicted": (_fit("targets.toml", "ok.csv"), 2, ["targets.toml", "does not predict 'force'"]),
    "unit of another quantity": (_fit("unit.toml", "ok.csv"), 2, ["unit.toml", "[data] units", "'uV'", "um"]),
    "unit of unknown column": (_fit("unitcol.toml", "ok.csv"), 2, ["unitcol.toml", "[data] units", "'strain'"]),
    "units not a table": (_fit("unittable.toml", "ok.csv"), 2, ["unittable.toml", "[data] units", "table"]),
    "unknown data key": (_fit("datakey.toml", "ok.csv"), 2, ["datakey.toml", "[data]", "'header'"]),
    "group not a name": (_fit("datagroup.toml", "ok.csv"), 2, ["datagroup.toml", "[data] group", "HDF5 group"]),
    "negative sample rate": (_fit("datarate.toml", "ok.csv"), 2, ["datarate.toml", "[data] sample_rate", "> 0"]),
    "rename to an unknown column": (_fit("datacolumns.toml", "ok.csv"), 2, ["datacolumns.toml", "[data] columns",
                                                                            "'voltage'"]),
    "rename a column the file lacks": (_fit_opts("--columns", "u=v_in"), 2, ["ok.csv", "renames ['u']"]),
    "rename onto an existing column": (_fit_opts("--columns", "displacement=v_in"), 2,
                                       ["ok.csv", "'v_in', which the file has already"]),
    "headerless csv without positions": (_fit("pi.toml", "noheader.csv"), 2, ["noheader.csv", "name them by position"]),
    "position beyond the fields": (_fit_opts("--columns", "1=t,2=v_in,9=displacement", data=("noheader.csv",)), 2,
                                   ["noheader.csv", "position(s) ['9']", "3 fields"]),
    "sample rate and a t column disagree": (_fit_opts("--sample-rate", "750"), 2,
                                            ["ok.csv", "sampled at 1000 Hz", "`sample_rate` = 750 Hz"]),
    "--sample-rate not positive": (_fit_opts("--sample-rate", "0"), 2, ["--sample-rate must be a positive"]),
    "missing group": (_fit_opts("--group", "multisine", data=("nov.h5",)), 2, ["nov.h5", "no group 'multisine'"]),
    "observer keys missing": (_fit("obsmissing.toml", "ok.csv"), 2, ["obsmissing.toml",
                                                                      "missing key(s) integrator_capacitance"]),
    "closed form with smoothing": (_fit("closedform.toml", "ok.csv"), 2, ["closedform.toml", "smoothing = 0"]),
    "no model blocks": (_fit("noblocks.toml", "ok.csv"), 2, ["noblocks.toml", "no model blocks"]),
    # ---- output paths and options (fit)
    "empty --out": (_raw("fit", "{d}/pi.toml", "{d}/ok.csv", "--out", ""), 2, ["--out is empty"]),
    "--out is the working directory": (_raw("fit", "{d}/pi.toml", "{d}/ok.csv", "--out", ".", "--overwrite",
                                            out="existing", cwd="existing"), 2, ["refusing", "working directory"]),
    "--out holds the working directory": (_raw("fit", "{d}/pi.toml", "{d}/ok.csv", "--out", "{d}/sub", "--overwrite",
                                               out="sub", cwd="sub/deeper"), 2,
                                          ["refusing", "sub", "contains the working directory"]),
    "--out holds the data": (_fit_opts("--overwrite", data=("sub/inner.csv",), out="sub"), 2,
                             ["refusing", "holds the input", "inner.csv"]),
    "--out holds the config": (_fit_opts("--overwrite", cfg="pi.toml", out="."), 2, ["refusing", "pi.toml"]),
    "--out is the data file": (_fit_opts("--overwrite", out="ok.csv"), 2, ["refusing", "is the input", "ok.csv"]),
    "--out exists": (_fit_opts(out="existing"), 2, ["'", "existing", "already exists", "no piezojax marker"]),
    "--overwrite an unmarked folder": (_fit_opts("--overwrite", out="existing"), 2,
                                       ["refusing to replace", "existing", "no piezojax marker"]),
    "--overwrite a predict folder": (_fit_opts("--overwrite", out="pred"), 2,
                                     ["refusing to replace", "pred", "`piezojax predict`"]),
    "--out is a file": (_fit_opts("--overwrite", out="afile"), 2, ["afile", "is a file"]),
    "--out name too long": (_fit_opts(out="x" * 240), 2, ["240 bytes", "at most"]),
    "--out parent missing": (_fit_opts(out="nowhere/out"), 2, ["nowhere", "does not exist"]),
    "--out parent is a file": (_fit_opts(out="afile/out"), 2, ["afile", "is not a directory"]),
    "--max-steps 0": (_fit_opts("--max-steps", "0"), 2, ["--max-steps must be >= 1"]),
    "--max-steps not a number": (_fit_opts("--max-steps", "ten"), 2, ["--max-steps", "invalid int value"]),
    "--units without =": (_fit_opts("--units", "um"), 2, ["--units", "COLUMN=UNIT", "'um'"]),
    "--units unknown unit": (_fit_opts("--units", "displacement=furlong"), 2, ["--units", "'furlong'",
                                                                              "'displacement'"]),
    "--units unknown column": (_fit_opts("--units", "strain=um"), 2, ["--units", "unknown column 'strain'"]),
    "unknown option": (_fit_opts("--fast"), 2, ["unrecognized arguments: --fast"]),
    "--out missing": (_raw("fit", "{d}/pi.toml", "{d}/ok.csv"), 2, ["the following arguments are required: --out"]),
    "no data files": (_raw("fit", "{d}/pi.toml", "--out", "{d}/out", out="out"), 2, ["DATA"]),
    "unknown command": (_raw("calibrate", "x"), 2, ["invalid choice: 'calibrate'"]),
    # ---- predict
    "predict into the fit folder": (_predict("fits/fit", "ok.csv", out="fits/fit", opts=("--overwrite",)), 2,
                                    ["refusing", "is the fitted model folder"]),
    "predict into a folder holding the fit": (_predict("fits/fit", "ok.csv", out="fits", opts=("--overwrite",)), 2,
                                              ["refusing", "holds the fitted model folder"]),
    "predict into the data's folder": (_predict("fits/fit", "sub/inner.csv", out="sub", opts=("--overwrite",)), 2,
                                       ["refusing", "holds the input", "inner.csv"]),
    "predict over a fit folder": (_predict("fits/fit", "ok.csv", out="existing", opts=("--overwrite",)), 2,
                                  ["refusing to replace", "no piezojax marker"]),
    "predict from a non-fit folder": (_predict("existing", "ok.csv"), 2, ["not a folder written by `piezojax fit`"]),
    "predict from a missing folder": (_predict("nofit", "ok.csv"), 2, ["nofit", "does not exist"]),
    "predict from an edited fit folder": (_predict("fits/edited", "ok.csv"), 2,
                                          ["edited", "model.eqx does not match the model of config.toml"]),
    "predict bad data": (_predict("fits/fit", "nan.csv"), 2, ["nan.csv", "line 19"]),
    "predict with a history of another rate": (_predict("fits/fit", "ok.csv", opts=("--history", "{d}/slow.csv")), 2,
                                                ["slow", "sampled every 0.002 s", "same sampling step"]),
    "predict scored from beyond the record": (_predict("fits/fit", "ok.csv", opts=("--score-from", "5")), 2,
                                              ["ok.csv", "--score-from 5 s leaves fewer than 2 samples"]),
    "predict with a negative warm-up": (_predict("fits/fit", "ok.csv", opts=("--warm-up", "-1")), 2,
                                        ["warm-up must be a number of seconds > 0", "-1"]),
    "predict with a warm-up as long as the record": (_predict("fits/fit", "ok.csv", opts=("--warm-up", "100")), 2,
                                                     ["ok.csv", "warm-up of 100 s", "each needs 2"]),
    "--out a symlink to a fit folder": (_fit_opts("--overwrite", out="fitlink"), 2,
                                        ["fitlink", "is a symbolic link"]),
    "--out a dangling symlink": (_fit_opts(out="dangling"), 2, ["dangling", "is a symbolic link"]),
    "--out a symlink loop": (_fit_opts("--overwrite", out="loop"), 2, ["loop", "is a symbolic link"]),
    "--window without a colon": (_fit_opts("--window", "7"), 2, ["--window", "START:STOP", "'7'"]),
    "--window not numbers": (_fit_opts("--window", "a:b"), 2, ["--window", "'a:b'"]),
    "--window empty": (_fit_opts("--window", "5:"), 2, ["--window 5:", "ok.csv", "t = 5 s to its end keeps 0 "
                                                        "sample(s)"]),
    "--window before the record, negative": (_fit_opts("--window", "-5:-1"), 2, ["--window -5:-1", "ok.csv",
                                                                                "keeps 0 sample(s)"]),
    "--max-steps above the bound": (_fit_opts("--max-steps", "100001"), 2, ["--max-steps", "<= 100000"]),
    "--units twice for a column": (_fit_opts("--units", "displacement=um,displacement=nm"), 2,
                                   ["--units", "'displacement' is given twice"]),
    "--group for a CSV file": (_fit_opts("--group", "multisine"), 2, ["--group multisine", "ok.csv", "HDF5"]),
    "same file through a symlinked folder": (_fit("pi.toml", "sub/inner.csv", "linked/inner.csv"), 2,
                                             ["inner.csv' is given twice (also as", "linked"]),
    "400-digit integer": (_fit("bigint.toml", "ok.csv"), 2, ["bigint.toml", "[hysteresis] w0", "finite number"]),
    "400-digit smoothing level": (_fit("bigsmooth.toml", "ok.csv"), 2, ["bigsmooth.toml", "[fit] smoothing"]),
    "400-digit sample rate": (_fit("bigrate.toml", "ok.csv"), 2, ["bigrate.toml", "[data] sample_rate"]),
    "channel weight overflowing": (_fit("bigweight.toml", "ok.csv"), 2, ["bigweight.toml", "[fit] weights",
                                                                         "<= 1e+20"]),
    "no weight for a target": (_fit("forceweight.toml", "ok.csv"), 2, ["forceweight.toml", "[fit] weights",
                                                                       "'displacement'"]),
    "underflowing values": (_fit("pi.toml", "tiny.csv"), 2, ["tiny.csv", "'displacement'", "underflow"]),
    "denormal drive": (_fit("pi.toml", "denormal.csv"), 2, ["denormal.csv", "'v_in'", "underflow"]),
    "simulate to a folder-like path": (_simulate("known.toml", "ok.csv", out="sim2.csv/"), 2,
                                       ["sim2.csv/", "ends with a slash"]),
    "predict bad --units": (_predict("fits/fit", "ok.csv", opts=("--units", "v_in=um")), 2,
                            ["--units", "'um'", "'v_in'", "voltage"]),
    # ---- simulate
    "simulate to .txt": (_simulate("known.toml", "ok.csv", out="sim.txt"), 2, ["sim.txt", "unsupported suffix"]),
    "simulate onto its input": (_simulate("known.toml", "ok.csv", out="ok.csv", opts=("--overwrite",)), 2,
                                ["refusing", "is the input", "ok.csv"]),
    "simulate onto the config": (_simulate("known.toml", "ok.csv", out="known.toml", opts=("--overwrite",)), 2,
                                 ["known.toml"]),
    "simulate over a user's file": (_simulate("known.toml", "ok.csv", out="ok2.csv", opts=("--overwrite",)), 2,
                                    ["refusing to replace", "ok2.csv", "not written by `piezojax simulate`"]),
    "simulate over existing output": (_simulate("known.toml", "ok.csv", out="sim.csv"), 2,
                                      ["sim.csv", "already exists; pass --overwrite"]),
    "simulate onto a folder": (_simulate("known.toml", "ok.csv", out="adir.csv", opts=("--overwrite",)), 2,
                               ["adir.csv", "is a directory"]),
    "simulate without values": (_simulate("pi.toml", "ok.csv"), 2, ["pi.toml", "missing: [hysteresis] weights"]),
    "simulate observer without v_out": (_simulate("observer_cp.toml", "ok.csv"), 2, ["'v_out'", "input"]),
    # without hysteresis the charge's scale C_P is the data's: a simulation needs it given
    "simulate observer without capacitance_p": (_simulate("observer.toml", "ok.csv"), 2,
                                                ["missing: [observer] capacitance_p"]),
    "simulate bad input file": (_simulate("known.toml", "gap.csv"), 2, ["gap.csv", "not uniformly sampled"]),
}


def _snapshot(path):
    if path is None or not path.exists():
        return None
    if path.is_file():
        return path.read_bytes()
    return sorted((str(p.relative_to(path)), p.lstat().st_mtime_ns) for p in path.rglob("*"))


@pytest.mark.parametrize("case", list(CASES))
def test_bad_cli_input_names_the_culprit(bench, capsys, monkeypatch, case):
    build, status, fragments = CASES[case]
    argv, out, *cwd = build(bench)
    monkeypatch.chdir(cwd[0] if cwd and cwd[0] is not None else bench)
    before = _snapshot(out)
    listing = sorted(p.name for p in bench.iterdir())
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == status, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and ": error: " in lines[0] and lines[0].startswith("piezojax"), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert "Traceback" not in err
    assert _snapshot(out) == before  # absent stays absent, an existing output is untouched
    assert sorted(p.name for p in bench.iterdir()) == listing  # nothing new, no temporary left behind


def test_case_table_is_large():
    assert len(CASES) >= 100


# ---------------------------------------------------------------------------------------------- what is accepted


def test_predict_reads_input_only_files_and_other_layouts(tmp_path, capsys):
    """A fit's `[data] columns` and `group` read the files to predict from: an input-only file in the training
    layout, CSV files after a grouped HDF5 fit; `--columns` replaces the mapping (another layout, or '' for none)."""
    t = np.arange(N) * DT
    v = 30 * np.sin(2 * np.pi * 3 * t)
    x = 1e-8 * v + 2e-9 * np.abs(v)
    with h5py.File(tmp_path / "train.h5", "w") as f:
        g = f.create_group("run1")
        for name, col in (("time_ms", 1e3 * t), ("drive_V", v), ("pos_um", 1e6 * x)):
            g[name] = col
    _csv(tmp_path / "train2.csv", ["time_ms", "drive_V", "pos_um"], [1e3 * t, 0.5 * v, 0.5e6 * x])
    _csv(tmp_path / "inputs.csv", ["time_ms", "drive_V"], [1e3 * t, v])
    _csv(tmp_path / "german.csv", ["zeit", "spannung", "weg"], [1e3 * t, v, 1e6 * x])
    _csv(tmp_path / "si.csv", ["t", "v_in", "displacement"], [t, v, x])
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(PI + '[data]\ncolumns = {time_ms = "t", drive_V = "v_in", pos_um = "displacement"}\n'
                   'units = {t = "ms", displacement = "um"}\n')
    fit = tmp_path / "fit"
    assert main(["fit", str(cfg), str(tmp_path / "train.h5"), str(tmp_path / "train2.csv"), "--group", "run1",
                 "--out", str(fit), "--quiet", "--no-figures"]) in (0, 1)

    def predict(name, *opts):
        out = tmp_path / f"pred_{name}"
        rc = main(["predict", str(fit), str(tmp_path / f"{name}.csv"), "--out", str(out), *opts])
        assert rc == 0, capsys.readouterr().err
        return out, json.loads((out / "metrics.json").read_text())

    out, metrics = predict("inputs")
    predict("inputs", "--history", str(tmp_path / "train.h5"), "--overwrite")  # the fit's group: the history's
    assert fitting.load_experiment(out / "inputs.csv").channel_names == ("displacement",)
    assert metrics["metrics"] == {}  # nothing measured, nothing scored
    _, german = predict("german", "--columns", "zeit=t,spannung=v_in,weg=displacement")
    _, si = predict("si", "--columns", "", "--units", "t=s,displacement=m")
    rmse = [m["metrics"][k]["displacement"]["rmse"] for m, k in ((german, "german"), (si, "si"))]
    np.testing.assert_allclose(rmse[0], rmse[1], rtol=1e-9)  # the same record read through either mapping
    capsys.readouterr()


def test_numpy_savetxt_header_and_declared_units(bench, tmp_path, capsys):
    """A header written by `numpy.savetxt` behind '# ' is read; µm declared in CONFIG or on the command line give
    the same SI data; undeclared µm warn on stderr and in result.json."""
    t = np.arange(N) * DT
    v = 30 * np.sin(2 * np.pi * 3 * t)
    x = 1e-8 * v + 2e-9 * np.abs(v)
    _csv(tmp_path / "savetxt.csv", ["t", "v_in", "displacement"], [t, v, x], comments="# ")
    exp = fitting.load_experiment(tmp_path / "savetxt.csv")
    np.testing.assert_array_equal(exp["displacement"], x)
    np.savetxt(tmp_path / "spaces.csv", np.column_stack([t, v, x]), header="t v_in displacement")  # the defaults
    np.testing.assert_allclose(fitting.load_experiment(tmp_path / "spaces.csv")["displacement"], x, rtol=1e-15)
    with pytest.raises(pj.PiezojaxValueError, match="`max_steps` must be an integer >= 1, got nan"):
        fitting.fit(pj.PrandtlIshlinskii(np.array([1e-9]), np.array([1.0]), w0=1e-8), fitting.Dataset([exp]),
                    max_steps=float("nan"))
    _csv(tmp_path / "micro.csv", ["t", "v_in", "displacement"], [t * 1e3, v * 1e3, x * 1e6])
    scaled = fitting.load_experiment(tmp_path / "micro.csv", units={"t": "ms", "v_in": "mV", "displacement": "µm"})
    np.testing.assert_allclose(scaled["displacement"], x, rtol=1e-15)
    np.testing.assert_allclose(scaled.t, t, rtol=1e-15, atol=1e-18)
    with pytest.warns(fitting._data.UnitWarning, match="'displacement' has a range of .* is it in µm"):
        fitting.load_experiment(tmp_path / "micro.csv", units={"t": "ms", "v_in": "mV"})
    (tmp_path / "um.toml").write_text(PI + '[data]\nunits = {t = "ms", v_in = "mV"}\n')
    out = tmp_path / "fit_um"
    rc = main(["fit", str(tmp_path / "um.toml"), str(tmp_path / "micro.csv"), "--out", str(out), "--quiet",
               "--no-figures"])
    err = capsys.readouterr().err
    assert rc in (0, 1) and "warning: experiment 'micro'" in err and "--units displacement=um" in err
    summary = json.loads((out / "result.json").read_text())
    assert len(summary["warnings"]) == 1 and "'displacement'" in summary["warnings"][0]
    assert summary["cli"]["data_settings"] == {"units": {"t": "ms", "v_in": "mV"}}
    out2 = tmp_path / "fit_um2"
    assert main(["fit", str(tmp_path / "um.toml"), str(tmp_path / "micro.csv"), "--out", str(out2), "--quiet",
                 "--no-figures", "--units", "displacement=um"]) in (0, 1)
    assert "warning" not in capsys.readouterr().err
    assert json.loads((out2 / "result.json").read_text())["warnings"] == []
    # predict reads new files in the units the fit declared, and says so; `--units ''` reads them in SI
    assert main(["predict", str(out2), str(tmp_path / "micro.csv"), "--out", str(tmp_path / "p")]) == 0
    assert "in the fit's units (t=ms,v_in=mV,displacement=um); --units '' reads them in SI" in capsys.readouterr().err
    pred = fitting.load_experiment(tmp_path / "p" / "micro.csv")
    np.testing.assert_allclose(pred.t, t, rtol=1e-15, atol=1e-18)
    assert main(["predict", str(out2), str(tmp_path / "savetxt.csv"), "--out", str(tmp_path / "p_si"),
                 "--units", ""]) == 0
    assert "fit's units" not in capsys.readouterr().err
    np.testing.assert_allclose(fitting.load_experiment(tmp_path / "p_si" / "savetxt.csv").t, t, rtol=1e-15)
    # --units adds to the fit's units, which the note names; '' first resets them, then the others apply
    assert main(["predict", str(out2), str(tmp_path / "micro.csv"), "--out", str(tmp_path / "p2"),
                 "--units", "displacement=um"]) == 0
    assert "in the fit's units (t=ms,v_in=mV); --units ''" in capsys.readouterr().err
    assert main(["predict", str(out2), str(tmp_path / "micro.csv"), "--out", str(tmp_path / "p3"),
                 "--units", "", "--units", "t=ms,v_in=mV,displacement=um"]) == 0
    assert "fit's units" not in capsys.readouterr().err
    np.testing.assert_allclose(fitting.load_experiment(tmp_path / "p3" / "micro.csv").t, t, rtol=1e-15, atol=1e-18)
    # a declared unit that gives implausible values is named as declared; an undeclared one gets its likely unit
    with pytest.warns(fitting._data.UnitWarning, match="'v_in', declared in 'kV', has a peak of .* check its"):
        fitting.load_experiment(tmp_path / "micro.csv", units={"t": "ms", "v_in": "kV", "displacement": "um"})
    with pytest.warns(fitting._data.UnitWarning, match=r"'v_in' has a peak of .* --units v_in=mV\)"):
        fitting.load_experiment(tmp_path / "micro.csv", units={"t": "ms", "displacement": "um"})


def test_overwrite_replaces_only_its_own_output(bench, tmp_path, capsys):
    d = bench
    fit_out, pred_out, sim_out = tmp_path / "f", tmp_path / "p", tmp_path / "s.h5"
    args = [str(d / "pi.toml"), str(d / "ok.csv"), "--out", str(fit_out), "--quiet", "--no-figures"]
    assert main(["fit", *args]) in (0, 1)
    assert json.loads((fit_out / ".piezojax").read_text())["kind"] == "fit"
    first = (fit_out / "model.eqx").stat().st_mtime_ns
    assert main(["fit", *args, "--overwrite"]) in (0, 1)
    assert (fit_out / "model.eqx").stat().st_mtime_ns != first
    assert main(["predict", str(fit_out), str(d / "ok.csv"), "--out", str(pred_out)]) == 0
    assert main(["predict", str(fit_out), str(d / "ok.csv"), "--out", str(pred_out), "--overwrite"]) == 0
    for suffix in (".h5", ".npz", ".mat", ".csv"):
        out = sim_out.with_suffix(suffix)
        argv = ["simulate", str(d / "known.toml"), "--input", str(d / "ok.csv"), "--out", str(out)]
        assert main(argv) == 0
        assert fitting._data.read_file_marker(out) == "simulate"
        assert fitting.load_experiment(out).channel_names == ("displacement",)  # the marker is not a column
        assert main([*argv, "--overwrite"]) == 0
    capsys.readouterr()


def test_window_runs_the_samples_before_its_start_as_history(bench, tmp_path, capsys):
    d = bench
    half = N * DT / 2
    argv = ["fit", str(d / "pi.toml"), str(d / "ok.csv"), "--max-steps", "2", "--quiet", "--no-figures"]
    assert main([*argv, "--window", f"{half}:", "--out", str(tmp_path / "late")]) in (0, 1)
    summary = json.loads((tmp_path / "late" / "result.json").read_text())
    # scored from the window's start, the whole record simulated: the metrics count only the scored samples
    assert summary["num_residuals"] == N // 2
    assert summary["metrics"]["ok"]["displacement"]["samples"] == N // 2
    like = fitting.load_config(tmp_path / "late" / "config.toml").build(None)
    model = pj.unwrap(fitting.load_model(tmp_path / "late", like=like))
    pred = fitting.predict(model, fitting.load_experiment(d / "ok.csv"))
    x = fitting.load_experiment(d / "ok.csv")["displacement"]
    rmse = np.sqrt(np.mean((pred["displacement"][N // 2:] - x[N // 2:]) ** 2))
    assert summary["metrics"]["ok"]["displacement"]["rmse"] == pytest.approx(rmse, rel=1e-6)
    capsys.readouterr()


def test_fitresult_save_overwrites_only_a_fit_folder(bench, tmp_path):
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me\n")
    with pytest.raises(pj.PiezojaxValueError, match="no piezojax marker"):
        with fitting.files.atomic_directory(other, overwrite=True, kind="fit"):
            pass
    assert (other / "notes.txt").read_text() == "keep me\n"
    with pytest.raises(pj.PiezojaxValueError, match="working directory"):
        with fitting.files.atomic_directory(Path.cwd(), overwrite=True):
            pass


def test_overwrite_never_deletes_what_a_user_added_to_an_output_folder(tmp_path):
    out = tmp_path / "fit"
    with fitting.files.atomic_directory(out, kind="fit") as d:
        (d / "result.json").write_text("{}")
        (d / "figures").mkdir()
        (d / "figures" / "fit.png").write_bytes(b"png")
    marker = json.loads((out / fitting.files.MARKER).read_text())
    assert marker["files"] == ["figures/", "figures/fit.png", "result.json"]
    (out / "my_notes.txt").write_text("keep me\n")
    (out / "figures" / "mine").mkdir()
    for overwrite in (False, True):  # refused before any work, naming what would be lost
        with pytest.raises(pj.PiezojaxValueError, match=r"refusing to replace .*'figures/mine/', 'my_notes.txt'"):
            with fitting.files.atomic_directory(out, overwrite=overwrite, kind="fit"):
                raise AssertionError("must be refused on entry")
    assert (out / "my_notes.txt").read_text() == "keep me\n" and (out / "result.json").exists()
    (out / "my_notes.txt").unlink()
    (out / "figures" / "mine").rmdir()
    with fitting.files.atomic_directory(out, overwrite=True, kind="fit") as d:
        (d / "result.json").write_text('{"new": 1}')
    assert json.loads((out / "result.json").read_text()) == {"new": 1} and not (out / "figures").exists()
    # a file added while the run computes: the run's folder replaces the old one, which is kept, not deleted
    with pytest.warns(fitting.files.OutputWarning, match=r"files were added .* kept, as .*fit\.previous"):
        with fitting.files.atomic_directory(out, overwrite=True, kind="fit") as d:
            (d / "result.json").write_text('{"newer": 1}')
            (out / "late.txt").write_text("added meanwhile\n")
            (out / ".DS_Store").write_bytes(b"")  # a file browser's metadata alone would not count
    assert json.loads((out / "result.json").read_text()) == {"newer": 1}
    assert (tmp_path / "fit.previous" / "late.txt").read_text() == "added meanwhile\n"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # only a browser's metadata added: the old folder goes, silently
        with fitting.files.atomic_directory(out, overwrite=True, kind="fit") as d:
            (d / "result.json").write_text("{}")
            (out / "._result.json").write_bytes(b"")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit", "fit.previous"]
    # a damaged list protects like a list: refused, naming the marker
    marker_file = out / fitting.files.MARKER
    marker_file.write_text(json.dumps({"written_by": "piezojax", "kind": "fit", "files": "result.json"}))
    with pytest.raises(pj.PiezojaxValueError, match=r"refusing to replace .*marker file .* is damaged"):
        with fitting.files.atomic_directory(out, overwrite=True, kind="fit"):
            pass
    # a marker written before the list of files: replaced as before
    marker_file.write_text(json.dumps({"written_by": "piezojax", "kind": "fit"}))
    (out / "extra.txt").write_text("x")
    with fitting.files.atomic_directory(out, overwrite=True, kind="fit") as d:
        (d / "result.json").write_text("{}")
    assert not (out / "extra.txt").exists()
    # an empty folder (made for the run) is replaced without overwrite
    (tmp_path / "made").mkdir()
    with fitting.files.atomic_directory(tmp_path / "made", kind="fit") as d:
        (d / "result.json").write_text("{}")
    assert (tmp_path / "made" / "result.json").exists()


def test_leftovers_of_killed_runs_are_removed_and_live_writers_refused(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "run"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / f".run.tmp-{pid}-abcdefgh").mkdir()
    (tmp_path / f".run.tmp-{pid}-abcdefgh" / "model.eqx").write_bytes(b"partial")
    (tmp_path / f".run.tmp-{pid}-old-zz").mkdir()
    with fitting.files.atomic_directory(out) as d:
        (d / "x").write_text("1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / f".run2.tmp-{live.pid}-abcdefgh").mkdir()
        with pytest.raises(pj.PiezojaxValueError, match=rf"another process \(pid {live.pid}\) is writing"):
            with fitting.files.atomic_directory(tmp_path / "run2"):
                pass
        with fitting.files.atomic_directory(tmp_path / "run2.v2") as d:  # another output: not blocked by run2's writer
            (d / "x").write_text("1")
        fitting.save_experiment(fitting.Experiment.from_arrays(v_in=np.ones(3), dt=1e-3), tmp_path / "run2.csv")
    finally:
        live.kill()
        live.wait()


def test_std_error_status_distinguishes_infinite_and_not_computed():
    from fitting._results import _std_error_status

    assert [_std_error_status(s) for s in (0.5, np.inf, np.nan)] == ["finite", "infinite", "not computed"]


def test_broken_stdout_pipe_keeps_the_status_and_the_outputs(bench, tmp_path):
    import os
    import subprocess
    import sys

    out = tmp_path / "piped"
    cmd = [sys.executable, "-m", "fitting.cli", "fit", str(bench / "pi.toml"), str(bench / "ok.csv"), "--out",
           str(out), "--quiet", "--no-figures"]
    r = subprocess.run(f"{' '.join(cmd)} | true; exit ${{PIPESTATUS[0]}}", shell=True, executable="/bin/bash",
                       capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert r.returncode in (0, 1), r.stderr
    assert "Traceback" not in r.stderr and "error" not in r.stderr
    assert (out / "result.json").is_file() and (out / "model.eqx").is_file()
    for redirect, out2 in ((">&-", tmp_path / "closed"), (">/dev/full", tmp_path / "full")):
        cmd2 = [*cmd[:-4], "--out", str(out2), "--quiet", "--no-figures"]
        r = subprocess.run(f"{' '.join(cmd2)} {redirect}", shell=True, executable="/bin/bash", capture_output=False,
                           stderr=subprocess.PIPE, text=True, timeout=600)
        assert r.returncode in (0, 1), (redirect, r.stderr)
        assert "Traceback" not in r.stderr and "error:" not in r.stderr, (redirect, r.stderr)
        assert (out2 / "result.json").is_file()


def test_fit_too_large_for_the_memory_is_refused_before_any_work(bench, tmp_path, capsys, monkeypatch):
    import fitting._calibrate as pipeline

    monkeypatch.setattr(pipeline, "physical_memory", lambda: 64 * 2**20)
    out = tmp_path / "big"
    rc = main(["fit", str(bench / "pi.toml"), str(bench / "ok.csv"), "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "GiB" in err[0] and "300 samples" in err[0] and "6 free parameters" in err[0], err
    assert "initial values" not in " ".join(err) and not out.exists()


DATA = Path(__file__).resolve().parents[1] / "experiments" / "data"


def test_the_shipped_records_read_through_the_generic_path(tmp_path, capsys):
    """Both shipped files, as users have them (a header-less CSV in µm with rounded time stamps; an HDF5 group with
    other column names and no time column), through the API and the command line."""
    rec = fitting.load_experiment(DATA / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv",
                                  columns={"2": "t", "3": "displacement", "4": "v_in"}, units={"displacement": "um"})
    assert rec.n == 50_001 and rec.dt == pytest.approx(2e-4, rel=1e-9)
    assert rec["displacement"][0] == pytest.approx(-1.6174316e-6)
    assert np.max(np.abs(rec.v_in)) == pytest.approx(150, rel=1e-3)
    bw = fitting.load_experiment(DATA / "boucwen_benchmark" / "train.h5", group="multisine",
                                 columns={"u": "v_in", "y": "displacement"}, sample_rate=750.0, ignore_extra=True)
    assert bw.n == 40_960 and bw.dt == pytest.approx(1 / 750)
    # the command line, on a shortened copy of the real record (the first 4 s: rest, the jump, two cycles)
    short = tmp_path / "piezo_4s.csv"
    lines = (DATA / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv").read_text().splitlines()[:20_000]
    short.write_text("\n".join(lines) + "\n")
    (tmp_path / "pi.toml").write_text(PI + '[data]\ncolumns = {2 = "t", 3 = "displacement", 4 = "v_in"}\n'
                                      'units = {displacement = "um"}\n')
    out = tmp_path / "fit"
    rc = main(["fit", str(tmp_path / "pi.toml"), str(short), "--out", str(out), "--quiet", "--no-figures"])
    err = capsys.readouterr().err
    assert rc in (0, 1) and "warning" not in err, err
    # predict reads the held-out file the way the fit read its own (positions, µm)
    assert main(["predict", str(out), str(short), "--out", str(tmp_path / "pred")]) == 0
    pred = fitting.load_experiment(tmp_path / "pred" / "piezo_4s.csv")
    assert pred.n == 20_000 and np.max(np.abs(pred["displacement"])) < 1e-4  # metres, not micrometres


def test_predict_continues_from_the_history(bench, tmp_path, capsys):
    """A record split in two: the second part predicted after the first (`--history`, `fitting.predict`) equals the
    end of the whole record's prediction, and `--score-from` scores that end; from rest it differs."""
    t = np.arange(N) * DT
    v = 30 * np.sin(2 * np.pi * 3 * t) + 10
    x = np.asarray(pj.PrandtlIshlinskii([0.5, 0.3], [4.0, 12.0], w0=1.0)(v)) * 1e-8  # with memory
    whole = fitting.Experiment.from_arrays(t=t, v_in=v, displacement=x, name="whole")
    first, second = whole.slice(None, 0.2, name="first"), whole.slice(0.2, None, name="second")
    for e in (whole, first, second):
        fitting.save_experiment(e, tmp_path / f"{e.name}.csv")
    fit = tmp_path / "fit"
    assert main(["fit", str(bench / "pi.toml"), str(tmp_path / "whole.csv"), "--out", str(fit), "--quiet",
                 "--no-figures"]) in (0, 1)
    assert main(["predict", str(fit), str(tmp_path / "second.csv"), "--history", str(tmp_path / "first.csv"),
                 "--out", str(tmp_path / "p_hist")]) == 0
    assert main(["predict", str(fit), str(tmp_path / "whole.csv"), "--score-from", "0.2", "--out",
                 str(tmp_path / "p_whole")]) == 0
    assert main(["predict", str(fit), str(tmp_path / "second.csv"), "--out", str(tmp_path / "p_rest")]) == 0
    capsys.readouterr()
    hist = fitting.load_experiment(tmp_path / "p_hist" / "second.csv")["displacement"]
    full = fitting.load_experiment(tmp_path / "p_whole" / "whole.csv")["displacement"]
    rest = fitting.load_experiment(tmp_path / "p_rest" / "second.csv")["displacement"]
    np.testing.assert_allclose(hist, full[first.n:], rtol=1e-12, atol=1e-20)
    assert np.max(np.abs(rest - hist)) > 1e-3 * np.ptp(hist)  # from rest, the hysteresis memory is lost
    m_hist = json.loads((tmp_path / "p_hist" / "metrics.json").read_text())["metrics"]["second"]["displacement"]
    m_whole = json.loads((tmp_path / "p_whole" / "metrics.json").read_text())["metrics"]["whole"]["displacement"]
    assert m_hist["rmse"] == pytest.approx(m_whole["rmse"], rel=1e-9)
    # the API: the same path for a fitted model, any length (10 samples)
    model = fitting.load_model(fit, like=fitting.load_config(fit / "config.toml").build(None))
    short = second.slice(0.2, 0.2 + 9.5 * DT)
    y = fitting.predict(model, short, history=first)["displacement"]
    assert short.n == 10
    np.testing.assert_allclose(y, hist[:10], rtol=1e-12, atol=1e-20)


def test_cold_start_on_the_real_record_and_fallback(monkeypatch):
    """The PI + Kelvin–Voigt cold start on the measured record's first 5 s gave infinite creep stiffnesses (the
    floor of its gains was relative to PI weights that the NNLS had set to 0); and a cold start that fails leaves
    the rule-based start with a warning instead of ending the fit."""
    rec = fitting.load_experiment(DATA / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv",
                                  columns={"2": "t", "3": "displacement", "4": "v_in"}, units={"displacement": "um"})
    cold = pj.unwrap(fitting.cold_start_actuator([rec.slice(None, 5.0)], 10, 2, 2))
    assert np.all(np.isfinite(np.asarray(cold.creep.stiffnesses)))

    def broken(*args, **kwargs):
        raise pj.PiezojaxValueError("`stiffnesses` must be finite and > 0, got [inf, inf]")

    monkeypatch.setattr("fitting._config.kinds.base.cold_start_actuator", broken)
    cfg = fitting.parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 3\n[creep]\nkind = "kelvin_voigt"\n'
                               "order = 1\n[dynamics]\norder = 2\n", "pc.toml")
    with pytest.warns(fitting._config.StartWarning, match="pc.toml: the data-driven cold start failed"):
        model = pj.unwrap(cfg.build(fitting.Dataset([rec.slice(3.0, 4.0)])))
    assert np.all(np.isfinite(np.asarray(model.creep.stiffnesses)))
