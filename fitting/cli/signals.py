"""SIGINT and SIGTERM while a command runs: raised as `Interrupted` in the main thread, recorded or held where
an interrupt must not cut a write short."""

import contextlib
import signal
import sys
import threading

# ------------------------------------------------------------------------------------------------------ signals


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread like Ctrl-C's `KeyboardInterrupt`, so that every cleanup path
    (temporary outputs removed, the solver's saving of the last accepted parameters) runs for both."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: list[int] = []
_consumed = 0


def _on_signal(signum, frame):
    _received.append(signum)
    raise Interrupted(signum)


def _check_interrupted() -> None:
    """Raise for a signal whose exception was swallowed on its way (Python drops exceptions raised inside
    garbage-collector callbacks and `__del__`), so that no interrupt is ever lost: called before outputs are made
    visible."""
    if len(_received) > _consumed:
        raise Interrupted(_received[-1])


def _pending_interrupt() -> bool:
    """Whether a signal arrived that no one has handled yet (`_consume_interrupt`)."""
    return len(_received) > _consumed


def _consume_interrupt() -> None:
    """The interrupts so far were handled (the solver stopped and returned its last accepted point)."""
    global _consumed
    _consumed = len(_received)


def _interrupt_status() -> int:
    return 128 + (_received[-1] if _received else signal.SIGINT)


@contextlib.contextmanager
def _signals_handled(restore: bool = True):
    """SIGINT and SIGTERM raise `Interrupted` while the command runs (main thread only); the previous handlers are
    restored after it unless `restore` is False (the console script replaces them itself, see `console_main`)."""
    global _consumed
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    _consumed = 0
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    old_hook = sys.unraisablehook

    def hook(unraisable):
        # An interrupt raised inside a garbage-collector callback or `__del__` cannot propagate; Python would print
        # it with a traceback and go on. It is recorded in `_received`, and `_check_interrupted` raises it again
        # before any output is made visible.
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        old_hook(unraisable)

    sys.unraisablehook = hook
    for s in old:
        signal.signal(s, _on_signal)
    try:
        yield
    finally:
        if restore:
            for s, h in old.items():
                signal.signal(s, h)
            sys.unraisablehook = old_hook


def _record_signal(signum, frame):
    _received.append(signum)


def _hold_signals() -> None:
    """From here on SIGINT and SIGTERM are only recorded, never raised: called once the outputs are about to be made
    visible (the command's outcome is decided), and by the console script before the interpreter's teardown (where a
    raised interrupt would print a traceback from an `atexit` callback). `_signals_handled` restores the previous
    handlers when the command returns in-process."""
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, _record_signal)


# ------------------------------------------------------------------------------------------------------ helpers


@contextlib.contextmanager
def _signals_deferred():
    """Hold SIGINT and SIGTERM back (delivered when the block ends) while compiled extensions are imported: an
    interrupt inside an extension's initialisation becomes an `ImportError` with a traceback printed from C."""
    signals = {signal.SIGINT, signal.SIGTERM}
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)

