"""Semi-public helpers (as `equinox.internal`): numerical building blocks that `fitting` and advanced users build on,
with no promise that their signatures stay as they are between minor versions. Everything else whose name starts
with an underscore is private; `fitting` imports the library only through `piezojax` and this module.

- Refusals: `refusal_mode(mode)` and `refusals_as_nan()` make a model's runtime checks (`eqx.error_if`) either raise
  or turn its outputs into NaN, as the solvers need for a trial point.
- Scans: `scan_mode()` and `parallel_scans(mode)` read and set, within a block, whether linear recursions use the
  sequential or the parallel (associative) scan.
- Dtypes: `common_float_dtype(*xs)`, `matmul(a, b)` (at the highest precision on every backend).
- Linear least squares on large records: `nnls_gram` (non-negative least squares through the Gram matrix),
  `row_subset` / `MAX_ROWS` / `check_max_rows` (a fixed random subset of rows), `columns_at_rows` (design columns
  evaluated at those rows), `contiguous_runs` (runs of active grid points), `lag_columns` (first-order lags of a
  signal sampled with a hold).
"""

from ._checks import refusal_mode as refusal_mode, refusals_as_nan as refusals_as_nan
from ._config import parallel_scans as parallel_scans, scan_mode as scan_mode
from ._creep.lags import lag_columns as lag_columns
from ._dtypes import common_float_dtype as common_float_dtype, matmul as matmul
from ._hysteresis.initialise import (
    MAX_ROWS as MAX_ROWS,
    check_max_rows as check_max_rows,
    columns_at_rows as columns_at_rows,
    contiguous_runs as contiguous_runs,
    nnls_gram as nnls_gram,
    row_subset as row_subset,
)
