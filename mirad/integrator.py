"""Mitsuba integrator plugin ``radiosity``: render a scene's radiosity solution with ``mi.render``.

{table}

Solver parameters are the fields of ``mirad.Settings`` (mirad/settings.py); the table is built
from ``mirad.options.PLUGIN``. The plugin solves quietly unless ``quiet`` is false.

Also accepted, as for every Mitsuba sampling integrator: ``hide_emitters``, ``block_size``,
``samples_per_pass``, ``timeout``. Any other property is an error naming it.

Each camera ray is traced by Mitsuba; the pixel shows the radiance B/pi of the leaf element
under its hit point (``mirad/display.py``). Directly visible area emitters show their radiosity
(emission plus reflected light) as radiance, non-diffuse surfaces their diffuse approximation,
and rays that leave the scene the environment emitter, if any. The solution is computed on the
first render of a scene object and kept, so further sensors or sample counts do not solve again.

.. tabs::

    .. code-tab:: xml

        <integrator type="radiosity">
            <float name="tolerance" value="0.02"/>
            <boolean name="final_gather" value="true"/>
        </integrator>

    .. code-tab:: python

        'type': 'radiosity',
        'tolerance': 0.02,
        'final_gather': True
"""

from __future__ import annotations

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import SettingsError
from .options import PLUGIN, check_render, plugin_table
from .scene import load_scene
from .settings import make_settings
from .shading import Shading, view_class
from .solver import solve_problem

import mitsuba as mi  # noqa: E402

__doc__ = __doc__.replace("{table}", plugin_table())
_DOC = __doc__

#: Properties that Mitsuba's SamplingIntegrator base class reads itself.
_BASE_PROPERTIES = ("hide_emitters", "block_size", "samples_per_pass", "timeout")
#: Parameters that are display options, not solver settings.
_DISPLAY = ("smooth", "final_gather", "gather_rays")

_classes: dict = {}


def _read(props, option):
    """The value of one plugin parameter (its default when absent), type-checked."""
    name, kind = option.name, option.kind
    if not props.has_property(name):
        return option.default
    value = props[name]
    if kind is bool:
        if not isinstance(value, bool):
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be a boolean "
                                f"(<boolean name=\"{name}\" value=\"true\"/>), got {value!r}")
    elif kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be an integer "
                                f"(<integer name=\"{name}\" .../>), got {value!r}")
        value = int(value)
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be a number, got {value!r}")
        value = float(value)
    elif not isinstance(value, str):
        raise SettingsError(f"radiosity integrator: parameter '{name}' must be a string "
                            f"(<string name=\"{name}\" .../>), got {value!r}")
    return value


def _make_class():
    """The integrator class for the current Mitsuba variant (its base class is variant-specific)."""

    class RadiosityIntegrator(view_class()):
        def __init__(self, props=None):
            props = mi.Properties("radiosity") if props is None else props
            names = [o.name for o in PLUGIN]
            unknown = [k for k in props.keys() if k not in names and k not in _BASE_PROPERTIES]
            if unknown:
                raise SettingsError(
                    f"radiosity integrator: unknown parameter '{unknown[0]}'; valid parameters are "
                    f"{', '.join(names)}")
            super().__init__(props)
            values = {o.name: _read(props, o) for o in PLUGIN}
            for name in names:
                if props.has_property(name):
                    props.mark_queried(name)
            solve = {k: v for k, v in values.items() if k not in _DISPLAY}
            if not props.has_property("quiet"):
                solve["quiet"] = True
            try:  # validate every option now, not at the first render
                self.settings = make_settings(**solve)
                check_render(**{k: values[k] for k in _DISPLAY})
            except SettingsError as exc:
                raise SettingsError(f"radiosity integrator: {exc}") from None
            for o in PLUGIN:  # every parameter readable as an attribute (integrator.tolerance, ...)
                setattr(self, o.name, getattr(self.settings, o.name) if o.name not in _DISPLAY else values[o.name])

        def _shading(self, scene):
            """The shading of ``scene``: the one set or solved before, else solve it now."""
            shading = self._cached(scene)
            if shading is None:
                loaded = load_scene(scene)
                shading = Shading(solve_problem(loaded, self.settings.replace(variant=mi.variant())))
                self._remember(scene, shading)
            return shading

        def to_string(self):
            shown = ", ".join(f"{o.name}={getattr(self, o.name)}" for o in PLUGIN)
            return f"RadiosityIntegrator[{shown}]"

    RadiosityIntegrator.__doc__ = _DOC
    return RadiosityIntegrator


def integrator_class():
    """The ``radiosity`` integrator class of the current variant."""
    variant = mi.variant()
    if variant not in _classes:
        _classes[variant] = _make_class()
    return _classes[variant]


def make_integrator(**params):
    """A ``radiosity`` integrator with the given parameters (see the module docstring)."""
    props = mi.Properties("radiosity")
    for name, value in params.items():
        props[name] = value
    return integrator_class()(props)


def register() -> None:
    """Register ``radiosity`` with Mitsuba for the current variant (no-op without a variant)."""
    if mi.variant() is None:
        return
    cls = integrator_class()
    mi.register_integrator("radiosity", lambda props: cls(props))


def _on_variant_change(old, new) -> None:
    if new is not None:
        register()


def install() -> None:
    """Register now and again whenever the Mitsuba variant changes."""
    register()
    if not getattr(install, "_done", False):
        mi.detail.add_variant_callback(_on_variant_change)
        install._done = True
