"""The package's user-facing errors: one root, :class:`FvinMpcError`, that every command catches.

A command (``python -m fvin_mpc.<cmd>``, through :func:`run_command`) prints an
error of this hierarchy as one line, ``error: <message>``, on stderr and exits with status 2; any
other exception is a bug and keeps its traceback. Raise these for what the user can fix (an
option's value, a scene, a checkpoint), with a message that says what to change.

This module sits in the core, the lowest layer, so that every layer may raise these
(``tests/test_layers.py``), and imports nothing of the package. The subclasses that stand for a bad
value also derive from :class:`ValueError`, so code that caught ``ValueError`` still catches them.
"""

from __future__ import annotations

import sys
from typing import Callable, Sequence


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


def run_command(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """A command's exit status: ``main(argv)``'s, or 2 for an error the user can fix.

    A :class:`FvinMpcError` is printed as one line, ``error: <message>``, on stderr, without a
    traceback: the message names what to change, and a traceback would bury it. Any other exception
    propagates with its traceback, since it is a bug rather than a bad input.
    """
    try:
        return main(argv)
    except FvinMpcError as error:
        print("error: " + " ".join(str(error).split()), file=sys.stderr)
        return 2
