"""The package's user-facing errors: one root, :class:`FvinMpcError`, that every command catches.

A command (``python -m fvin_mpc.<cmd>``, through :func:`run_command`) prints an
error of this hierarchy as one line, ``error: <message>``, on stderr and exits with status 2 (an option
argparse refuses too; Ctrl-C: one line and status 130); any other exception is a bug and keeps its
traceback. Raise these for what the user can fix (an option's value, a scene, a checkpoint, a data
file, an output path), with a message that says what to change, and before any work: validate once,
at the edge (docs/bad-inputs.md lists the refusals, each with its line).

This module sits in the core, the lowest layer, so that every layer may raise these
(``tests/test_layers.py``), and imports nothing of the package. The subclasses that stand for a bad
value also derive from :class:`ValueError`, so code that caught ``ValueError`` still catches them.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
from typing import Any, Callable, Iterator, NoReturn, Sequence


class FvinMpcError(Exception):
    """The root of the errors a user caused and can fix; the message is shown as is."""


class UsageError(FvinMpcError, ValueError):
    """An option's value, or a combination of options, that makes no sense (``--duration 0``)."""


class SceneError(FvinMpcError, ValueError):
    """A scene that is neither built in nor an existing MJCF file, or one that cannot be simulated."""


class DataFileNotFound(FvinMpcError, FileNotFoundError):
    """A trajectory-data file that is not there (a ``FileNotFoundError`` too)."""


class DataFileError(FvinMpcError, ValueError):
    """A file that is not the kind of trajectory data asked for."""


#: The exit status of a command stopped with Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED_STATUS = 130
#: What a command without torch is told (``learn`` and ``train`` train models; the runtime needs none).
INSTALL_TRAIN = 'pip install torch==2.13.0 && pip install -e ".[train]"'


#: Whether a Ctrl-C is pending in the command that runs (:func:`run_command`): set by its handler.
_PENDING = {"interrupted": False}


def raise_if_interrupted() -> None:
    """``KeyboardInterrupt`` if a Ctrl-C is pending: what a long loop (a closed-loop episode) calls once per
    step, so that an interrupt a callee swallowed as an error of its own (``except Exception`` around a
    solve) still stops the command there."""
    if _PENDING["interrupted"]:
        raise KeyboardInterrupt


@contextlib.contextmanager
def _interrupts_that_stick() -> Iterator[dict[str, bool]]:
    """Ctrl-C that stops the command wherever it lands. CasADi's solvers poll for an interrupt from inside
    a solve: Python's own handler would raise ``KeyboardInterrupt`` there, CasADi stops the solve, prints a
    warning and swallows it, and the MPC reports a failed solve while the episode runs on. So Ctrl-C only
    marks the interrupt here, and a trace function raises it at the next line of Python code the command
    runs (once the solve has returned). Only in the main thread, where the default handler is installed."""
    state = _PENDING
    state["interrupted"] = False
    if threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield state
        return

    def stop(frame: Any, event: str, arg: Any) -> Any:
        raise KeyboardInterrupt

    def on_interrupt(signum: int, frame: Any) -> None:
        state["interrupted"] = True
        sys.settrace(stop)  # frames entered from now on
        while frame is not None:  # and the frames running now, from their next line on
            frame.f_trace, frame.f_trace_lines = stop, True
            frame = frame.f_back

    signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield state
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        if state["interrupted"]:
            sys.settrace(None)


def _one_line_parse_error(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """``ArgumentParser.error`` while a command runs: the parse error as a :class:`UsageError`, so that
    it is printed as the one line every other refusal is (argparse's own prints the usage block first)."""
    raise UsageError(f"{message} (see {parser.prog} --help)")


def run_command(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """A command's exit status: ``main(argv)``'s, 2 for an error the user can fix, 130 for Ctrl-C.

    A :class:`FvinMpcError` is printed as one line, ``error: <message>``, on stderr, without a
    traceback: the message names what to change, and a traceback would bury it. So is an option
    argparse refuses while ``main`` parses (its usage block left out: ``--help`` shows it), and a
    missing torch (the train extra: the runtime needs none). Ctrl-C is one line too, ``error:
    interrupted``, and status 130; outputs are written whole at the end of a command's work
    (data through a temporary file), so nothing is left half written. Any other exception propagates
    with its traceback, since it is a bug rather than a bad input.
    """
    saved = argparse.ArgumentParser.error
    argparse.ArgumentParser.error = _one_line_parse_error  # type: ignore[method-assign, assignment]
    try:
        with _interrupts_that_stick() as interrupt:
            try:
                status = main(argv)
            except Exception:
                # Raised from a frame that C code called (NumPy converting a CasADi matrix), the interrupt
                # reaches Python as that caller's error (a SystemError): while one is pending, any error is it.
                if interrupt["interrupted"]:
                    raise KeyboardInterrupt from None
                raise
        if interrupt["interrupted"]:  # swallowed to the end: the work may be whole, but it was not wanted
            raise KeyboardInterrupt
        return status
    except FvinMpcError as error:
        print("error: " + " ".join(str(error).split()), file=sys.stderr)
        return 2
    except ModuleNotFoundError as error:
        if error.name != "torch":
            raise
        print(f"error: this command trains models and needs torch, which is not installed: {INSTALL_TRAIN}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted (Ctrl-C)", file=sys.stderr)
        return INTERRUPTED_STATUS
    finally:
        argparse.ArgumentParser.error = saved  # type: ignore[method-assign]
