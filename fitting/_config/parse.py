"""Reading a CONFIG: `parse_config` (TOML text to a validated `ModelConfig`) and `load_config` (a file)."""

import dataclasses
import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax.numpy as jnp

from piezojax import PiezojaxValueError

from .._data import CHANNELS, parse_columns, parse_units
from .._problem import matches, parameter_paths
from .kinds.base import DEFAULT_KIND, get_kind, registered_kinds
from .kinds.models import ACTUATOR, get_model_kind, model_kinds
from .kinds.options import common_keys
from .model_config import (
    _DATA_KEYS,
    _FIT_KEYS,
    _WEIGHT_MODES,
    MAX_LEVELS,
    MAX_STEPS,
    MAX_WEIGHT,
    MODEL_TABLES,
    TABLES,
    ModelConfig,
    _kind,
    _parse_polynomial,
)
from .table import ConfigTable, finite_number


def parse_config(text: str, source: str = "config") -> ModelConfig:
    """Parse and validate a model configuration from TOML text.

    **Arguments:**

    - `text`: the TOML text.
    - `source`: the name used in error messages (the file name).

    **Returns:** a `ModelConfig`. Any problem — TOML syntax, unknown table, key or kind, wrong type, wrong length —
    raises a one-line `PiezojaxValueError` naming the file, the table and key, and the allowed values.

    ```python
    cfg = parse_config('[hysteresis]\\nkind = "prandtl_ishlinskii"\\nplays = 8\\n[dynamics]\\norder = 2\\n')
    model = pj.unwrap(cfg.build(dataset))
    ```
    """
    if not isinstance(text, str):
        raise PiezojaxValueError(f"{source}: `text` must be the TOML text (a str; read a file with "
                                 f"`fitting.load_config`), got {type(text).__name__}")
    text = text.removeprefix("\ufeff")  # a byte-order mark (some editors on Windows save one), as in CSV files
    raw = _read_tables(text, source)
    model, mkind, mt = _model_kind(source, raw)
    kinds, opts = _parse_blocks(source, raw, mkind, model)
    h_kind = kinds["hysteresis"]
    model_options = mkind.parse(mt, raw, source)
    no_dynamics = getattr(opts["dynamics"], "order", 0) == 0  # the order of a dynamics kind that has one
    if mkind.table is None and kinds["creep"] == "none" and h_kind == "none" and no_dynamics:
        raise PiezojaxValueError(f"{source}: every block is 'none': the model has no parameters")
    blocks = dict(source=source, hysteresis=h_kind, hysteresis_options=opts["hysteresis"], creep=kinds["creep"],
                  creep_options=opts["creep"], dynamics=kinds["dynamics"], dynamics_options=opts["dynamics"],
                  model=model, model_options=model_options)
    outputs = ModelConfig(text="", **blocks, free=None, weights="range", smoothing=None, max_steps=1,
                          targets=None).outputs
    ft = ConfigTable(source, "fit", raw.get("fit", {}), _FIT_KEYS)
    fit = _parse_fit(ft, h_kind, outputs)
    cfg = ModelConfig(text=text, **blocks, **fit, data=_parse_data(source, raw))
    if fit["free"] is not None:
        _check_free(cfg, ft, fit["free"])
    return cfg


