"""Exceptions raised by mirad, and its warnings. Every message names the file, shape or parameter
and the fix."""

from __future__ import annotations

import os
import sys
import warnings

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` at the caller's line outside mirad (the user's ``mirad.solve(...)``, the
    CLI's entry point), however deep inside the package it was raised: a fixed ``stacklevel``
    pointed into mirad's own modules whenever the call came another way (the API, the CLI, the
    Mitsuba plugin, a test), and Python then showed it once per process for every caller."""
    level, frame = 2, sys._getframe(1)
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


class MiradError(Exception):
    """Base class of every error mirad raises on purpose (the CLI prints these without a traceback)."""


class SceneError(MiradError):
    """The scene cannot be loaded or contains something mirad cannot solve."""


class SettingsError(MiradError, ValueError):
    """An option has a value outside its valid range."""


class EnvironmentProblem(MiradError):
    """The installation (LLVM, Mitsuba variant) cannot run mirad."""


class SolutionMismatch(MiradError):
    """A saved solution does not belong to the scene it is applied to."""


class OutputError(MiradError):
    """An output file cannot be written."""


class BandTableError(MiradError, ValueError):
    """A band table (``mirad.bands``) that cannot apply to its scene: unknown ids or bands, missing
    rows or values, values out of range."""
