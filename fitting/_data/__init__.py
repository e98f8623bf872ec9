"""Measured experiments, data files and datasets for calibration.

An *experiment* is one record on a uniform time grid: time `t` [s], applied voltage `v_in` [V], and any subset of the
measured channels in `CHANNELS`. A `Dataset` is an ordered collection of experiments of possibly different lengths and
channel sets, with the grouping and padding the calibration engine needs to `vmap` over them.

Data live on the host as read-only float64 numpy arrays: they are loaded and validated once, eagerly, with error
messages naming the file, the column and the row. The engine converts them to JAX arrays (in the dtype it chooses)
when it builds residuals.
"""

from .dataset import Dataset as Dataset, experiments_of as experiments_of
from .experiment import (
    CHANNELS as CHANNELS,
    COLUMNS as COLUMNS,
    UNITS as UNITS,
    Experiment as Experiment,
)
from .formats import (
    FILE_MARKER as FILE_MARKER,
    SUPPORTED_SUFFIXES as SUPPORTED_SUFFIXES,
    UNGROUPED_SUFFIXES as UNGROUPED_SUFFIXES,
    listed_files as listed_files,
    load_experiment as load_experiment,
    parse_columns as parse_columns,
    read_file_marker as read_file_marker,
    save_experiment as save_experiment,
)
from .units import (
    UnitWarning as UnitWarning,
    parse_units as parse_units,
    plausibility_warnings as plausibility_warnings,
    unit_scale as unit_scale,
)
