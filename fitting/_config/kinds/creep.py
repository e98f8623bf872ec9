"""The creep kinds: Kelvin–Voigt, logarithmic, lag, linear and none."""

import dataclasses
from collections.abc import Mapping

import numpy as np

import piezojax as pj

from ..table import MAX_CREEP_ORDER, TINY, Negative, f64
from .base import BlockKind, StartData, _NoBlock
from .options import CreepOptions


class NoCreep(_NoBlock):
    table, name, Options = "creep", "none", CreepOptions

    def cold_start_args(self, o, config):
        return {"creep_order": 0}


def _creep_gain(data: StartData) -> float:
    """The creep's scale: 1 where it acts on a signal in the output's units (in series after the hysteresis, or on
    the voltage ahead of the dynamics' gain), else the static gain from volts to the output."""
    series = data.config.creep_structure == "series" and not data.config.hysteresis_kind.empty
    return 1.0 if data.unit_drive or series else data.static_gain()


class KelvinVoigtKind(BlockKind):
    """`pj.KelvinVoigtCreep`: `order` lags (≤ 10), `stiffnesses`, `time_constants`; in series with an instantaneous
    compliance 1 (`k0 = 1`), in parallel without."""

    table, name = "creep", "kelvin_voigt"
    lag_gains = "stiffnesses"  # the compliances 1/k_j are the gains

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(CreepOptions):
        order: int
        stiffnesses: np.ndarray | None = None
        time_constants: np.ndarray | None = None

    def gains(self, values):
        return 1.0 / values

    def from_gains(self, gains):
        return 1.0 / gains

    def parse(self, t, raw):
        n, (k, tau) = t.sized_vectors("order", 1, MAX_CREEP_ORDER, {"stiffnesses": dict(positive=True),
                                                                  "time_constants": dict(positive=True)})
        return self.Options(order=n, stiffnesses=k, time_constants=tau)

    def parameters(self, o):
        return ("stiffnesses", "time_constants")

    def placeholder(self, o):
        n = o.order
        return {"stiffnesses": np.full(n, 10.0), "time_constants": np.geomspace(1.0, 10.0, n)}

    def start(self, o, data):
        n, dt, span = o.order, data.dt(), data.span()
        # one lag at a tenth of the longest record, or n lags from 1/100 to 1/3 of it; each at 1 % of the gain
        taus = np.array([span / 10]) if n == 1 else np.geomspace(span / 100, span / 3, n)
        gain = abs(_creep_gain(data))
        return {"stiffnesses": np.full(n, 1.0 / max(0.01 * gain, TINY)), "time_constants": np.maximum(taus, 5 * dt)}

    def build(self, o, v, config):
        series = config.creep_structure == "series"
        return pj.KelvinVoigtCreep(f64(v["stiffnesses"]), f64(v["time_constants"]), k0=f64(1.0) if series else None)

    def constraints(self, o):
        return {"stiffnesses": pj.Positive, "time_constants": pj.Positive}

    def cold_start_args(self, o, config):
        return {"creep_order": o.order, "structure": config.creep_structure}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        return {"stiffnesses": np.asarray(block.stiffnesses), "time_constants": np.asarray(block.time_constants)}


class LogarithmicKind(BlockKind):
    """`pj.LogarithmicCreep`: `gamma`, `t0`, `gain` (fixed by default: only $g\\gamma$ is identifiable in parallel
    with the hysteresis)."""

    table, name = "creep", "logarithmic"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(CreepOptions):
        gamma: float | None = None
        t0: float | None = None
        gain: float | None = None

    def parse(self, t, raw):
        return self.Options(gamma=t.number("gamma", None), t0=t.number("t0", None, positive=True),
                            gain=t.number("gain", None))

    def parameters(self, o):
        return ("gamma", "t0", "gain")

    def required(self, o):
        return ("gamma", "t0")

    def placeholder(self, o):
        return {"gamma": 0.01, "t0": 1.0, "gain": 1.0}

    def start(self, o, data):
        return {"gamma": 0.01, "t0": 10 * data.dt(), "gain": _creep_gain(data)}

    def optional_start(self, o, data):
        return self.placeholder(o) | {"gain": _creep_gain(data)}

    def data_derived(self, o, config):
        # 1 (the placeholder) only where the creep acts on a signal in the output's units, as `_creep_gain`
        unit = config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics
        series = config.creep_structure == "series" and not config.hysteresis_kind.empty
        return () if unit or series else ("gain",)

    def build(self, o, v, config):
        return pj.LogarithmicCreep(f64(v["gamma"]), f64(v["t0"]), gain=f64(v["gain"]),
                                   instantaneous=config.creep_structure == "series")

    def constraints(self, o):
        return {"t0": pj.Positive}

    def default_free(self, o, config):
        return ("gamma", "t0")


