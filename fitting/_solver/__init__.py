r"""The least-squares solvers, as optimistix splits them: a small abstract solver (`init` / `step` / `terminate`),
each concrete solver a *descent* (the step from a linearisation) and a *search* (whether to take it, and the next
step size or radius); a results enumeration with messages; a pluggable progress meter; the loop's own stopping
tests (`advance`: flat cost, stall, non-finite Jacobian; shared with `fit_fleet`) and one verdict per stopping code
(`verdict_of`); and `iterate`, the loop that runs a solver from several starts at once.

Everything works in normal-equation form: a linearisation at an accepted point is $(r, \tfrac12\|r\|^2, g, H)$ with
$g = J^\top r$ and $H = J^\top J$ (`Problem.normal_equations`: forward mode, a chunk of experiments at a time, the
$m \times p$ Jacobian never kept), and a rejected trial costs one simulation, not a Jacobian.

The multi-start bookkeeping above one level of continuation (levels of smoothing, restarts past kinks, the choice
of the best start, the report) is `fitting.solve`'s.
"""

from .loop import (
    Run as Run,
    iterate as iterate,
)
from .outcomes import (
    HARD_FAILURES as HARD_FAILURES,
    RESULTS as RESULTS,
    SUCCESSES as SUCCESSES,
    FitError as FitError,
    Verdict as Verdict,
    result_code as result_code,
    result_message as result_message,
)
from .progress import (
    AbstractProgressMeter as AbstractProgressMeter,
    NoProgressMeter as NoProgressMeter,
    Progress as Progress,
    TextProgressMeter as TextProgressMeter,
    as_progress_meter as as_progress_meter,
)
from .solvers import (
    AbstractNormalSolver as AbstractNormalSolver,
    LevenbergMarquardt as LevenbergMarquardt,
    Linearisation as Linearisation,
    RadiusSearch as RadiusSearch,
    Trial as Trial,
    TrustRegion as TrustRegion,
    TrustRegionDescent as TrustRegionDescent,
)
from .stopping import (
    CONVERGED as CONVERGED,
    CONVERGED_FLAT as CONVERGED_FLAT,
    LINEAR_SOLVE_FAILED as LINEAR_SOLVE_FAILED,
    NONFINITE as NONFINITE,
    NONFINITE_INITIAL as NONFINITE_INITIAL,
    OUTPACE_WINDOW as OUTPACE_WINDOW,
    OUTPACED as OUTPACED,
    PADDING as PADDING,
    RUNNING as RUNNING,
    STALLED as STALLED,
    Bookkeeping as Bookkeeping,
    advance as advance,
    begin as begin,
    outpaced as outpaced,
    verdict_of as verdict_of,
)
