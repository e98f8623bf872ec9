"""Experiment/Dataset containers, data file loaders and atomic writers of `fitting/`."""

import json
import math
import os
import zipfile

import h5py
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.io

from fitting._data import (
    CHANNELS,
    Dataset,
    Experiment,
    load_experiment,
    save_experiment,
)
from fitting.files import (
    atomic_directory,
    atomic_write_bytes,
    atomic_write_text,
    check_writable,
    save_json,
)
from piezojax._checks import PiezojaxValueError

N = 257
DT = 1e-4


def _make(rng, n=N, dt=DT, name="exp", channels=("v_out", "displacement", "force"), t0=0.0):
    # Values with full float64 mantissas, so exact round trips are a real test of the writers.
    scale = {"charge": 1e-9}  # plausible coulombs: no unit warning
    chans = {c: rng.standard_normal(n) * 10.0 ** rng.integers(-9, 2) * scale.get(c, 1.0) for c in channels}
    return Experiment.from_arrays(v_in=100 * rng.random(n), dt=dt, t0=t0, name=name, **chans)


def _assert_same(a: Experiment, b: Experiment):
    assert set(a.channels) == set(b.channels)
    for k, v in a.columns().items():
        np.testing.assert_allclose(b[k], v, rtol=1e-15, atol=0)


def _no_temp_files(directory):
    return [p for p in os.listdir(directory) if ".tmp-" in p]


# --------------------------------------------------------------------------------------------------------- Experiment


def test_experiment_properties(rng):
    e = _make(rng, t0=2.0)
    assert e.n == N
    assert math.isclose(e.dt, DT, rel_tol=1e-12)
    assert math.isclose(e.duration, (N - 1) * DT, rel_tol=1e-12)
    assert e.has("force") and e.has("t") and e.has("v_in") and not e.has("charge")
    assert e.channel_names == ("v_out", "displacement", "force")
    assert e.t[0] == 2.0
    r = repr(e)
    assert "exp" in r and f"n={N}" in r and "force" in r and len(r) < 120
    # read-only, frozen
    with pytest.raises(ValueError):
        e.t[0] = 1.0
    with pytest.raises(AttributeError):
        e.name = "other"
    with pytest.raises(TypeError):
        e.channels["charge"] = np.zeros(N)
    with pytest.raises(PiezojaxValueError, match="unknown channel 'flux'"):
        e.has("flux")
    with pytest.raises(PiezojaxValueError, match="has no channel 'charge'"):
        e["charge"]


def test_experiment_from_arrays_t_or_dt(rng):
    v = rng.random(10)
    e1 = Experiment.from_arrays(v_in=v, dt=0.5, t0=1.0)
    np.testing.assert_array_equal(e1.t, 1.0 + 0.5 * np.arange(10))
    e2 = Experiment.from_arrays(v_in=v, t=e1.t, charge=v, current=None)
    assert e2.channel_names == ("charge",)
    with pytest.raises(PiezojaxValueError, match="exactly one of `t` and `dt`"):
        Experiment.from_arrays(v_in=v)
    with pytest.raises(PiezojaxValueError, match="exactly one of `t` and `dt`"):
        Experiment.from_arrays(v_in=v, t=e1.t, dt=0.5)
    with pytest.raises(PiezojaxValueError, match="`dt` must be a positive"):
        Experiment.from_arrays(v_in=v, dt=-1.0)
    for text in ("1e-4", True):  # a string or a flag is no step
        with pytest.raises(PiezojaxValueError, match="`dt` must be a positive finite scalar"):
            Experiment.from_arrays(v_in=v, dt=text)
    # channels are stored in CHANNELS order whatever the order given
    e3 = Experiment.from_arrays(v_in=v, dt=1.0, current=v, v_out=v)
    assert e3.channel_names == ("v_out", "current")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(v_in=np.ones(5), t=np.arange(6.0)), r"'bad'.*column 'v_in' has 5 samples but column 't' has 6"),
        (dict(v_in=np.ones(1), t=np.zeros(1)), r"experiment 'bad'.*column 't' has 1 sample"),
        (dict(v_in=np.ones((4, 2)), t=np.arange(4.0)), r"column 'v_in' must be 1-D, got shape \(4, 2\)"),
        (dict(v_in=np.array(["a", "b"]), t=np.arange(2.0)), r"column 'v_in' is not numeric"),
        (dict(v_in=np.ones(4) + 1j, t=np.arange(4.0)), r"column 'v_in' is complex"),
        (dict(v_in=np.ones(4), t=np.array([0.0, 1.0, 1.0, 2.0])), r"column 't' is not strictly increasing: t\[2\]"),
        (dict(v_in=np.ones(4), t=np.array([0.0, 1.0, 2.5, 3.0])), r"column 't' is not uniformly.*t\[2\] - t\[1\]"),
        (dict(v_in=np.ones(4), t=np.arange(4.0), flux=np.ones(4)), r"channel\(s\) \['flux'\]; allowed.*'current'"),
    ],
)
def test_experiment_rejects(kwargs, match):
    with pytest.raises(PiezojaxValueError, match=match):
        Experiment.from_arrays(name="bad", **kwargs)