class LagKind(BlockKind):
    """`pj.LagCreep`: `lags` (≤ 10), `fractions` (sum < 1), `time_constants`; DC gain 1, so only in series."""

    table, name = "creep", "lag"
    lag_gains, max_total_gain = "fractions", 1.0
    structures = ("series",)
    structure_note = ("a 'lag' creep is DC-normalised (its gain is 1): it belongs in series after the hysteresis; "
                      "use 'kelvin_voigt' for creep in parallel")

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(CreepOptions):
        lags: int
        fractions: np.ndarray | None = None
        time_constants: np.ndarray | None = None

    def parse(self, t, raw):
        n, (alpha, tau) = t.sized_vectors("lags", 1, MAX_CREEP_ORDER, {"fractions": dict(positive=True),
                                                                     "time_constants": dict(positive=True)})
        if alpha is not None and sum(alpha) >= 1:
            raise t.error(f"the fractions must add up to less than 1 (the rest responds at once), got {sum(alpha)}",
                          "fractions")
        return self.Options(lags=n, fractions=alpha, time_constants=tau)

    def parameters(self, o):
        return ("fractions", "time_constants")

    def placeholder(self, o):
        n = o.lags
        return {"fractions": np.full(n, 0.1 / n), "time_constants": np.geomspace(1e-2, 1.0, n)}

    def start(self, o, data):
        n, lo = o.lags, 50 * data.dt()
        # 20 % of the response lagging, split evenly; lags from 50 samples to a tenth of the longest record
        taus = np.array([lo]) if n == 1 else np.geomspace(lo, max(data.span() / 10, 2 * lo), n)
        return {"fractions": np.full(n, 0.2 / n), "time_constants": taus}

    def build(self, o, v, config):
        return pj.LagCreep(f64(v["fractions"]), f64(v["time_constants"]))

    def cold_start_args(self, o, config):
        return {"creep_order": o.lags, "structure": "series", "creep": "lag"}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        return {"fractions": np.asarray(block.fractions), "time_constants": np.asarray(block.time_constants)}

    def constraints(self, o):
        return {"fractions": pj.Fractions, "time_constants": pj.Positive}


