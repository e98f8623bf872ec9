r"""How the identification judges a structure: on data its fit did not see (`Split`), by its validation error over
the measurement noise (`score`), and which structure it keeps (`select`).

**The split.** Every record's last `VALIDATION_FRACTION` of the time is held out: a candidate is fitted on the
beginnings of all the records and predicts each end continuing from the state its beginning leaves
(`fitting.predict(..., history=...)`), so a model that only interpolates the training samples (an over-fitted creep
or resonance) is caught where the records go on, and every kind of excitation the user recorded is in the fit.
Holding out whole records instead leaves each candidate without that record's excitation: measured on a plant-study
PI draw (training records of nested triangles and of held steps), fitted on the triangles and validated on the
steps, every candidate scored 3–30× the noise in validation against about 1× in training (the triangles alone do
not show the creep's time constants), and the structure kept predicted the held-out drives at 1.24× and 1.85× the
noise. A record too short to leave `MIN_VALIDATION_SAMPLES` at its end is fitted whole. The structure chosen is then
fitted again on every record, whole.

**The rule.** Each candidate's residuals on the validation samples are divided by the measurement noise of their
channel (`estimate_noise_std`, white part; the channel's range / 1000 where a record has no measurable noise), so
the score $s = \sqrt{\overline{(e/\sigma)^2}}$ is 1 for a model that predicts to the noise. Two candidates' scores
differ by their misfits and by chance: with $e_c = n + m_c$ (noise $n$, misfit $m_c$), the difference of their mean
squares is $\overline{m_c^2 - m_b^2} + 2\,\overline{n(m_c - m_b)}$, whose random part has the standard error
$2\sqrt{\overline{(e_c - e_b)^2}/N}$ over $N$ samples ($e_c - e_b = m_c - m_b$: the noise cancels). Kept: the
candidate with the fewest fitted parameters whose mean squared score exceeds the best's by at most `Z` such standard
errors; among those, the lowest score. A more complex structure is kept only when the data say it predicts better.
(A standard error from blocks of the differences, tried first, counts the misfit's own variation over time as
chance: on the plant-study draw it found candidates at 6× the noise within the uncertainty of one at 1.1×.)
"""

import dataclasses

import numpy as np

from piezojax import PiezojaxValueError

from .._data import Dataset, Experiment
from .._predict import predict
from .._problem import estimate_noise_std

VALIDATION_FRACTION = 0.3
"""The held-out end of a single record."""
Z = 2.0
"""Standard errors within which a simpler candidate counts as good as the best."""
MIN_VALIDATION_SAMPLES = 200


@dataclasses.dataclass(frozen=True)
class Split:
    """The training records and the validation records, each with the records run before it (its history)."""

    training: Dataset
    validation: tuple[tuple[Experiment, tuple[Experiment, ...]], ...]
    description: str


def split(dataset: Dataset) -> Split:
    """The identification's split of `dataset` (see the module docstring)."""
    training, validation, whole = [], [], []
    for e in dataset:
        cut = e.t[0] + (1 - VALIDATION_FRACTION) * (e.t[-1] - e.t[0] + e.dt)
        if e.n - int(np.count_nonzero(e.t < cut - 1e-6 * e.dt)) < MIN_VALIDATION_SAMPLES:
            training.append(e)
            whole.append(e.name)
            continue
        head, tail = e.slice(None, cut), e.slice(cut, None)
        training.append(head)
        validation.append((tail, (head,)))
    if not validation:
        raise PiezojaxValueError(f"the records are too short to identify a structure: the last "
                                 f"{VALIDATION_FRACTION:.0%} of at least one (the validation) needs "
                                 f"{MIN_VALIDATION_SAMPLES} samples")
    return Split(Dataset(training), tuple(validation),
                 f"fitted on the first {1 - VALIDATION_FRACTION:.0%} of each record"
                 + (f" ({', '.join(whole)} whole)" if whole else "")
                 + f"; validated on the last {VALIDATION_FRACTION:.0%} (predicted after the beginning)")


def scaled_errors(model, predictor, validation, targets) -> np.ndarray:
    """The validation residuals of `model`, each divided by its channel's noise, in time order per record and
    channel, concatenated; NaN where the model's prediction is not finite."""
    out = []
    for exp, history in validation:
        pred = predict(model, exp, predictor=predictor, history=history, check_finite=False)
        for c in targets:
            if not exp.has(c):
                continue
            measured = np.asarray(exp[c], float)
            sigma = estimate_noise_std(measured)
            floor = 1e-3 * float(np.ptp(measured)) or 1.0
            sigma = sigma if sigma > 1e-9 * float(np.max(np.abs(measured))) else floor
            out.append((np.asarray(pred[c], float) - measured) / sigma)
    return np.concatenate(out)


def score(errors: np.ndarray) -> float:
    """$\\sqrt{\\overline{(e/\\sigma)^2}}$ (inf when a residual is not finite)."""
    return float(np.sqrt(np.mean(errors**2))) if np.all(np.isfinite(errors)) else np.inf


def select(errors: list[np.ndarray], sizes: list[int]) -> tuple[int, list[bool]]:
    """The index of the candidate kept (the rule of the module docstring), and per candidate whether it is within
    the best's uncertainty. `errors`: each candidate's `scaled_errors` (the same samples); `sizes`: their numbers of
    fitted parameters."""
    scores = [score(e) for e in errors]
    if not any(np.isfinite(scores)):
        raise PiezojaxValueError("no candidate structure predicts the validation data with finite values")
    best = int(np.nanargmin(scores))
    within = []
    for e, s in zip(errors, scores):
        if not np.isfinite(s):
            within.append(False)
            continue
        excess = float(np.mean(e**2 - errors[best] ** 2))
        se = 2.0 * float(np.sqrt(np.mean((e - errors[best]) ** 2) / e.size))
        within.append(excess <= Z * se)
    kept = min((i for i in range(len(errors)) if within[i]), key=lambda i: (sizes[i], scores[i]))
    return kept, within