def test_experiment_nan_names_column_and_row():
    t = np.arange(6.0)
    f = np.ones(6)
    f[3] = np.nan
    with pytest.raises(PiezojaxValueError, match=r"experiment 'x'.*column 'force'.*at row 3"):
        Experiment.from_arrays(t=t, v_in=np.ones(6), force=f, name="x")
    v = np.ones(6)
    v[5] = np.inf
    with pytest.raises(PiezojaxValueError, match=r"column 'v_in'.*\(inf\) at row 5"):
        Experiment.from_arrays(t=t, v_in=v)


def test_uniformity_tolerance():
    # Rounded stamps are accepted and replaced by their uniform grid: arange-like rounding, float32 stamps, epoch-scale
    # times, jitter up to 1e-3·dt. A larger jitter, a gap and a change of rate are errors that say which, with the
    # size and place of the worst step.
    t = np.arange(10_000) * 1e-4 + 1000.0
    e = Experiment.from_arrays(t=t, v_in=np.zeros_like(t))
    np.testing.assert_array_equal(e.t, t)  # exact grids are kept bit for bit
    for stamps, dt in (((np.arange(50_000) * 2e-4).astype(np.float32), 2e-4), (np.arange(10_000) * 2e-4 + 1.7e9, 2e-4),
                       (t + 5e-8 * np.sin(np.arange(10_000)), 1e-4)):
        e = Experiment.from_arrays(t=stamps, v_in=np.zeros(stamps.size))
        assert e.dt == pytest.approx(dt, rel=1e-6)
        np.testing.assert_allclose(e.t, np.asarray(stamps, np.float64), rtol=0, atol=5e-3 * e.dt)
    t2 = t.copy()
    t2[7000] += 2e-7
    with pytest.raises(PiezojaxValueError, match=r"t\[7000\] - t\[6999\] = .* at row 7000 \(jitter of 0.002·dt"):
        Experiment.from_arrays(t=t2, v_in=np.zeros_like(t))
    gap = np.delete(t, [5000, 5001])
    with pytest.raises(PiezojaxValueError, match=r"t\[5000\] - t\[4999\] = .*3·dt.*a gap: about 2 sample\(s\) missing"):
        Experiment.from_arrays(t=gap, v_in=np.zeros_like(gap))
    fast = np.concatenate([t[:5000], t[4999] + 0.5e-4 * np.arange(1, 1001)])
    with pytest.raises(PiezojaxValueError, match=r"not uniformly sampled.*change of rate"):
        Experiment.from_arrays(t=fast, v_in=np.zeros_like(fast))


def test_slice_partitions_record(rng):
    e = _make(rng, n=1000, dt=1e-3)  # t = 0 … 0.999, rounding error in k*1e-3
    a, b = e.slice(None, 0.3), e.slice(0.3, None)
    assert a.n == 300 and b.n == 700
    np.testing.assert_array_equal(np.concatenate([a.t, b.t]), e.t)
    np.testing.assert_array_equal(np.concatenate([a["force"], b["force"]]), e["force"])
    m = e.slice(0.1, 0.2)
    assert m.n == 100 and m.t[0] == e.t[100] and m.name == "exp[0.1:0.2]"
    with pytest.raises(PiezojaxValueError, match="keeps 1 sample"):
        e.slice(0.5, 0.5005)
    with pytest.raises(PiezojaxValueError, match="keeps 0 sample"):
        e.slice(5.0, 6.0)


# --------------------------------------------------------------------------------------------------------- file formats


