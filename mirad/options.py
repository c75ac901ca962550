"""Every option of the API, the CLI and the plugin, from one table: ``Settings`` and ``RENDER``.

Solver options are the fields of :class:`mirad.settings.Settings`: their types and defaults
come from the dataclass, their help from its docstring. Display options (how a solution is
drawn) are :data:`RENDER`. The CLI (``cli.py``) adds one ``--name`` per option, the plugin
(``integrator.py``) reads one parameter per option, and ``mirad.solve``/``mirad.render`` take
them as keywords, so the three cannot drift (``tests/test_options.py`` compares them).
"""

from __future__ import annotations

import argparse
import dataclasses
import re

from .errors import SettingsError
from .settings import CORES, MAX_SAMPLES_PER_LINK, ORACLES, SOLVERS, SWITCHES, Settings, annotation_text

__all__ = ["Option", "SOLVE", "RENDER", "PLUGIN", "add_arguments", "given", "check_render"]


@dataclasses.dataclass(frozen=True)
class Option:
    """One option: name (Python spelling), kind (float, int, str or bool), default, whether None
    is allowed, choices (or None) and a one-paragraph help text."""

    name: str
    kind: type
    default: object
    optional: bool
    choices: tuple | None
    help: str

    @property
    def flag(self) -> str:
        """The CLI spelling, ``--samples-per-link``."""
        return "--" + self.name.replace("_", "-")


_CHOICES = {"solver": SOLVERS, "oracle": ORACLES, "shaft_culling": SWITCHES, "clustering": SWITCHES,
            "core": CORES, "periodic_up": ("+z", "-z", "+y", "-y", "+x", "-x")}
_KINDS = {"float": float, "int": int, "str": str, "bool": bool}


def _docstring_help(doc: str) -> dict:
    """Field name -> help text, from the numpydoc ``Attributes`` section of a docstring."""
    out, name, lines = {}, None, []
    for line in doc.split("Attributes", 1)[1].splitlines()[2:]:
        head = re.match(r"    (\w+) : ", line)
        if head:
            if name:
                out[name] = " ".join(lines)
            name, lines = head.group(1), []
        elif name and line.strip():
            lines.append(line.strip())
    if name:
        out[name] = " ".join(lines)
    return out


def settings_options() -> tuple:
    """One Option per field of Settings, in order, from its annotation, default and docstring."""
    helps = _docstring_help(Settings.__doc__)
    options = []
    for f in dataclasses.fields(Settings):
        kind_text = annotation_text(f.type).replace(" ", "")
        optional = "None" in kind_text
        kind = _KINDS[kind_text.replace("|None", "")]
        options.append(Option(f.name, kind, f.default, optional, _CHOICES.get(f.name), helps.get(f.name, "")))
    return tuple(options)


#: Solver options: one per field of Settings, same order.
SOLVE = settings_options()

#: Display options of ``mirad.render``, ``mirad render`` and the plugin.
RENDER = (
    Option("spp", int, 4, False, None, "Samples per pixel (>= 1)."),
    Option("smooth", bool, True, False, None,
           "Interpolate radiosity between element corners (true) or show flat elements (false)."),
    Option("final_gather", bool, False, False, None,
           "One bounce of gathering from the solution at each pixel's hit point (crisp contact "
           "shadows; costs pixels x elements x gather_rays shadow rays)."),
    Option("gather_rays", int, 4, False, None, "Shadow rays per element in the final gather (>= 1)."),
)

#: Plugin parameters: solver options (the variant is Mitsuba's, the plugin is quiet unless told)
#: and display options (``spp`` is mi.render's own).
PLUGIN = tuple(o for o in SOLVE if o.name != "variant") + tuple(o for o in RENDER if o.name != "spp")

_DEFAULTS = {o.name: o.default for o in SOLVE + RENDER}


def default(name: str):
    """Default value of an option."""
    return _DEFAULTS[name]


def _cli_help(option: Option) -> str:
    first = re.split(r"(?<=[.;])\s", option.help, maxsplit=1)[0].rstrip(".;")
    shown = option.default if option.kind is not bool else str(option.default).lower()
    return f"{first} (default {shown})".replace("%", "%%")


def add_arguments(parser: argparse.ArgumentParser, options, *, skip=()) -> None:
    """Add ``--name`` for each option (default None: unset means the option's own default)."""
    for o in options:
        if o.name in skip:
            continue
        if o.kind is bool:
            parser.add_argument(o.flag, action=argparse.BooleanOptionalAction, default=None, help=_cli_help(o))
        else:
            parser.add_argument(o.flag, type=o.kind, default=None, choices=o.choices, help=_cli_help(o),
                                metavar=None if o.choices else o.name.upper())


def given(args, options, *, skip=()) -> dict:
    """The options set on the command line: name -> value."""
    return {o.name: getattr(args, o.name) for o in options
            if o.name not in skip and getattr(args, o.name, None) is not None}


def check_render(*, spp=None, gather_rays=None, smooth=None, final_gather=None) -> None:
    """Check display options; SettingsError naming the option and the fix."""
    for name, value in (("spp", spp), ("gather_rays", gather_rays)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or int(value) != value or value < 1):
            raise SettingsError(f"{name}={value!r} must be an integer >= 1 (e.g. {default(name)})")
        if value is not None and value > MAX_SAMPLES_PER_LINK:
            raise SettingsError(f"{name}={value!r} is more than a render pass of bounded memory holds; give at most "
                                f"{MAX_SAMPLES_PER_LINK} (e.g. {default(name)}) and average several renders for more")
    for name, value in (("smooth", smooth), ("final_gather", final_gather)):
        if value is not None and not isinstance(value, bool):
            raise SettingsError(f"{name}={value!r} must be True or False")


def plugin_table() -> str:
    """The ``pluginparameters`` table of the plugin's docstring, built from PLUGIN."""
    kinds = {float: "|float|", int: "|int|", str: "|string|", bool: "|bool|"}
    rows = []
    for o in PLUGIN:
        shown = "none" if o.default is None else (str(o.default).lower() if o.kind is bool else o.default)
        rows.append(f" * - {o.name}\n   - {kinds[o.kind]}\n   - {o.help} (Default: {shown})")
    return ".. pluginparameters::\n\n" + "\n".join(rows)
