"""The model structures the identification searches: `Structure` (a hysteresis kind, a creep, the dynamics' order,
the initial state, an input delay) written as a CONFIG, and the neighbours of a structure that each stage fits."""

import dataclasses
import tomllib

from piezojax import PiezojaxValueError

HYSTERESIS_KINDS = ("none", "prandtl_ishlinskii", "play", "bouc_wen", "maxwell_slip", "preisach")
"""Every hysteresis kind the search fits at least once."""

_ELEMENT_KEY = {"prandtl_ishlinskii": "plays", "play": "plays", "maxwell_slip": "elements", "preisach": "levels"}
_SHORT = {"none": "no hysteresis", "prandtl_ishlinskii": "PI", "play": "play", "bouc_wen": "Bouc-Wen",
          "maxwell_slip": "Maxwell slip", "preisach": "Preisach", "kelvin_voigt": "KV", "lag": "lag",
          "logarithmic": "log"}
SEARCHED_TABLES = ("hysteresis", "creep", "dynamics", "state", "input")
"""The CONFIG tables a structure writes; a base CONFIG that gives one of them fixes it."""


@dataclasses.dataclass(frozen=True)
class Structure:
    """One model structure of `pj.Actuator`: the hysteresis kind (`elements`: its plays, elements or levels; an
    output `polynomial` of that degree, 0 for none), the creep kind (`creep_order` lags, in `creep_structure`), the
    dynamics' poles (`dynamics`, from 0) and `zeros` (a pair with two or more poles: an antiresonance; else real),
    a fitted hysteresis `prehistory` and an input `delay`."""

    hysteresis: str = "prandtl_ishlinskii"
    elements: int = 8
    polynomial: int = 0
    creep: str = "none"
    creep_order: int = 1
    creep_structure: str = "parallel"
    dynamics: int = 0
    zeros: int = 0
    prehistory: bool = False
    delay: bool = False

    def label(self) -> str:
        """A short name: `PI(8) + KV(1) series + 2 poles + prehistory + delay`."""
        h = _SHORT[self.hysteresis]
        if self.hysteresis in _ELEMENT_KEY:
            h += f"({self.elements})"
        if self.polynomial:
            h += f" + polynomial {self.polynomial}"
        parts = [h]
        if self.creep != "none":
            order = f"({self.creep_order})" if self.creep in ("kelvin_voigt", "lag") else ""
            parts.append(f"{_SHORT[self.creep]}{order} {self.creep_structure}")
        if self.dynamics:
            parts.append(f"{self.dynamics} pole{'s' if self.dynamics > 1 else ''}")
        if self.zeros:
            parts.append(f"{self.zeros} zero{'s' if self.zeros > 1 else ''}")
        parts += ["prehistory"] * self.prehistory + ["delay"] * self.delay
        return " + ".join(parts)

    def tables(self, inputs: tuple[float, float] | None = None) -> dict[str, str]:
        """The structure's CONFIG tables, as TOML text by table name. `inputs`: the smallest and largest voltage of
        the records, from which a Preisach operator's grid is laid (`preisach_range`; else the kind's default)."""
        out = {}
        h = [f'kind = "{self.hysteresis}"']
        if self.hysteresis in _ELEMENT_KEY:
            h.append(f"{_ELEMENT_KEY[self.hysteresis]} = {self.elements}")
        if self.hysteresis == "preisach" and inputs is not None:
            lo, hi = preisach_range(*inputs, self.elements)
            h.append(f"range = [{lo!r}, {hi!r}]")
        if self.polynomial and self.hysteresis != "none":
            h.append(f"polynomial = {self.polynomial}")
        out["hysteresis"] = h
        if self.creep != "none":
            c = [f'kind = "{self.creep}"']
            if self.creep == "kelvin_voigt":
                c.append(f"order = {self.creep_order}")
            elif self.creep == "lag":
                c.append(f"lags = {self.creep_order}")
            c.append(f'structure = "{self.creep_structure}"')
            out["creep"] = c
        if self.dynamics:
            out["dynamics"] = [f"order = {self.dynamics}"]
            if self.zeros:
                out["dynamics"].append(f"zero_pairs = {self.zeros // 2}" if self.dynamics >= 2 and self.zeros % 2 == 0
                                       else f"real_zeros = {self.zeros}")
        if self.prehistory and self.hysteresis != "none":
            out["state"] = ["prehistory = true"]
        if self.delay:
            out["input"] = ["delay = true"]
        return {table: "\n".join(lines) for table, lines in out.items()}

    def toml(self, base: str = "", inputs: tuple[float, float] | None = None) -> str:
        """The CONFIG of this structure: the tables of `base` (a CONFIG's text) as they are, and this structure's
        tables that `base` does not give (`inputs` as for `tables`)."""
        given = fixed_tables(base)
        own = [f"[{table}]\n{text}\n" for table, text in self.tables(inputs).items() if table not in given]
        return "\n".join(own) + ("\n" + base if base.strip() else "")

    def normal(self) -> "Structure":
        """The same model with the fields its CONFIG does not write at their defaults (a creep's order for none or
        a logarithmic creep, its structure for none, zeros without dynamics, the elements and polynomial of a kind
        without them), so that one CONFIG is one structure (fitted once)."""
        changes = {}
        if self.creep not in ("kelvin_voigt", "lag"):
            changes["creep_order"] = 1
        if self.creep == "none":
            changes["creep_structure"] = "parallel"
        if not self.dynamics:
            changes["zeros"] = 0
        if self.hysteresis not in _ELEMENT_KEY:
            changes["elements"] = Structure.elements
        if self.hysteresis == "none":
            changes |= dict(polynomial=0, prehistory=False)
        return dataclasses.replace(self, **changes)

    def valid(self) -> bool:
        """Whether the CONFIG can express it (a lag creep only in series; a prehistory needs a hysteresis; no more
        zeros than poles)."""
        return not ((self.creep == "lag" and self.creep_structure != "series")
                    or (self.prehistory and self.hysteresis == "none")
                    or (self.hysteresis == "none" and self.creep == "none" and self.dynamics == 0)
                    or self.zeros > self.dynamics)


