"""Exceptions raised by mirad. Every message names the file, shape or parameter and the fix."""

from __future__ import annotations


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
