"""Where a command's wall time goes: `Timings` splits it into phases (`imports`, `read`, `starts`, `steps`, `write`)
and the time JAX spent compiling (`compile`: tracing, lowering and XLA compilation or loading from the persistent
cache), which it takes out of every phase it overlaps. The parts of the library that run a phase mark it with
`phase(name)`, which does nothing unless a `Timings` is recording (`with Timings() as t:`). Only the standard library
is imported here (the command line imports it before JAX)."""

import contextlib
import contextvars
import os
import time

COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
"""The JAX monitoring events whose time spans are compilation (`jax._src.dispatch`'s names): tracing a function to
a jaxpr, lowering it to MLIR, and compiling it (or reading it from the persistent compilation cache)."""

PHASES = ("imports", "read", "starts", "steps", "write")
"""The phases a command reports, in order (`compile` and `other` beside them)."""

_recording: contextvars.ContextVar["Timings | None"] = contextvars.ContextVar("piezojax_timings", default=None)
_listening = False


def _on_span(event: str, start: float, end: float, **kwargs) -> None:
    t = _recording.get()
    if t is not None and event in COMPILE_EVENTS:
        t.compile_spans.append((start, end))


def process_start() -> float | None:
    """The `time.time()` at which this process started (Linux: from /proc), or `None` where it cannot be read."""
    try:
        with open("/proc/self/stat") as f:
            started = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22: start time in clock ticks after boot
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return time.time() - (uptime - started / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


class Timings:
    """A record of a command's phases and of JAX's compilation within them.

    `with Timings() as t:` records until the block ends; inside it `phase(name)` marks a phase. `summary()` gives
    seconds per phase with the compilation inside it taken out, `compile` (the union of the compilation spans, each
    instant counted once: JAX traces nested functions inside an outer trace), `other` (the rest of the wall time) and
    `total`. Compilation while no phase runs counts in `compile` alone."""

    def __init__(self, start: float | None = None):
        self.start = time.time() if start is None else start
        self.end: float | None = None
        self.phases: dict[str, list[tuple[float, float]]] = {}
        self.compile_spans: list[tuple[float, float]] = []
        self._token = None

    def __enter__(self) -> "Timings":
        global _listening
        if not _listening:
            import jax.monitoring  # here, not at import: the command line imports this module before JAX

            jax.monitoring.register_event_time_span_listener(_on_span)
            _listening = True
        self._token = _recording.set(self)
        return self

    def __exit__(self, *exc) -> None:
        self.end = time.time()
        _recording.reset(self._token)

    def add(self, name: str, start: float, end: float) -> None:
        """Count the interval `[start, end]` (`time.time()`) in the phase `name`."""
        self.phases.setdefault(name, []).append((start, end))

    def summary(self) -> dict[str, float]:
        """Seconds per phase (compilation taken out), `compile`, `other` and `total`, rounded to milliseconds."""
        end = time.time() if self.end is None else self.end
        compiled = _union(self.compile_spans)
        out = {}
        for name in PHASES + tuple(n for n in self.phases if n not in PHASES):
            spans = _union(self.phases.get(name, []))
            out[name] = sum(b - a for a, b in spans) - _overlap(spans, compiled)
        out["compile"] = sum(b - a for a, b in compiled)
        total = end - self.start
        out["other"] = max(total - sum(out.values()), 0.0)
        out["total"] = total
        return {k: round(v, 3) for k, v in out.items()}

    def line(self) -> str:
        """One line for stderr: `51.8 s: imports 3.1, read 0.2, ... other 0.4`."""
        s = self.summary()
        return f"{s['total']:.1f} s: " + ", ".join(f"{k} {v:.1f}" for k, v in s.items() if k != "total")


@contextlib.contextmanager
def phase(name: str):
    """Mark the block as the phase `name` of the `Timings` recording, if any. Phases do not nest (a nested one
    would count in both, and `other` no longer make up the rest)."""
    t = _recording.get()
    start = time.time()
    try:
        yield
    finally:
        if t is not None:
            t.add(name, start, time.time())


def _union(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[list[float]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def _overlap(xs: list[tuple[float, float]], ys: list[tuple[float, float]]) -> float:
    """The length of the intersection of two unions of disjoint sorted intervals."""
    total, j = 0.0, 0
    for a, b in xs:
        while j < len(ys) and ys[j][1] <= a:
            j += 1
        k = j
        while k < len(ys) and ys[k][0] < b:
            total += min(b, ys[k][1]) - max(a, ys[k][0])
            k += 1
    return total
