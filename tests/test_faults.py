"""Faults and tampered files: a fit folder edited by hand, a full disk, a stale temporary whose process id now
belongs to another process, a CONFIG with a byte-order mark, a model file without its summary, a damaged
compilation cache. Each ends with one line naming the file, key or path (exit 2 on the command line), and nothing
is written or removed but the temporaries of dead runs.
"""

import errno
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj
from fitting.cli import main

DT = 1e-3
N = 300
CONFIG = '[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[fit]\nmax_steps = 5\n'


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A data file and one fit folder made from it."""
    d = tmp_path_factory.mktemp("faults")
    t = np.arange(N) * DT
    v = 30 * np.sin(2 * np.pi * 3 * t)
    x = 1e-8 * v + 2e-9 * np.abs(v)
    np.savetxt(d / "ok.csv", np.column_stack([t, v, x]), delimiter=",", header="t,v_in,displacement", comments="")
    (d / "pi.toml").write_text(CONFIG)
    assert main(["fit", str(d / "pi.toml"), str(d / "ok.csv"), "--out", str(d / "fit"), "--quiet",
                 "--no-figures"]) in (0, 1)
    return d


def _nan_model(fit):
    """model.eqx in a valid format, every value NaN."""
    like = fitting.load_config(fit / "config.toml").build(None)
    nan = jax.tree_util.tree_map(lambda x: jnp.full_like(x, jnp.nan) if eqx.is_inexact_array(x) else x, like)
    eqx.tree_serialise_leaves(fit / "model.eqx", nan)


def _settings(key, value):
    def edit(fit):
        result = json.loads((fit / "result.json").read_text())
        result["cli"]["data_settings"][key] = value
        (fit / "result.json").write_text(json.dumps(result))

    return edit


def _binary_config(fit):
    (fit / "config.toml").write_bytes(bytes(range(256)))


def _not_json(fit):
    (fit / "result.json").write_text("{ truncated")


def _no_result(fit):
    (fit / "result.json").unlink()


TAMPERED = {
    # edit of the fit folder, what the one line names
    "every value of model.eqx NaN": (_nan_model, ["model.eqx", "is not finite", "refit"]),
    "units a string": (_settings("units", "um"), ["result.json", "cli.data_settings.units", "must be an object"]),
    "sample_rate not a number": (_settings("sample_rate", "x"), ["result.json", "cli.data_settings.sample_rate",
                                                                 "positive number"]),
    "columns a number": (_settings("columns", 5), ["result.json", "cli.data_settings.columns", "must be an object"]),
    "an unknown data setting": (_settings("colour", "red"), ["result.json", "cli.data_settings", "'colour'"]),
    "config.toml binary": (_binary_config, ["config.toml", "cannot read"]),
    "result.json not JSON": (_not_json, ["result.json", "not valid JSON"]),
    "result.json missing": (_no_result, ["no result.json"]),
}


@pytest.mark.parametrize("case", list(TAMPERED))
def test_predict_from_a_tampered_fit_folder_names_the_file(bench, tmp_path, capsys, case):
    edit, fragments = TAMPERED[case]
    fit = tmp_path / "fit"
    shutil.copytree(bench / "fit", fit)
    edit(fit)
    before = {p.name: p.read_bytes() for p in fit.iterdir()}
    out = tmp_path / "pred"
    assert main(["predict", str(fit), str(bench / "ok.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("piezojax: error:"), err
    for fragment in fragments:
        assert fragment in err[0], (fragment, err[0])
    assert not out.exists() and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    assert {p.name: p.read_bytes() for p in fit.iterdir()} == before  # nothing in the fit folder touched
    # the library says the same
    with pytest.raises(pj.PiezojaxValueError) as e:
        fitting.load_fit(fit)
    assert fragments[0] in str(e.value)


def test_the_untampered_folder_loads_and_predicts(bench, tmp_path):
    fit = fitting.load_fit(bench / "fit")
    config, model = fit  # unpacks as `fitting.cli.load_fitted` returned
    assert config.outputs == ("displacement",) and fit.data_settings == {}
    assert fit.summary["cli"]["data_settings"] == {} and fit.path == bench / "fit"
    assert main(["predict", str(bench / "fit"), str(bench / "ok.csv"), "--out", str(tmp_path / "p")]) == 0
    with pytest.warns(DeprecationWarning, match="fitting.load_fit"):
        from fitting.cli import load_fitted

        assert load_fitted(bench / "fit")[0].outputs == config.outputs


def test_a_full_disk_names_the_output(bench, tmp_path, capsys, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(fitting.files, "save_json", full)
    out = tmp_path / "pred"
    assert main(["predict", str(bench / "fit"), str(bench / "ok.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and str(out) in err[0], err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_a_stale_temporary_whose_process_id_was_reused_is_cleaned(bench, tmp_path, capsys):
    """A temporary names its writer by process id and start time: a live process with that id that started at
    another time did not write it (the id was reused), so the temporary is a dead run's and is removed. One named in
    the older way (id only) by a live process is refused, and the message says how to clear it."""
    live = os.getppid()  # a live process other than this one
    out = tmp_path / "pred"
    stale = tmp_path / f".pred.tmp-{live}-s1-abcdefgh"  # started at tick 1: not that process
    stale.mkdir()
    (stale / "metrics.json").write_text("partial")
    args = ["predict", str(bench / "fit"), str(bench / "ok.csv"), "--out", str(out)]
    assert main(args) == 0
    assert not stale.exists() and out.is_dir()
    old_style = tmp_path / f".again.tmp-{live}-abcdefgh"
    old_style.mkdir()
    capsys.readouterr()
    assert main(args[:-1] + [str(tmp_path / "again")]) == 2
    err = capsys.readouterr().err
    assert f"another process (pid {live})" in err and f"remove '{old_style}'" in err
    assert old_style.exists()


def test_a_config_with_a_byte_order_mark_reads_as_without(tmp_path):
    (tmp_path / "bom.toml").write_bytes(b"\xef\xbb\xbf" + CONFIG.encode())
    with_bom = fitting.load_config(tmp_path / "bom.toml")
    plain = fitting.parse_config(CONFIG, "plain.toml")
    assert (with_bom.hysteresis, with_bom.hysteresis_options, with_bom.max_steps) == (
        plain.hysteresis, plain.hysteresis_options, plain.max_steps)


def test_load_model_without_its_summary_names_it(bench, tmp_path):
    shutil.copy(bench / "fit" / "model.eqx", tmp_path / "model.eqx")
    like = fitting.load_config(bench / "fit" / "config.toml").build(None)
    with pytest.raises(pj.PiezojaxValueError,
                       match="result.json' is missing"):
        fitting.load_model(tmp_path / "model.eqx", like=like)


def test_a_damaged_compilation_cache_entry_is_replaced(tmp_path):
    """JAX keeps an entry it cannot read and compiles the program again in every process; piezojax's cache writes
    the fresh compilation over it, so the next process reads it without a warning."""
    script = textwrap.dedent(f"""
        import warnings
        import jax, jax.numpy as jnp
        import piezojax as pj
        pj.enable_compilation_cache({str(tmp_path / "cache")!r})
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            jax.jit(lambda x: jnp.sin(x) * 3 + x ** 2)(jnp.arange(5.0)).block_until_ready()
        print(sum("compilation cache" in str(m.message) for m in w))
    """)

    def run():
        return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout

    assert run().split() == ["0"]
    entries = sorted((tmp_path / "cache").glob("*-cache"))
    assert entries
    for e in entries:
        e.write_bytes(b"damaged")
    assert int(run().split()[0]) >= 1  # JAX warns that it cannot read them, and compiles
    assert all(e.read_bytes() != b"damaged" for e in entries)  # ... and now they are replaced
    assert run().split() == ["0"]


def test_a_fit_folder_of_version_0_1_0_still_predicts(tmp_path, capsys):
    """A fit folder written by piezojax 0.1.0 (`tests/data/fit_0.1.0`, with the record it was fitted to and what
    0.1.0's `predict` wrote) is read and predicts the same numbers, in the fit's units."""
    data = Path(__file__).parent / "data"
    fit = tmp_path / "fit"
    shutil.copytree(data / "fit_0.1.0", fit)
    assert fitting.load_fit(fit).data_settings == {"units": {"displacement": "um"}}
    out = tmp_path / "pred"
    assert main(["predict", str(fit), str(data / "fit_0.1.0_record.csv"), "--out", str(out)]) == 0
    assert "reading the files in the fit's units (displacement=um)" in capsys.readouterr().err
    now = np.loadtxt(out / "fit_0.1.0_record.csv", delimiter=",", skiprows=2)
    then = np.loadtxt(data / "fit_0.1.0_predicted.csv", delimiter=",", skiprows=2)
    np.testing.assert_array_equal(now, then)
