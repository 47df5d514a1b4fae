"""How a command ends when it is stopped: SIGTERM raised as :class:`Terminated` so the same clean-up runs
as on Ctrl-C, one line and the shell's status (130 / 143) instead of a traceback
(:func:`ends_on_signals`, :func:`run_import`), signals held while a write must finish
(:func:`signals_deferred`) or left to a library that handles them (:func:`sigterm_left_alone`)."""

from __future__ import annotations

import contextlib
import functools
import json
import signal
import sys
import threading
from collections.abc import Iterator

# ------------------------------------------------------------------ signals
EXIT_SIGINT = 128 + int(signal.SIGINT)  # the status a shell gives a process ended by Ctrl-C: 130
EXIT_SIGTERM = 128 + int(signal.SIGTERM)  # ... and by SIGTERM: 143


class Terminated(SystemExit):
    """SIGTERM arrived while a command ran; exits with status 143 (128 + SIGTERM), as an untrapped one."""

    def __init__(self) -> None:
        super().__init__(EXIT_SIGTERM)


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """While the block runs, SIGTERM raises ``Terminated`` in the main thread so that the cleanup runs as on
    Ctrl-C; a second SIGTERM during that cleanup is ignored. The previous handler comes back afterwards.
    A no-op off the main thread, and where SIGTERM is ignored or handled outside Python."""
    previous = signal.getsignal(signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread() or previous in (signal.SIG_IGN, None):
        yield
        return
    fired = False

    def handler(signum, frame) -> None:
        nonlocal fired
        if not fired:
            fired = True
            raise Terminated

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def stopped_by(stop: BaseException) -> tuple[str, int]:
    """What stopped a command (:class:`Terminated` or ``KeyboardInterrupt``), in words, and the exit
    status a shell gives a process ended by that signal (143, 130)."""
    if isinstance(stop, Terminated):
        return "terminated (SIGTERM)", EXIT_SIGTERM
    return "interrupted (SIGINT)", EXIT_SIGINT


def signal_name(stop: BaseException | None) -> str | None:
    """The signal behind ``stop`` (:class:`Terminated`: ``"SIGTERM"``, ``KeyboardInterrupt``:
    ``"SIGINT"``), for a record; None for no stop."""
    if stop is None:
        return None
    return "SIGTERM" if isinstance(stop, Terminated) else "SIGINT"


def ends_on_signals(main):
    """A command's ``main`` (returning its exit status) that SIGINT and SIGTERM end with one line,
    ``error: interrupted (SIGINT)`` / ``error: terminated (SIGTERM)``, and the status a shell gives a
    process ended by that signal (130 / 143), not a traceback. Every file a command writes goes through
    :func:`~.files.atomic_target`, so a stopped command leaves no partial file; one that keeps work it
    finished says so itself before this line would be printed."""

    @functools.wraps(main)
    def ended(*args, **kwargs):
        try:
            with sigterm_raises():
                return main(*args, **kwargs)
        except (Terminated, KeyboardInterrupt) as stop:
            why, status = stopped_by(stop)
            print(f"error: {why}", file=sys.stderr)
            return status

    return ended


def run_import(convert, out, errors=(OSError, ValueError)) -> int:
    """An importer's run: ``convert()`` (its staging folder removed however it ends) under
    :func:`sigterm_raises`; a signal or an input error (``errors``) one line, exit
    130 / 143 or 2; else its summary printed as JSON, exit 0."""
    try:
        with sigterm_raises():
            summary = convert()
    except (Terminated, KeyboardInterrupt) as stop:
        why, status = stopped_by(stop)
        print(f"error: {why}; nothing was written to {out}", file=sys.stderr)
        return status
    except errors as err:  # CalibrationError and ImageError are ValueErrors
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2))
    return 0


@contextlib.contextmanager
def sigterm_left_alone() -> Iterator[None]:
    """While the block runs, SIGTERM has its default action again, as if :func:`sigterm_raises` were not
    around it: for a library that handles SIGTERM itself and would call a handler it finds (Lightning
    stops training at a batch boundary). A no-op off the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM arriving while the block runs are held until it ends, then given to the
    handlers that were there before: a write that must finish (a checkpoint: ``torch.save`` cut by
    Ctrl-C fails with a zip error, not ``KeyboardInterrupt``) is never cut in half, and the stop it
    asked for comes right after. A no-op off the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    wanted = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: arrived.append(signum)) for s in wanted}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for signum in dict.fromkeys(arrived):  # each once, in the order they came
            signal.raise_signal(signum)