@pytest.mark.parametrize("suffix", [".csv", ".npz", ".h5", ".hdf5", ".mat"])
def test_round_trip(tmp_path, rng, suffix):
    e = _make(rng, channels=CHANNELS)
    p = tmp_path / f"run{suffix}"
    save_experiment(e, p)
    back = load_experiment(p)
    assert back.name == "run" and back.source == str(p)
    _assert_same(e, back)
    assert _no_temp_files(tmp_path) == []
    # subset of channels, and the name argument
    e2 = _make(rng, channels=("charge",))
    save_experiment(e2, p)  # overwrite in place
    back2 = load_experiment(p, name="renamed")
    assert back2.name == "renamed" and back2.channel_names == ("charge",)
    _assert_same(e2, back2)


def test_save_experiment_unit_labels(tmp_path, rng):
    """`units` relabels columns (a force-driven model's input) in the CSV header and the HDF5 attributes; the values
    are unchanged and the file reads back as before. A label for a column the experiment lacks is refused."""
    e = _make(rng)
    save_experiment(e, tmp_path / "f.csv", units={"v_in": "N"})
    head = (tmp_path / "f.csv").read_text().splitlines()[0]
    assert "v_in [N]" in head and "displacement [m]" in head
    _assert_same(e, load_experiment(tmp_path / "f.csv"))
    save_experiment(e, tmp_path / "f.h5", units={"v_in": "N"})
    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert f["v_in"].attrs["units"] == "N" and f["displacement"].attrs["units"] == "m"
    for bad in ({"charge": "C"}, {"v_in": ""}, {"v_in": 3}, "N", ["v_in"]):
        with pytest.raises(PiezojaxValueError, match="`units`"):
            save_experiment(e, tmp_path / "g.csv", units=bad)
    assert not (tmp_path / "g.csv").exists()


def test_hdf5_group(tmp_path, rng):
    e = _make(rng)
    p = tmp_path / "g.h5"
    save_experiment(e, p, group="run3")
    with h5py.File(p, "r") as f:
        assert list(f) == ["run3"] and f["run3/displacement"].attrs["units"] == "m"
    _assert_same(e, load_experiment(p, group="run3"))
    with pytest.raises(PiezojaxValueError, match=r"g\.h5.*no group 'run4'.*\['run3'\]"):
        load_experiment(p, group="run4")
    with pytest.raises(PiezojaxValueError, match=r"g\.h5.*no datasets at the root.*groups at the root: \['run3'\]"):
        load_experiment(p)  # root has only the group


def test_mat_v5_from_matlab_layouts(tmp_path, rng):
    # Row vectors (1×n) and column vectors (n×1) as MATLAB users save them.
    e = _make(rng, channels=("v_out",))
    p = tmp_path / "m.mat"
    scipy.io.savemat(p, {"t": e.t[None, :], "v_in": e.v_in[:, None], "v_out": e["v_out"]})
    _assert_same(e, load_experiment(p))