def _read_tables(text: str, source: str) -> dict:
    """The TOML document's tables, each a table with a known name, and at least one model block among them."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise PiezojaxValueError(f"{source}: not valid TOML ({' '.join(str(e).split())})") from e
    unknown = [k for k in raw if k not in TABLES]
    if unknown:
        raise PiezojaxValueError(
            f"{source}: unknown table or key [{unknown[0]}]; allowed tables: {', '.join(f'[{t}]' for t in TABLES)}"
        )
    for name, data in raw.items():
        if not isinstance(data, Mapping):
            raise PiezojaxValueError(f"{source}: {name} must be a table ([{name}]), got a {type(data).__name__}")
    if not any(k in raw for k in ("hysteresis", "creep", "dynamics") + MODEL_TABLES):
        raise PiezojaxValueError(
            f"{source}: no model blocks; give at least one of [hysteresis], [creep], [dynamics], [observer] or [model]"
        )
    return raw


def _model_kind(source: str, raw: dict):
    """`(name, ModelKind, its ConfigTable or None)`: the observer or model that [observer] / [model] names, else the
    actuator; a block table the model does not use is an error."""
    named = [t for t in MODEL_TABLES if t in raw]
    if len(named) > 1:
        raise PiezojaxValueError(f"{source}: [observer] and [model] both name a whole model; keep one")
    if named:
        table = named[0]
        model = _kind(source, table, raw[table], model_kinds(table))
        mkind = get_model_kind(model)
        mt = ConfigTable(source, table, raw[table], mkind.keys, model)
    else:
        model, mkind, mt = ACTUATOR.name, ACTUATOR, None
    for t in ("hysteresis", "creep", "dynamics", "charge", "state", "input"):
        if t in raw and t not in mkind.tables + mkind.blocks:
            raise PiezojaxValueError(
                f"{source}: [{t}] is not used by the {mkind.name.replace('_', ' ')} model (kind {model!r}); remove "
                f"it, or remove [{mkind.table}] for an actuator model")
    return model, mkind, mt


def _parse_blocks(source: str, raw: dict, mkind, model: str) -> tuple[dict, dict]:
    """Each block table's kind and options, parsed by its kind, with the table's common keys (`common_keys`) filled
    in here (the default kind with its default options for a block the model lacks)."""
    kinds, opts = {}, {}
    for table in ("hysteresis", "creep", "dynamics"):
        if table not in mkind.blocks:  # a block the model does not have
            kinds[table] = DEFAULT_KIND[table]
            opts[table] = get_kind(table, DEFAULT_KIND[table]).Options()
            continue
        data = raw.get(table, {"kind": DEFAULT_KIND[table]} if table != "dynamics" else {"order": 0})
        if table == "dynamics" and isinstance(data, Mapping) and "kind" not in data:
            data = {**data, "kind": DEFAULT_KIND[table]}
        name = _kind(source, table, data, registered_kinds(table))
        kind = get_kind(table, name)
        common = () if kind.empty else common_keys(table)
        t = ConfigTable(source, table, data, kind.keys + common, name)
        o = kind.parse(t, raw)
        if not isinstance(o, kind.Options):
            raise TypeError(f"the {table} kind {name!r}: `parse` must return its `Options`, got {type(o).__name__}")
        if table == "hysteresis" and not kind.empty:
            o = dataclasses.replace(o, **_parse_polynomial(t))
        if table == "creep" and not kind.empty:
            o = dataclasses.replace(o, **_creep_structure(t, kind, mkind, name))
        kinds[table], opts[table] = name, o
    return kinds, opts


def _creep_structure(t: ConfigTable, kind, mkind, name: str) -> dict:
    """`{"structure": ...}` when the [creep] table gives one the kind and the model support, else `{}`."""
    structure = t.string("structure", ("series", "parallel"))
    allowed = [s for s in kind.structures if s in mkind.structures]
    if structure is not None and structure not in allowed or not allowed:
        if structure is not None and structure not in kind.structures:
            raise t.error(kind.structure_note or f"a {name!r} creep supports only structure = "
                          f"{' or '.join(map(repr, kind.structures))}", "structure")
        raise t.error(f"the {mkind.name.replace('_', ' ')} model adds its creep in "
                      f"{' or '.join(mkind.structures)} (paper 001's eq. 4 for the observer); use a kind that "
                      f"supports it, without another `structure`", "structure" if structure else "kind")
    return {} if structure is None else {"structure": structure}


def _parse_fit(ft: ConfigTable, h_kind: str, outputs) -> dict:
    """The [fit] table as `ModelConfig`'s keyword arguments: free, weights, smoothing, max_steps, method, targets."""
    if "kind" in ft.data:
        raise ft.error(f"unknown key 'kind'; allowed keys: {', '.join(_FIT_KEYS)}", "kind")
    free = ft.data.get("free")
    if free is not None:
        if not (isinstance(free, list) and free and all(isinstance(p, str) and p for p in free)):
            raise ft.error(f"must be a non-empty list of parameter paths (e.g. \"hysteresis.weights\"), got {free!r}",
                           "free")
        free = tuple(free)
    weights = _weights(ft)
    smoothing = _smoothing(ft, h_kind)
    max_steps = ft.integer("max_steps", 500, minimum=1, maximum=MAX_STEPS)
    method = ft.string("method", ("levenberg_marquardt", "trust_region"), "levenberg_marquardt")
    targets = _targets(ft, outputs)
    if isinstance(weights, dict) and targets is not None:
        lacking = [c for c in targets if c not in weights]
        if lacking:
            raise ft.error(f"no weight for the target channel {lacking[0]!r}", "weights")
    return dict(free=free, weights=weights, smoothing=smoothing, max_steps=max_steps, method=method,
                targets=targets)


