"""A fit folder read back: `load_fit` validates the `config.toml`, `result.json` and `model.eqx` that `piezojax fit`
(or `Calibration.save`) wrote, as strictly as a CONFIG and data files, and returns the fitted model with how the fit
read its data."""

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.tree_util as jtu
import numpy as np

from piezojax import PiezojaxValueError

from ._config import ModelConfig, load_config
from ._data import parse_columns, parse_units
from ._problem import path_string
from ._results import load_model

DATA_SETTINGS = ("units", "columns", "group", "sample_rate", "ignore_extra")
"""The keys of a fit's `data_settings` (`result.json`'s `cli.data_settings`): CONFIG's `[data]` keys."""


@dataclasses.dataclass(frozen=True)
class FitFolder:
    """A fit folder read back by `load_fit`.

    - `path`: the folder.
    - `config`: its `config.toml` (`fitting.ModelConfig`): the model's structure, predictor and outputs.
    - `model`: the fitted model (unwrapped: physical values), ready for `fitting.predict` or `simulate`.
    - `summary`: `result.json` as a dict (the verdict, metrics, standard errors, ...).
    - `data_settings`: how the fit read its data files (units, columns, group, sample rate, extra columns): what
      `piezojax predict` reads new files with unless told otherwise.
    """

    path: Path
    config: ModelConfig
    model: Any
    summary: dict
    data_settings: dict

    def __iter__(self):  # `config, model = load_fit(folder)`, as `fitting.cli.load_fitted` returned
        return iter((self.config, self.model))


def load_fit(folder: str | os.PathLike) -> FitFolder:
    """Read a fit folder written by `piezojax fit` (or `fitting.Calibration.save`).

    **Arguments:**

    - `folder`: the folder holding `config.toml`, `result.json` and `model.eqx`.

    **Returns:** a `FitFolder` (`config`, `model`, `summary`, `data_settings`; it also unpacks as
    `config, model = load_fit(folder)`).

    Every file is validated: a missing or unreadable file, a `config.toml` that is not a valid CONFIG, a
    `result.json` that is not a JSON object or whose `cli.data_settings` do not say how to read data files, a
    `model.eqx` that does not hold the model of `config.toml` or holds a non-finite value each raise one
    `PiezojaxValueError` naming the file and key. Nothing in the folder is changed.

    ```python
    fit = fitting.load_fit("run1_fit")
    y = fitting.predict(fit.model, new_experiment, predictor=fit.config.predictor())
    ```
    """
    d = Path(os.fspath(folder)).expanduser()
    if not d.is_dir():
        raise PiezojaxValueError(f"fit folder {str(d)!r} does not exist or is not a folder")
    for name in ("config.toml", "model.eqx", "result.json"):
        if not (d / name).is_file():
            raise PiezojaxValueError(f"{str(d)!r} is not a folder written by `piezojax fit` (no {name})")
    config = load_config(d / "config.toml")
    summary = _summary(d / "result.json")
    settings = data_settings(summary, d / "result.json", config)
    try:
        model = load_model(d, like=config.build(None))
    except PiezojaxValueError as e:
        raise PiezojaxValueError(f"{str(d)!r}: model.eqx does not match the model of config.toml there (was one of "
                                 f"them edited, or copied from another fit?): {e}") from e
    _check_finite(model, d / "model.eqx")
    return FitFolder(d, config, model, summary, settings)


def _summary(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise PiezojaxValueError(f"cannot read {str(path)!r}: {e}") from e
    try:
        summary = json.loads(text)
    except ValueError as e:
        raise PiezojaxValueError(f"{str(path)!r} is not valid JSON ({e})") from e
    if not isinstance(summary, dict):
        raise PiezojaxValueError(f"{str(path)!r} must hold a JSON object (a fit's summary), got a "
                                 f"{type(summary).__name__}")
    return summary


def data_settings(summary: Mapping, source: str | os.PathLike, config: ModelConfig) -> dict:
    """How the fit read its data files: `summary["cli"]["data_settings"]` checked key by key (errors name `source`
    and the key), or CONFIG's `[data]` table when the summary records none (a fit made in Python)."""
    cli = summary.get("cli")
    if cli is None or isinstance(cli, Mapping) and cli.get("data_settings") is None:
        return dict(config.data)
    where = f"{os.fspath(source)}: cli"
    if not isinstance(cli, Mapping):
        raise PiezojaxValueError(f"{where} must be an object, got {json.dumps(cli)}")
    settings = cli["data_settings"]
    where += ".data_settings"
    if not isinstance(settings, Mapping):
        raise PiezojaxValueError(f"{where} must be an object {{units, columns, group, sample_rate, ignore_extra}}, "
                                 f"got {json.dumps(settings)}")
    unknown = [k for k in settings if k not in DATA_SETTINGS]
    if unknown:
        raise PiezojaxValueError(f"{where}: unknown key {unknown[0]!r}; allowed keys: {', '.join(DATA_SETTINGS)}")
    for key, example in (("units", '{"displacement": "um"}'), ("columns", '{"u": "v_in"}')):
        value = settings.get(key)
        if value is not None and not isinstance(value, Mapping):
            raise PiezojaxValueError(f"{where}.{key} must be an object, e.g. {example}, got {json.dumps(value)}")
    parse_units(settings.get("units"), f"{where}.units")
    parse_columns(settings.get("columns"), f"{where}.columns")
    group = settings.get("group")
    if group is not None and not isinstance(group, str):
        raise PiezojaxValueError(f"{where}.group must be the name of an HDF5 group (a string) or null, got "
                                 f"{json.dumps(group)}")
    rate = settings.get("sample_rate")
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, int | float) or not math.isfinite(rate)
                             or rate <= 0):
        raise PiezojaxValueError(f"{where}.sample_rate must be a positive number of Hz, got {json.dumps(rate)}")
    extra = settings.get("ignore_extra")
    if extra is not None and not isinstance(extra, bool):
        raise PiezojaxValueError(f"{where}.ignore_extra must be true or false, got {json.dumps(extra)}")
    return {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in settings.items()}


def _check_finite(model, path: Path) -> None:
    """Every floating parameter of the loaded `model` is finite (a damaged or hand-edited model file is named here,
    not deep inside a simulation)."""
    leaves = jtu.tree_leaves_with_path(eqx.filter(model, eqx.is_inexact_array))
    for key, leaf in leaves:
        value = np.asarray(leaf)
        if not np.all(np.isfinite(value)):
            raise PiezojaxValueError(f"{path}: parameter {path_string(key)!r} is not finite "
                                     f"({np.array2string(value, threshold=6)}); the file was edited or damaged: refit")
