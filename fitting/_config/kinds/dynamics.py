"""The dynamics kind: a stable transfer function of configurable order, with zeros."""

import dataclasses

import numpy as np

import piezojax as pj

from ..table import DYNAMICS_ORDERS, Negative, f64
from .base import BlockKind
from .options import KindOptions


class TransferFunctionKind(BlockKind):
    r"""`pj.StableTransferFunction` (the default `[dynamics]` kind): `order` (0–8) poles, `order // 2` pairs
    (`omega`, `zeta`) and `order % 2` real (`poles`); `zero_pairs` (≤ the pole pairs) complex zero pairs
    (`zero_omega`, `zero_zeta`: a mode with an antiresonance, e.g. a low-frequency mode of the mount) and
    `real_zeros` (`zeros`); `gain` (DC gain, default 1). Zero pair $i$ starts at 1.25 $\omega_i$ with $\zeta_i$
    (near the pole pair, so the mode starts weak), real zero $j$ at 1.25 times real pole $j$, further real zeros
    spread from 1.25 to 5 times the fastest pole (distinct, so that they can part)."""

    table, name = "dynamics", "transfer_function"

    @dataclasses.dataclass(frozen=True)
    class Options(KindOptions):
        """Every field has a default: `Options()` is a model without dynamics (order 0)."""

        order: int = 0
        gain: float | None = None
        omega: np.ndarray | None = None
        zeta: np.ndarray | None = None
        poles: np.ndarray | None = None
        zero_pairs: int = 0
        zero_omega: np.ndarray | None = None
        zero_zeta: np.ndarray | None = None
        real_zeros: int = 0
        zeros: np.ndarray | None = None

    def parse(self, t, raw):
        order = t.integer("order", None, allowed=DYNAMICS_ORDERS)
        if order is None:
            raise t.error(f"missing; allowed values: {', '.join(map(str, DYNAMICS_ORDERS))}", "order")
        n2, n1 = divmod(order, 2)
        for k, n in (("omega", n2), ("zeta", n2), ("poles", n1)):
            if n == 0 and k in t.data:
                raise t.error(f"not used with order = {order}", k)
        m2, (zw, zz) = t.sized_vectors("zero_pairs", 0, n2, {"zero_omega": dict(positive=True), "zero_zeta": {}},
                                       minimum=0)
        m1, (z,) = t.sized_vectors("real_zeros", 0, n1 + 2 * (n2 - m2), {"zeros": {}}, minimum=0)
        return self.Options(order=order, gain=t.number("gain", None, nonzero=True),
                            omega=t.vector("omega", n2, positive=True), zeta=t.vector("zeta", n2, positive=True),
                            poles=t.vector("poles", n1, negative=True), zero_pairs=m2, zero_omega=zw, zero_zeta=zz,
                            real_zeros=m1, zeros=z)

    def parameters(self, o):
        n2, n1 = divmod(o.order, 2)
        return (("omega", "zeta") if n2 else ()) + (("poles",) if n1 else ()) + (
            ("zero_omega", "zero_zeta") if o.zero_pairs else ()) + (("zeros",) if o.real_zeros else ()) + (
            "gain",)

    def required(self, o):
        return tuple(p for p in self.parameters(o) if p != "gain")

    def data_derived(self, o, config):
        # without hysteresis the DC gain is the scale from volts to the output, started from the data's (and fitted)
        return ("gain",) if config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics else ()

    def _zeros(self, o, omega, zeta, poles) -> dict:
        m2, m1 = o.zero_pairs, o.real_zeros
        # real zeros at 1.25 times the real poles, then spread (distinct, so that they can part) above the pairs
        near = 1.25 * np.asarray(poles)[:m1]
        top = max([1.0] + [abs(float(x)) for x in np.r_[np.asarray(poles), np.asarray(omega)]])
        extra = -1.25 * top * np.geomspace(1.0, 4.0, max(m1 - near.size, 1))[: m1 - near.size]
        return {"zero_omega": 1.25 * np.asarray(omega)[:m2], "zero_zeta": np.asarray(zeta)[:m2],
                "zeros": np.concatenate([near, extra])}

    def placeholder(self, o):
        n2, n1 = divmod(o.order, 2)
        out = {"omega": np.geomspace(1e3, 1e4, n2) if n2 else np.zeros(0), "zeta": np.full(n2, 0.5),
               "poles": np.full(n1, -1e3), "gain": 1.0}
        return out | self._zeros(o, _given(o, "omega", out), _given(o, "zeta", out), _given(o, "poles", out))

    def start(self, o, data):
        n2, n1 = divmod(o.order, 2)
        # rule of thumb: modes at 1/10 (and 1/4, ...) of the sampling rate, damping 0.5, real poles at 1/10
        nyquist = 0.5 / data.dt()
        fractions = np.geomspace(0.2, 0.8, n2) if n2 > 2 else np.array([0.2, 0.5])[:n2]
        out = {"omega": 2 * np.pi * nyquist * fractions, "zeta": np.full(n2, 0.5),
               "poles": -2 * np.pi * 0.2 * nyquist * np.geomspace(1.0, 3.0, n1) if n1 else np.zeros(0),
               "gain": data.static_gain() if data.unit_drive else 1.0}
        return out | self._zeros(o, _given(o, "omega", out), _given(o, "zeta", out), _given(o, "poles", out))

    def optional_start(self, o, data):
        return self.placeholder(o) | {"gain": data.static_gain() if data.unit_drive else 1.0}

    def from_cold_start(self, o, block):
        # only all-pole even orders are in the cold start's family (`cold_start_args`)
        return None if block is None else {"omega": np.asarray(block.omega), "zeta": np.asarray(block.zeta),
                                           "gain": 1.0}

    def values(self, o, data):
        out = super().values(o, data)
        for k in ("omega", "zeta", "poles", "zero_omega", "zero_zeta", "zeros"):
            out.setdefault(k, np.zeros(0))
        return out

    def build(self, o, v, config):
        if not o.order and not (config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics):
            return None  # without hysteresis the dynamics' DC gain is the only scale from volts to metres
        return pj.StableTransferFunction(f64(v["gain"]), omega=f64(v["omega"]), zeta=f64(v["zeta"]),
                                         poles=f64(v["poles"]), zeros=f64(v["zeros"]),
                                         zero_omega=f64(v["zero_omega"]), zero_zeta=f64(v["zero_zeta"]))

    def constraints(self, o):
        n2, n1 = divmod(o.order, 2)
        return ({"omega": pj.Positive, "zeta": pj.Positive} if n2 else {}) | ({"poles": Negative} if n1 else {}) | (
            {"zero_omega": pj.Positive} if o.zero_pairs else {})

    def default_free(self, o, config):
        # the DC gain duplicates the scale of the hysteresis; it is the scale when there is no hysteresis
        scale = config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics
        return (("gain",) if scale else ()) + tuple(p for p in self.parameters(o) if p != "gain")

    def cold_start_args(self, o, config):
        if o.order % 2 or o.zero_pairs or o.real_zeros:
            return None
        return {"dynamics_order": o.order}


def _given(o: KindOptions, key: str, made: dict) -> np.ndarray:
    value = getattr(o, key)
    return np.asarray(made[key] if value is None else value)