def _weights(ft: ConfigTable):
    """`[fit] weights`: "range", "noise" or a table {channel = weight}."""
    weights = ft.data.get("weights", "range")
    if isinstance(weights, str):
        if weights not in _WEIGHT_MODES:
            raise ft.error(f"unknown value {weights!r}; allowed values: \"range\", \"noise\" or a table "
                           "{channel = weight}", "weights")
    elif isinstance(weights, Mapping):
        bad = [c for c in weights if c not in CHANNELS]
        if bad:
            raise ft.error(f"unknown channel {bad[0]!r}; allowed channels: {', '.join(CHANNELS)}", "weights")
        for c, w in weights.items():
            if not (finite_number(w) and 0 < w <= MAX_WEIGHT):
                raise ft.error(f"weight of {c!r} must be a number > 0 and <= {MAX_WEIGHT:g}, got {w!r}", "weights")
        weights = {c: float(w) for c, w in weights.items()}
    else:
        raise ft.error(f"must be \"range\", \"noise\" or a table {{channel = weight}}, got {weights!r}", "weights")
    return weights


def _smoothing(ft: ConfigTable, h_kind: str) -> tuple[float, ...] | None:
    """`[fit] smoothing`: the continuation levels, which need a hysteresis block."""
    smoothing = ft.data.get("smoothing")
    if smoothing is not None:
        if not (isinstance(smoothing, list) and smoothing and all(
                finite_number(s) and s >= 0
                for s in smoothing)):
            raise ft.error(f"must be a non-empty list of numbers >= 0 (continuation levels), got {smoothing!r}",
                           "smoothing")
        if h_kind == "none":
            raise ft.error("continuation needs a hysteresis block with smoothing", "smoothing")
        if len(smoothing) > MAX_LEVELS:
            raise ft.error(f"at most {MAX_LEVELS} continuation levels, got {len(smoothing)}", "smoothing")
        smoothing = tuple(float(s) for s in smoothing)
    return smoothing


def _targets(ft: ConfigTable, outputs) -> tuple[str, ...] | None:
    """`[fit] targets`: channels the model predicts."""
    targets = ft.data.get("targets")
    if targets is not None:
        if not (isinstance(targets, list) and targets and all(isinstance(c, str) for c in targets)):
            raise ft.error(f"must be a non-empty list of channel names, got {targets!r}", "targets")
        bad = [c for c in targets if c not in outputs]
        if bad:
            raise ft.error(f"the model does not predict {bad[0]!r}; it predicts: {', '.join(outputs)}", "targets")
        targets = tuple(targets)
    return targets