def test_mat_v73_is_hdf5(tmp_path, rng):
    # MATLAB v7.3: an HDF5 file with a 512-byte user block, column-major (so n×1 vectors appear as 1×n) and a
    # '#refs#' group.
    e = _make(rng, channels=("current",))
    p = tmp_path / "v73.mat"
    with h5py.File(p, "w", userblock_size=512) as f:
        for k, v in e.columns().items():
            ds = f.create_dataset(k, data=v[None, :])
            ds.attrs["MATLAB_class"] = np.bytes_("double")
        f.create_group("#refs#")
    with open(p, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Sun Nov 22 2026 HDF5 schema 1.00 .")
    _assert_same(e, load_experiment(p))


def test_csv_comments_blank_lines_and_extra_columns(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text(
        "# bench A, 2026-11-22\n"
        "t, v_in ,force,temperature\n"
        "0.0,1.0,0.5,20\n"
        "# a comment between rows\n"
        "\n"
        "0.1,2.0,0.25,21\n"
        "0.2,3.0,0.125,22\n"
    )
    with pytest.raises(PiezojaxValueError, match=r"c\.csv.*unknown column\(s\) \['temperature'\].*ignore_extra"):
        load_experiment(p)
    e = load_experiment(p, ignore_extra=True)
    np.testing.assert_array_equal(e["force"], [0.5, 0.25, 0.125])
    np.testing.assert_array_equal(e.v_in, [1.0, 2.0, 3.0])
    assert math.isclose(e.dt, 0.1)
    # one mapping reads a training file and an input-only file; a file with some renamed channels must have all
    mapping = {"time_ms": "t", "drive_V": "v_in", "pos_um": "displacement", "f_N": "force"}
    p.write_text("time_ms,drive_V\n0,1\n1,2\n2,3\n")
    assert load_experiment(p, columns=mapping, units={"t": "ms"}).channel_names == ()
    p.write_text("time_ms,drive_V,pos_um\n0,1,5\n1,2,6\n2,3,7\n")
    with pytest.raises(PiezojaxValueError, match=r"`columns` renames \['f_N'\], which the file does not have"):
        load_experiment(p, columns=mapping, units={"t": "ms"})
    # an error about a renamed column, in converted units, says how the file was read
    p.write_text("time_ms,drive_V\n0,1\n1,2\n2.5,3\n3,4\n")
    with pytest.raises(PiezojaxValueError, match=r"'t' is not uniformly sampled.*\(t = file column 'time_ms'; "
                       r"v_in = file column 'drive_V'; converted to SI: t from ms\)"):
        load_experiment(p, columns={"time_ms": "t", "drive_V": "v_in"}, units={"t": "ms"})
    # pandas' DataFrame.to_csv writes its index first, in a column without a name
    p.write_text(",t,v_in,force\n0,0.0,1.0,0.5\n1,0.1,2.0,0.25\n")
    with pytest.raises(PiezojaxValueError, match=r"unknown column\(s\) \['\(unnamed column 1\)'\].*ignore_extra"):
        load_experiment(p)
    np.testing.assert_array_equal(load_experiment(p, ignore_extra=True)["force"], [0.5, 0.25])
    # every line ending with the delimiter (some spreadsheet exports) adds no column
    p.write_text("t,v_in,force,\n0.0,1.0,0.5,\n0.1,2.0,0.25,\n")
    assert load_experiment(p).channel_names == ("force",)


@pytest.mark.parametrize(
    "text, match",
    [
        ("t,force\n0,1\n1,2\n", r"required column\(s\) \['v_in'\] missing"),
        ("v_in,force\n0,1\n1,2\n", r"required column\(s\) \['t'\] missing"),
        ("t,v_in,force,flux\n0,1,2,3\n1,2,3,4\n", r"unknown column\(s\) \['flux'\]"),
        ("t,v_in,force\n0,1,2\n1,2,nan\n2,3,4\n", r"line 3, column 'force' holds a non-finite value \(nan\)"),
        ("t,v_in\n0,1\n# note\n0,2\n1,3\n", r"column 't' \(the time\) must increase from line to line: line 4 holds "
                                             r"0.0, line 2 0.0"),
        ("t,v_in,force\n0,1,2\n1,2,\n2,3,4\n", r"cannot parse numbers: line 3, column 'force' holds ''"),
        ("# note\nt,v_in,force\n0,1,2\n\n1,x1,3\n", r"cannot parse numbers: line 5, column 'v_in' holds 'x1'"),
        ("t,v_in,force\n0,1,2\n1,2\n", r"line 3 has 2 fields but the header names 3"),
        ("t,v_in\n0,1\n1,2\n3,3\n", r"column 't' is not uniformly sampled"),
        ("t,v_in\n0,1\n", r"column 't' has 1 sample"),
        ("t,v_in\n", r"column 't' has 0 sample"),
        ("# only a comment\n", r"no header row"),
        ("t,v_in,t\n0,1,0\n1,1,1\n", r"duplicate column\(s\) \['t'\]"),
    ],
)
def test_csv_bad_input_names_file_and_column(tmp_path, text, match):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(PiezojaxValueError, match=r"bad\.csv") as info:
        load_experiment(p)
    assert info.match(match)


@pytest.mark.parametrize("suffix", [".npz", ".h5", ".mat"])
def test_binary_formats_bad_columns(tmp_path, suffix):
    t = np.arange(5.0) * 1e-3
    v = np.ones(5)
    p = tmp_path / f"b{suffix}"

    def write(cols):
        if suffix == ".npz":
            np.savez(p, **cols)
        elif suffix == ".h5":
            with h5py.File(p, "w") as f:
                for k, x in cols.items():
                    f[k] = x
        else:
            scipy.io.savemat(p, cols)

    write({"t": t, "force": v})
    with pytest.raises(PiezojaxValueError, match=rf"b\{suffix}.*required column\(s\) \['v_in'\] missing"):
        load_experiment(p)
    write({"t": t, "v_in": v, "strain": v})
    with pytest.raises(PiezojaxValueError, match=rf"b\{suffix}.*unknown column\(s\) \['strain'\]"):
        load_experiment(p)
    assert load_experiment(p, ignore_extra=True).n == 5
    write({"t": t, "v_in": v, "force": np.ones(4)})
    with pytest.raises(PiezojaxValueError, match=rf"b\{suffix}.*column 'force' has 4 samples but column 't' has 5"):
        load_experiment(p)
    bad = v.copy()
    bad[2] = np.nan
    write({"t": t, "v_in": v, "charge": bad})
    with pytest.raises(PiezojaxValueError, match=rf"b\{suffix}.*column 'charge'.*at row 2"):
        load_experiment(p)
    write({"t": np.array([0.0, 1.0, 2.0, 4.0, 5.0]) * 1e-3, "v_in": v})
    with pytest.raises(PiezojaxValueError, match=rf"b\{suffix}.*column 't' is not uniformly sampled"):
        load_experiment(p)


@pytest.mark.parametrize("suffix", [".csv", ".npz", ".h5", ".hdf5", ".mat"])
def test_corrupt_and_missing_files(tmp_path, rng, suffix):
    p = tmp_path / f"broken{suffix}"
    save_experiment(_make(rng), p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 3])  # truncated, as after a crash of a writer without atomic writes
    if suffix != ".csv":
        with pytest.raises(PiezojaxValueError, match=rf"broken\{suffix}"):
            load_experiment(p)
    p.write_bytes(b"\x00\xff garbage \x89PNG" * 7)
    with pytest.raises(PiezojaxValueError, match=rf"broken\{suffix}"):
        load_experiment(p)
    with pytest.raises(PiezojaxValueError, match=r"nothere.*does not exist"):
        load_experiment(tmp_path / f"nothere{suffix}")


def test_zip_that_is_not_npz(tmp_path):
    # A zip whose members are not .npy arrays (np.load hands them back as bytes), and one with a broken .npy header.
    p = tmp_path / "z.npz"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("t.npy", b"not an npy file")
        z.writestr("v_in.npy", b"not an npy file")
    with pytest.raises(PiezojaxValueError, match=r"z\.npz.*column 't' is not numeric"):
        load_experiment(p)
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("t.npy", b"\x93NUMPY\x01\x00\x10\x00{'descr': garbage")
        z.writestr("v_in.npy", b"\x93NUMPY\x01\x00\x10\x00{'descr': garbage")
    with pytest.raises(PiezojaxValueError, match=r"z\.npz.*cannot read it as \.npz"):
        load_experiment(p)


def test_unknown_suffix(tmp_path, rng):
    with pytest.raises(PiezojaxValueError, match=r"data\.xlsx.*unsupported suffix '\.xlsx'.*'\.csv'.*'\.mat'"):
        load_experiment(tmp_path / "data.xlsx")
    with pytest.raises(PiezojaxValueError, match=r"out\.txt.*unsupported suffix"):
        save_experiment(_make(rng), tmp_path / "out.txt")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------------------ Dataset


@pytest.fixture(scope="module")
def dataset():
    rng = np.random.default_rng(7)
    return Dataset(
        [
            _make(rng, n=100, name="a", channels=("v_out", "displacement")),
            _make(rng, n=60, name="b", channels=("force",)),
            _make(rng, n=100, name="c", channels=("displacement", "v_out")),
            _make(rng, n=100, dt=2e-4, name="d", channels=("v_out", "displacement")),
            _make(rng, n=100, name="e", channels=("v_out", "displacement"), t0=5.0),
        ]
    )


def test_dataset_sequence(dataset):
    assert len(dataset) == 5
    assert [e.name for e in dataset] == ["a", "b", "c", "d", "e"]
    assert dataset[1] is dataset["b"] and dataset[-1].name == "e"
    assert dataset.names == ("a", "b", "c", "d", "e")
    assert isinstance(dataset[1:3], Dataset) and dataset[1:3].names == ("b", "c")
    assert "c" in dataset and "z" not in dataset
    assert dataset.channels == ("v_out", "displacement", "force")  # CHANNELS order
    with pytest.raises(KeyError, match="no experiment named 'z'"):
        dataset["z"]
    with pytest.raises(AttributeError):
        dataset._experiments = ()
    assert "5 experiments" in repr(dataset)


def test_dataset_rejects_duplicates_and_empty(rng):
    e = _make(rng)
    with pytest.raises(PiezojaxValueError, match=r"duplicate experiment name\(s\) \['exp'\]"):
        Dataset([e, e])
    with pytest.raises(PiezojaxValueError, match="must not be empty"):
        Dataset([])
    with pytest.raises(PiezojaxValueError, match=r"`experiments\[1\]` must be an Experiment"):
        Dataset([e, np.zeros(3)])


def test_dataset_require(dataset):
    assert dataset[::2].require(["v_out", "displacement"]) is not None
    with pytest.raises(PiezojaxValueError, match=r"'b' lacks \['v_out'\]") as info:
        dataset.require("v_out")
    assert "'a'" not in str(info.value)
    with pytest.raises(PiezojaxValueError, match=r"'a' lacks \['force'\].*'c' lacks \['force'\]"):
        dataset.require(["force"])
    with pytest.raises(PiezojaxValueError, match=r"unknown channel\(s\) \['temp'\]"):
        dataset.require(["temp"])


def test_dataset_from_files(tmp_path, rng):
    (tmp_path / "r1").mkdir()
    (tmp_path / "r2").mkdir()
    e1, e2, e3 = _make(rng, n=50), _make(rng, n=70, channels=("charge",)), _make(rng, n=50)
    save_experiment(e1, tmp_path / "r1" / "data.csv")
    save_experiment(e2, tmp_path / "r2" / "data.csv")
    save_experiment(e3, tmp_path / "other.h5")
    ds = Dataset.from_files([tmp_path / "r1" / "data.csv", tmp_path / "r2" / "data.csv", tmp_path / "other.h5"])
    assert ds.names == ("r1/data", "r2/data", "other")
    _assert_same(e2, ds["r2/data"])
    save_experiment(e1, tmp_path / "other.npz")
    ds2 = Dataset.from_files([tmp_path / "other.h5", tmp_path / "other.npz"])
    assert ds2.names == ("other.h5", "other.npz")
    with pytest.raises(PiezojaxValueError, match=r"other.h5' is given twice$"):
        Dataset.from_files([tmp_path / "other.h5", tmp_path / "other.h5"])
    # a group concerns the HDF5 and .mat files only; with none among them it is a mistake
    save_experiment(e1, tmp_path / "grouped.h5", group="run1")
    ds3 = Dataset.from_files([tmp_path / "grouped.h5", tmp_path / "other.npz"], group="run1")
    _assert_same(e1, ds3["grouped"])
    with pytest.raises(PiezojaxValueError, match=r"applies to HDF5 and .mat files.*other.npz"):
        Dataset.from_files([tmp_path / "other.npz"], group="run1")
    with pytest.raises(PiezojaxValueError, match=r"grouped.h5.*no datasets at the root.*\['run1'\]"):
        Dataset.from_files([tmp_path / "grouped.h5"])


# ---------------------------------------------------------------------------------------------------------- atomic io


def test_atomic_write_bytes_and_text(tmp_path):
    p = tmp_path / "out.bin"
    atomic_write_bytes(p, b"first")
    atomic_write_bytes(p, b"second")
    assert p.read_bytes() == b"second"
    umask = os.umask(0)
    os.umask(umask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask  # as open() would create it, not mkstemp's 0600
    os.chmod(p, 0o640)
    atomic_write_text(p, "thïrd")
    assert p.read_text(encoding="utf-8") == "thïrd"
    assert p.stat().st_mode & 0o777 == 0o640  # mode of the replaced file is kept
    assert _no_temp_files(tmp_path) == []


class _Boom(Exception):
    pass


def test_atomic_write_failure_leaves_old_content_and_no_temp(tmp_path, monkeypatch):
    p = tmp_path / "keep.txt"
    atomic_write_text(p, "old")

    def fail(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_text(p, "new")
    monkeypatch.undo()
    assert p.read_text() == "old"
    assert _no_temp_files(tmp_path) == []
    with pytest.raises(PiezojaxValueError, match="must be bytes"):
        atomic_write_bytes(p, "text")


def test_save_experiment_failure_is_atomic(tmp_path, rng, monkeypatch):
    p = tmp_path / "x.h5"
    e = _make(rng)
    save_experiment(e, p)
    before = p.read_bytes()

    def fail(self, name, data=None, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(h5py.Group, "create_dataset", fail)
    with pytest.raises(KeyboardInterrupt):
        save_experiment(_make(rng), p)
    monkeypatch.undo()
    assert p.read_bytes() == before
    assert _no_temp_files(tmp_path) == []


def test_unwritable_locations(tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    for bad in (tmp_path / "missing" / "out.json", f / "out.json"):
        with pytest.raises(PiezojaxValueError, match=str(bad)):
            check_writable(bad)
        with pytest.raises(PiezojaxValueError, match=str(bad)):
            atomic_write_text(bad, "x")
        with pytest.raises(PiezojaxValueError, match=str(bad)):
            save_json(bad, {})
        with pytest.raises(PiezojaxValueError, match=str(bad)):
            with atomic_directory(bad):
                raise AssertionError("body must not run")
    assert check_writable(tmp_path / "new.json") == tmp_path / "new.json"
    with pytest.raises(PiezojaxValueError, match="a directory of that name exists"):
        atomic_write_text(tmp_path, "x")


def test_atomic_directory_create(tmp_path):
    out = tmp_path / "run"
    with atomic_directory(out) as d:
        assert d.parent == tmp_path and d != out
        (d / "a.txt").write_text("A")
        assert not out.exists()  # nothing visible until the end
    assert (out / "a.txt").read_text() == "A"
    assert _no_temp_files(tmp_path) == []
    with pytest.raises(PiezojaxValueError, match=r"already exists; pass overwrite=True"):
        with atomic_directory(out):
            raise AssertionError("must fail before the body runs")
    assert (out / "a.txt").read_text() == "A"


@pytest.mark.parametrize("exc", [KeyboardInterrupt, _Boom])
def test_atomic_directory_interrupted_leaves_nothing(tmp_path, exc):
    out = tmp_path / "run"
    with pytest.raises(exc):
        with atomic_directory(out) as d:
            (d / "partial.txt").write_text("half")
            raise exc()
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("exc", [KeyboardInterrupt, _Boom])
def test_atomic_directory_overwrite_keeps_old_on_failure(tmp_path, exc):
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(exc):
        with atomic_directory(out, overwrite=True) as d:
            (d / "new.txt").write_text("new")
            raise exc()
    assert sorted(os.listdir(out)) == ["old.txt"] and (out / "old.txt").read_text() == "old"
    assert _no_temp_files(tmp_path) == []


def test_atomic_directory_overwrite_replaces(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_directory(out, overwrite=True) as d:
        (d / "new.txt").write_text("new")
        assert (out / "old.txt").exists()  # old stays until the new one is complete
    assert sorted(os.listdir(out)) == ["new.txt"]
    assert _no_temp_files(tmp_path) == []


def test_atomic_directory_overwrite_fallback_without_exchange(tmp_path, monkeypatch):
    # Where renameat2 is unavailable: two renames, old parked aside, then removed.
    import fitting.files as fio

    monkeypatch.setattr(fio, "_exchange", lambda a, b: False)
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_directory(out, overwrite=True) as d:
        (d / "new.txt").write_text("new")
    assert sorted(os.listdir(out)) == ["new.txt"]
    assert _no_temp_files(tmp_path) == []

    # If the second rename fails, the old directory is put back.
    real_rename = os.rename
    calls = []

    def flaky(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_rename(src, dst)

    monkeypatch.setattr(os, "rename", flaky)
    with pytest.raises(KeyboardInterrupt):
        with atomic_directory(out, overwrite=True) as d:
            (d / "newer.txt").write_text("newer")
    monkeypatch.undo()
    assert sorted(os.listdir(out)) == ["new.txt"]
    assert _no_temp_files(tmp_path) == []

    # A folder that cannot be moved (an immutable one): one message naming it, not the temporary path
    def refused(src, dst):
        if os.fspath(src) == os.fspath(out):
            raise PermissionError(1, "Operation not permitted", str(src), None, str(dst))
        return real_rename(src, dst)

    monkeypatch.setattr(fio, "_exchange", lambda a, b: False)
    monkeypatch.setattr(os, "rename", refused)
    with pytest.raises(PiezojaxValueError, match=r"cannot replace directory '.*run': Operation not permitted; it "
                       r"was left as it was and this run's outputs were discarded$"):
        with atomic_directory(out, overwrite=True) as d:
            (d / "newest.txt").write_text("newest")
    monkeypatch.undo()
    assert sorted(os.listdir(out)) == ["new.txt"]
    assert _no_temp_files(tmp_path) == []


def test_save_json_converts_arrays_and_nonfinite(tmp_path):
    p = tmp_path / "r.json"
    obj = {
        "rmse": np.float64(1.5e-7),
        "n": np.int64(3),
        "ok": np.bool_(True),
        "params": jnp.array([1.0, jnp.nan, 3.0]),
        "cov": np.array([[1.0, np.inf], [-np.inf, 2.0]]),
        "nan": float("nan"),
        "names": ("a", "b"),
        "path": tmp_path,
        1: [np.float32(0.5), None],
    }
    save_json(p, obj)
    back = json.loads(p.read_text())
    assert back == {
        "rmse": 1.5e-7,
        "n": 3,
        "ok": True,
        "params": [1.0, None, 3.0],
        "cov": [[1.0, None], [None, 2.0]],
        "nan": None,
        "names": ["a", "b"],
        "path": str(tmp_path),
        "1": [0.5, None],
    }
    assert "NaN" not in p.read_text() and "Infinity" not in p.read_text()
    with pytest.raises(PiezojaxValueError, match=r"obj\['bad'\]\[1\] of type object"):
        save_json(p, {"bad": [1, object()]})
    assert json.loads(p.read_text())["n"] == 3  # failed save left the previous file
    assert _no_temp_files(tmp_path) == []


def test_pickle_and_replace(rng, dataset):
    import copy
    import dataclasses
    import pickle

    e = _make(rng)
    back = pickle.loads(pickle.dumps(e))
    assert back.name == e.name
    _assert_same(e, back)
    _assert_same(e, copy.deepcopy(e))
    ds = pickle.loads(pickle.dumps(dataset))
    assert ds.names == dataset.names and [e.n for e in ds] == [e.n for e in dataset]
    # dataclasses.replace revalidates
    assert dataclasses.replace(e, name="renamed").name == "renamed"
    with pytest.raises(PiezojaxValueError, match=r"column 'v_in' has 3 samples"):
        dataclasses.replace(e, v_in=np.ones(3))


def test_mat_v5_struct_group(tmp_path, rng):
    e = _make(rng, channels=("displacement",))
    p = tmp_path / "s.mat"
    scipy.io.savemat(p, {"run1": {k: v[:, None] for k, v in e.columns().items()}, "note": np.ones(2)})
    _assert_same(e, load_experiment(p, group="run1"))
    with pytest.raises(PiezojaxValueError, match=r"s\.mat.*no struct variable 'run2'.*\['run1'\]"):
        load_experiment(p, group="run2")


@pytest.mark.parametrize("delim", [",", "\t", ";"])
def test_csv_delimiters_and_quoted_header(tmp_path, delim):
    p = tmp_path / "d.csv"
    rows = ["0.0", "0.5"], ["1e-3", "-0.25"], ["2e-3", "0.125"]
    p.write_text(delim.join(['"t"', '"v_in"']) + "\n" + "\n".join(delim.join(r) for r in rows) + "\n")
    e = load_experiment(p)
    np.testing.assert_array_equal(e.v_in, [0.5, -0.25, 0.125])
    np.testing.assert_array_equal(e.t, [0.0, 1e-3, 2e-3])


def test_atomic_directory_mode(tmp_path):
    umask = os.umask(0)
    os.umask(umask)
    with atomic_directory(tmp_path / "run") as d:
        (d / "x").write_text("x")
    assert (tmp_path / "run").stat().st_mode & 0o777 == 0o777 & ~umask  # not mkdtemp's 0700


def test_read_settings_of_a_fit_apply_to_the_files_they_fit(tmp_path):
    """`predict` reads new files the way the fit read its own: the field positions of a header-less CSV do not apply
    to a file with named columns, and `sample_rate` (for files without 't') is refused only where a file's own 't'
    disagrees with it (both had refused a file the fit's settings did not concern)."""
    t = np.arange(50) / 750.0
    v = np.sin(2 * np.pi * 5 * t)
    np.savez(tmp_path / "named.npz", t=t, v_in=v, displacement=1e-6 * v)
    exp = load_experiment(tmp_path / "named.npz", columns={"2": "v_in", "3": "displacement"}, sample_rate=750.0)
    np.testing.assert_allclose(exp.t, t)
    np.testing.assert_allclose(exp["displacement"], 1e-6 * v)
    with pytest.raises(PiezojaxValueError, match=r"sampled at 750 Hz, but `sample_rate` = 1000 Hz"):
        load_experiment(tmp_path / "named.npz", sample_rate=1000.0)
    # a header-less CSV still reads its fields by position, and its times from the sample rate
    np.savetxt(tmp_path / "fields.csv", np.column_stack([v, 1e-6 * v]), delimiter=",")
    exp = load_experiment(tmp_path / "fields.csv", columns={"1": "v_in", "2": "displacement"}, sample_rate=750.0)
    np.testing.assert_allclose(exp.t, t, atol=1e-15)
