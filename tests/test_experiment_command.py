"""The reproductions' shared command-line plumbing (`experiments._command`): the output folder is checked before any
work and replaces only the experiment's own earlier output, Ctrl-C ends with 130 and writes nothing, bad input ends
with 2 and one line."""

import argparse
import json
import types

import pytest

import fitting
from experiments import _command, calibrate, piezo_150v_1hz
from piezojax import PiezojaxValueError

KIND = "experiments.calibrate"


def _users_folder(tmp_path):
    folder = tmp_path / "mine"
    (folder / "sub").mkdir(parents=True)
    (folder / "run1.csv").write_text("1,2,3\n")
    (folder / "sub" / "notes.txt").write_text("keep me\n")
    return folder


def test_output_folder_refuses_a_folder_it_did_not_write(tmp_path):
    folder = _users_folder(tmp_path)
    with pytest.raises(PiezojaxValueError, match=r"mine.*no piezojax marker.*`python -m experiments\.calibrate`"):
        _command.output_folder(str(folder), KIND)
    assert (folder / "run1.csv").read_text() == "1,2,3\n" and (folder / "sub" / "notes.txt").exists()
    # the command line of the experiment refuses it before any work, and deletes nothing
    with pytest.raises(PiezojaxValueError, match="mine"):
        calibrate.main(["--quick", "--out", str(folder)])
    assert sorted(p.name for p in folder.iterdir()) == ["run1.csv", "sub"]


def test_output_folder_replaces_only_its_own_earlier_output(tmp_path):
    out = tmp_path / "out"
    assert _command.output_folder(str(out), KIND) == out  # absent: fine
    for version in ("first", "second"):
        with _command.writing(out, KIND) as tmp:
            (tmp / "table.txt").write_text(version)
        assert (out / "table.txt").read_text() == version
        assert json.loads((out / fitting.files.MARKER).read_text())["kind"] == KIND
        _command.output_folder(str(out), KIND)  # its own earlier output: may be replaced
    # another experiment's output is not this one's
    with pytest.raises(PiezojaxValueError, match=r"holds the output of `python -m experiments\.calibrate`"):
        _command.output_folder(str(out), "experiments.chen2014")
    # a file the user added is named, and the folder is not replaced
    (out / "my_notes.txt").write_text("mine")
    with pytest.raises(PiezojaxValueError, match="my_notes.txt"):
        _command.output_folder(str(out), KIND)
    assert (out / "my_notes.txt").exists()


def test_output_folder_parents(tmp_path, monkeypatch):
    with pytest.raises(PiezojaxValueError, match="does not exist"):
        _command.output_folder(str(tmp_path / "missing" / "out"), KIND)
    assert not (tmp_path / "missing").exists()
    monkeypatch.chdir(tmp_path)  # the experiment's own default folder gets its parents (results/ in a fresh clone)
    _command.output_folder("results/x", KIND, default="results/x")
    assert (tmp_path / "results").is_dir() and not (tmp_path / "results" / "x").exists()
    with pytest.raises(PiezojaxValueError, match="empty"):
        _command.output_folder("", KIND)
    with pytest.raises(PiezojaxValueError, match="working directory"):
        _command.output_folder(".", KIND)


def test_run_exit_status(capsys):
    assert _command.run(lambda: {"done": True}, "prog") == 0

    def bad():
        raise PiezojaxValueError("--data 'x.csv': no such file")

    assert _command.run(bad, "prog") == 2
    assert capsys.readouterr().err == "prog: error: --data 'x.csv': no such file\n"

    def interrupted():
        raise KeyboardInterrupt

    assert _command.run(interrupted, "prog") == 130
    assert "interrupted; nothing written" in capsys.readouterr().err

    def bug():
        raise RuntimeError("bug")

    with pytest.raises(RuntimeError):  # anything else is a bug: its traceback is kept
        _command.run(bug, "prog")


def test_an_interrupted_fit_writes_nothing(tmp_path, monkeypatch):
    """Ctrl-C during the main command's joint fit: `fitting.fit` returns its last point with code "interrupted";
    the command stops there (exit 130) instead of reporting it, and an earlier output stays as it was."""
    out = tmp_path / "cal"
    with _command.writing(out, KIND) as tmp:
        (tmp / "table.txt").write_text("the earlier, complete run")
    bench = types.SimpleNamespace(observer=lambda **_: None)
    monkeypatch.setattr(calibrate, "make_records", lambda quick: ([None, None], [], bench))
    monkeypatch.setattr(calibrate, "joint_start", lambda staged: None)
    monkeypatch.setattr(fitting, "staged_ivan2009", lambda *a, **k: None)
    monkeypatch.setattr(fitting, "fit", lambda *a, **k: types.SimpleNamespace(code="interrupted"))
    assert _command.run(lambda: calibrate.main(["--quick", "--out", str(out)]), "calibrate") == 130
    assert (out / "table.txt").read_text() == "the earlier, complete run"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal"]  # no temporary folder left


@pytest.mark.parametrize("argv, message", [
    (["--max-steps", "0"], "--max-steps: expected a positive integer, got 0"),
    (["--max-steps", "x"], "--max-steps: expected a positive integer, got 'x'"),
])
def test_calibrate_refuses_bad_arguments(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        calibrate.main(argv)
    assert info.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--n-elements", "-2"], "--n-elements: expected a positive integer, got -2"),
    (["--models", ","], "--models: no model"),
    (["--models", "bw"], "--models: unknown model 'bw' (choose from PI, BW, MS)"),
    (["--data", "/nonexistent/file.csv"], "--data: no such file: '/nonexistent/file.csv'"),
])
def test_piezo_150v_refuses_bad_arguments(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        piezo_150v_1hz.main(argv)
    assert info.value.code == 2 and message in capsys.readouterr().err


def test_positive_int():
    assert _command.positive_int("3") == 3
    for text in ("0", "-1", "1.5", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            _command.positive_int(text)