def _parse_data(source: str, raw: dict) -> dict[str, Any]:
    """The [data] table: how the data files are read (units, columns, group, sample_rate, ignore_extra)."""
    dtab = ConfigTable(source, "data", raw.get("data", {}), _DATA_KEYS)
    if "kind" in dtab.data:
        raise dtab.error(f"unknown key 'kind'; allowed keys: {', '.join(_DATA_KEYS)}", "kind")
    data: dict[str, Any] = {}
    for key, example in (("units", '{displacement = "um"}'), ("columns", '{u = "v_in", y = "displacement"}')):
        value = dtab.data.get(key)
        if value is None:
            continue
        if not isinstance(value, Mapping):
            raise dtab.error(f"must be a table, e.g. {example}, got {value!r}", key)
        (parse_units if key == "units" else parse_columns)(value, f"{source}: [data] {key}")
        data[key] = {str(k): v for k, v in value.items()}
    if "group" in dtab.data:
        if not isinstance(dtab.data["group"], str) or not dtab.data["group"]:
            raise dtab.error(f"must be the name of an HDF5 group (or .mat struct), got {dtab.data['group']!r}", "group")
        data["group"] = dtab.data["group"]
    fs = dtab.number("sample_rate", None, positive=True)
    if fs is not None:
        data["sample_rate"] = fs
    if "ignore_extra" in dtab.data:
        if not isinstance(dtab.data["ignore_extra"], bool):
            raise dtab.error(f"must be true or false, got {dtab.data['ignore_extra']!r}", "ignore_extra")
        data["ignore_extra"] = dtab.data["ignore_extra"]
    return data


def _check_free(cfg: ModelConfig, ft: ConfigTable, free: tuple[str, ...]) -> None:
    """Every `[fit] free` selector matches a parameter of the built model that has entries and acts on an output."""
    values = parameter_paths(cfg.build(None))
    paths = list(values)
    # without a [charge] table the actuator's capacitance and coupling act on no predicted channel
    no_charge = cfg.model_kind is ACTUATOR and cfg.charge is None
    charge_only = ("capacitance", "coupling") if no_charge else ()
    listed = [p for p in paths if p not in charge_only]
    for sel in free:
        matched = [p for p in paths if matches(p, sel)]
        if not matched:
            raise ft.error(f"unknown parameter path {sel!r}; the model's parameters: {', '.join(listed)}", "free")
        if sel in charge_only:
            raise ft.error(f"{sel!r} acts only on the charge and current, which this model does not predict: add "
                           "a [charge] table to fit it", "free")
        if all(jnp.size(values[p]) == 0 for p in matched):
            # e.g. `dynamics.poles` of a model with pole pairs only: nothing to fit
            sized = ", ".join(p for p in listed if jnp.size(values[p]) > 0)
            raise ft.error(f"{sel!r} has no entries in this model (its sizes come from the block tables); the "
                           f"model's parameters with entries: {sized}", "free")


def load_config(path: str | os.PathLike) -> ModelConfig:
    """Read and validate a TOML model configuration file (see `parse_config`).

    **Arguments:**

    - `path`: the `.toml` file.

    **Returns:** a `ModelConfig`; unreadable files and invalid content raise a one-line `PiezojaxValueError`.

    ```python
    cfg = load_config("pi_creep.toml"); init = cfg.build(fitting.Dataset.from_files(["run1.csv"]))
    ```
    """
    return parse_config(read_config_text(path), source=str(Path(os.fspath(path)).expanduser()))


def read_config_text(path: str | os.PathLike) -> str:
    """The text of a configuration file (UTF-8); a missing, unreadable or non-file path raises one
    `PiezojaxValueError` naming it."""
    p = Path(os.fspath(path)).expanduser()
    if not p.exists():
        raise PiezojaxValueError(f"configuration file {str(p)!r} does not exist")
    if p.is_dir():
        raise PiezojaxValueError(f"configuration file {str(p)!r} is a directory")
    try:
        return p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise PiezojaxValueError(f"cannot read configuration file {str(p)!r}: {e}") from e