def preisach_range(v_min: float, v_max: float, levels: int) -> tuple[float, float]:
    r"""The range of a Preisach grid of `levels` levels for records whose voltage spans `[v_min, v_max]`: its cells
    of side $h = (v_{\max} - v_{\min})/(\text{levels} - 1)$ cover the records' span and one row below it, so
    every level but the lowest switches within the records and the lowest row's relays, once on, never switch off
    (all relays whose switching-off value lies below the records behave alike). The kind's default, symmetric
    about 0, leaves half its levels unused on unipolar drives."""
    h = (v_max - v_min) / max(levels - 1, 1)
    return (v_min - h, v_max)


def fixed_tables(base: str) -> set[str]:
    """The searched tables a base CONFIG gives (the search leaves them as they are)."""
    if not base.strip():
        return set()
    try:
        raw = tomllib.loads(base.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as e:
        raise PiezojaxValueError(f"the base CONFIG is not valid TOML ({' '.join(str(e).split())})") from e
    if "observer" in raw or "model" in raw:
        raise PiezojaxValueError("the identification searches the structure of an actuator (pj.Actuator); a base "
                                 "CONFIG with [observer] or [model] is not searched")
    return {t for t in SEARCHED_TABLES if t in raw}


def creep_neighbours(s: Structure) -> list[Structure]:
    """`s` with each creep the search tries: none; Kelvin-Voigt of one and two lags and a lag creep, in series and
    in parallel (a lag creep only in series); a logarithmic creep in either structure."""
    out = [dataclasses.replace(s, creep="none")]
    for order in (1, 2):
        for structure in ("series", "parallel"):
            out.append(dataclasses.replace(s, creep="kelvin_voigt", creep_order=order, creep_structure=structure))
    out.append(dataclasses.replace(s, creep="lag", creep_order=1, creep_structure="series"))
    out += [dataclasses.replace(s, creep="logarithmic", creep_structure=st) for st in ("series", "parallel")]
    return out


def deeper_creep(s: Structure) -> list[Structure]:
    """One more lag than the chosen Kelvin-Voigt or lag creep (up to three)."""
    if s.creep not in ("kelvin_voigt", "lag") or s.creep_order >= 3:
        return []
    return [dataclasses.replace(s, creep_order=s.creep_order + 1)]


def dynamics_neighbours(s: Structure) -> list[Structure]:
    """`s` with no dynamics, one real pole, one and two resonances (without zeros)."""
    return [dataclasses.replace(s, dynamics=n, zeros=0) for n in (0, 1, 2, 4)]


def hysteresis_neighbours(s: Structure) -> list[Structure]:
    """`s` with each hysteresis kind (`HYSTERESIS_KINDS`)."""
    return [dataclasses.replace(s, hysteresis=k, polynomial=0, prehistory=s.prehistory and k != "none")
            for k in HYSTERESIS_KINDS]


EXTRAS = ("elements", "zeros", "polynomial", "prehistory", "delay")
"""The last stages, one at a time, in this order: each adds one part to the structure kept so far."""

MAX_ELEMENTS = 16
"""The most plays or elements the `"elements"` stage gives a PI, play or Maxwell-slip operator."""


def extra_neighbours(s: Structure, what: str | None = None) -> list[Structure]:
    """`s` with the part `what` of `EXTRAS` where it lacks it (every one of them for `None`): twice the plays or
    elements of a PI, play or Maxwell-slip operator (up to `MAX_ELEMENTS`; a finer staircase of thresholds), zeros
    in its dynamics (a pair, an antiresonance, with two poles or more; one real zero with one pole), an output
    polynomial of degree 2, a prehistory, an input delay."""
    out = []
    if (what in (None, "elements") and s.hysteresis in ("prandtl_ishlinskii", "play", "maxwell_slip")
            and s.elements < MAX_ELEMENTS):
        out.append(dataclasses.replace(s, elements=min(2 * s.elements, MAX_ELEMENTS)))
    if what in (None, "zeros") and s.dynamics and not s.zeros:
        out.append(dataclasses.replace(s, zeros=2 if s.dynamics >= 2 else 1))
    if what in (None, "polynomial") and s.hysteresis != "none" and not s.polynomial:
        out.append(dataclasses.replace(s, polynomial=2))
    if what in (None, "prehistory") and s.hysteresis != "none" and not s.prehistory:
        out.append(dataclasses.replace(s, prehistory=True))
    if what in (None, "delay") and not s.delay:
        out.append(dataclasses.replace(s, delay=True))
    return out
