r"""The least-squares solvers, as optimistix splits them: a small abstract solver (`init` / `step` / `terminate`),
each concrete solver a *descent* (the step from a linearisation) and a *search* (whether to take it, and the next
step size or radius); the outcomes (`RESULTS`, an enumeration with messages that the loop carries per start, and
what is derived from it: codes, verdicts, success sets); a pluggable progress meter; the loop's own stopping tests
(`advance`: flat cost, stall, non-finite Jacobian); `step`, the one compiled iteration of a batch of starts that
`iterate` and `fit_fleet` both take; and `iterate`, the loop that runs a solver from several starts at once.

Everything works in normal-equation form: a linearisation at an accepted point is $(r, \tfrac12\|r\|^2, g, H)$ with
$g = J^\top r$ and $H = J^\top J$ (`Problem.normal_equations`: forward mode, a chunk of experiments at a time, the
$m \times p$ Jacobian never kept), and a rejected trial costs one simulation, not a Jacobian.

The multi-start bookkeeping above one level of continuation (levels of smoothing, restarts past kinks, the choice
of the best start, the report) is `fitting.solve`'s.
"""

from .iteration import (
    Carry as Carry,
    iteration as iteration,
    linearise_one as linearise_one,
    reject as reject,
    rejected as rejected,
    select_rows as select_rows,
    start as start,
    step as step,
    stop as stop,
)
from .loop import (
    Run as Run,
    iterate as iterate,
)
from .outcomes import (
    CODES as CODES,
    HARD_FAILURES as HARD_FAILURES,
    LOOP_ONLY as LOOP_ONLY,
    NAMES as NAMES,
    RESULTS as RESULTS,
    SUCCESSES as SUCCESSES,
    FitError as FitError,
    Verdict as Verdict,
    result_code as result_code,
    result_message as result_message,
    result_names as result_names,
    verdict_of as verdict_of,
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
    OUTPACE_WINDOW as OUTPACE_WINDOW,
    Bookkeeping as Bookkeeping,
    advance as advance,
    begin as begin,
    outpaced as outpaced,
)