class LinearCreepKind(BlockKind):
    r"""`pj.LinearCreep` of a `pj.StableTransferFunction` (paper 001's eq. 9): `order` real poles (≤ 10, `poles`
    < 0 in rad/s), `real_zeros` real zeros (`zeros` < 0) and the DC `gain`. In parallel the creep is strictly proper
    ($h(0^+) = 0$, at most `order - 1` zeros, default `order - 1`); in series it responds at once ($h(0^+) \ne 0$:
    `order` zeros), and its DC `gain` is fixed by default (the hysteresis carries the scale). Start: the
    Kelvin–Voigt creep's start or joint cold start with `order` lags, written as its transfer function ($\sum_i
    c_i/(1 + \tau_i s)$, plus 1 in series): poles $-1/\tau_i$, the zeros of the numerator (real, between them)."""

    table, name = "creep", "linear"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(CreepOptions):
        order: int
        poles: np.ndarray | None = None
        real_zeros: int
        zeros: np.ndarray | None = None
        gain: float | None = None

    def parse(self, t, raw):
        n, (p,) = t.sized_vectors("order", 1, MAX_CREEP_ORDER, {"poles": dict(negative=True)})
        series = _structure(raw) == "series"
        limit = n if series else n - 1
        m, (z,) = t.sized_vectors("real_zeros", limit, max(limit, 0), {"zeros": dict(negative=True)}, minimum=0)
        if series and m != n:
            raise t.error(f"a creep in series responds at once: it needs as many zeros as poles ({n}), got {m}",
                          "real_zeros" if t.has("real_zeros") else "zeros")
        return self.Options(order=n, poles=p, real_zeros=m, zeros=z, gain=t.number("gain", None, nonzero=True))

    def parameters(self, o):
        return ("poles",) + (("zeros",) if o.real_zeros else ()) + ("gain",)

    def placeholder(self, o):
        n, m = o.order, o.real_zeros
        return {"poles": -np.geomspace(1.0, 10.0, n), "zeros": -1.5 * np.geomspace(1.0, 10.0, n)[:m], "gain": 1.0}

    def _from_lags(self, o, c: np.ndarray, tau: np.ndarray, series: bool) -> dict:
        r"""Poles, zeros and DC gain of $d + \sum_i c_i/(1 + \tau_i s)$ ($d$ = 1 in series, else 0)."""
        tau = _strictly_ascending_taus(np.asarray(tau, float))
        den = [np.poly1d([t, 1.0]) for t in tau]
        num = np.poly1d([1.0 if series else 0.0])
        for t in tau:
            num = num * np.poly1d([t, 1.0])
        for i, ci in enumerate(c):
            term = np.poly1d([float(ci)])
            for j, d in enumerate(den):
                if j != i:
                    term = term * d
            num = num + term
        zeros = np.sort(np.real(np.roots(num.coeffs)))[::-1] if num.order > 0 else np.zeros(0)
        zeros = np.minimum(zeros, -1e-12)[: o.real_zeros]
        m = o.real_zeros
        if zeros.size < m:  # more zeros asked than the lags have (a parallel creep with fewer lags' worth)
            zeros = np.r_[zeros, -1.5 / tau[: m - zeros.size]]
        return {"poles": -1.0 / tau, "zeros": zeros, "gain": float(series) + float(np.sum(c))}

    def start(self, o, data):
        kv = KelvinVoigtKind().start(KelvinVoigtKind.Options(order=o.order), data)
        series = data.config.creep_structure == "series"
        return self._from_lags(o, 1.0 / kv["stiffnesses"], kv["time_constants"], series)

    def build(self, o, v, config):
        return pj.LinearCreep(pj.StableTransferFunction(f64(v["gain"]), poles=f64(v["poles"]),
                                                        zeros=f64(v.get("zeros", np.zeros(0)))))

    def values(self, o, data):
        out = super().values(o, data)
        out.setdefault("zeros", np.zeros(0))
        return out

    def constraints(self, o):
        return {"system.poles": Negative} | ({"system.zeros": Negative} if o.real_zeros else {})

    def default_free(self, o, config):
        series = config.creep_structure == "series"
        return ("system.poles",) + (("system.zeros",) if o.real_zeros else ()) + (
            () if series else ("system.gain",))

    def cold_start_args(self, o, config):
        default = o.order if config.creep_structure == "series" else o.order - 1
        if o.real_zeros != default:
            return None
        return {"creep_order": o.order, "structure": config.creep_structure}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        series = block.k0 is not None
        return self._from_lags(o, 1.0 / np.asarray(block.stiffnesses), np.asarray(block.time_constants), series)


def _structure(raw: Mapping) -> str:
    """The creep structure a CONFIG names (`[creep] structure`, default parallel), before it is validated."""
    c = raw.get("creep", {})
    return c.get("structure", "parallel") if isinstance(c, Mapping) else "parallel"


def _strictly_ascending_taus(tau: np.ndarray) -> np.ndarray:
    """Time constants made distinct (at least 1 % apart), so that the lags' poles and zeros stay apart."""
    tau = np.sort(tau)
    for i in range(1, tau.size):
        tau[i] = max(tau[i], 1.01 * tau[i - 1])
    return tau
