"""Finding the structure of an actuator's model: the candidate structures (`structures.py`), how a candidate is
judged on data its fit did not see (`validation.py`) and the staged search (`search.py`, `identify`)."""

from .search import (
    CANDIDATE_MAX_STEPS as CANDIDATE_MAX_STEPS,
    START as START,
    Candidate as Candidate,
    Identification as Identification,
    identify as identify,
    parse_base as parse_base,
)
from .structures import HYSTERESIS_KINDS as HYSTERESIS_KINDS, Structure as Structure
from .validation import VALIDATION_FRACTION as VALIDATION_FRACTION, Z as Z, select as select
