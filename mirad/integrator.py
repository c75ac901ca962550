"""Mitsuba integrator plugin ``radiosity``: render a scene's radiosity solution with ``mi.render``.

.. pluginparameters::

 * - tolerance
   - |float|
   - Target relative error of the radiosity solution, in (0, 1). (Default: 0.03)
 * - samples_per_link
   - |int|
   - Shadow rays and receiver quadrature points per link of the solver, >= 1. (Default: 16)
 * - seed
   - |int|
   - Seed of the solver and of the final gather; same seed, same image. (Default: 0)
 * - final_gather
   - |bool|
   - One bounce of gathering from the solution at each pixel's hit point (crisp contact
     shadows; costs pixels x elements x gather_rays shadow rays). (Default: false)
 * - smooth
   - |bool|
   - Interpolate radiosity between element corners (true) or show flat elements (false).
     (Default: true)
 * - gather_rays
   - |int|
   - Shadow rays per element in the final gather, >= 1. (Default: 4)
 * - shadow_textures
   - |bool|
   - Solve with convolution shadow textures on links from lights that would otherwise split
     their receiver; the pixels show the shadow inside the coarse element. (Default: false)

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

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

_DOC = __doc__


#: Plugin parameters: name -> (type, default). Solver defaults come from mirad.Settings.
def _parameters() -> dict:
    from .settings import Settings

    return {
        "tolerance": (float, Settings.tolerance),
        "samples_per_link": (int, Settings.samples_per_link),
        "seed": (int, Settings.seed),
        "final_gather": (bool, False),
        "smooth": (bool, True),
        "gather_rays": (int, 4),
        "shadow_textures": (bool, Settings.shadow_textures),
    }


#: Properties that Mitsuba's SamplingIntegrator base class reads itself.
_BASE_PROPERTIES = ("hide_emitters", "block_size", "samples_per_pass", "timeout")
#: At most this many scene objects keep a cached solution per integrator.
_CACHE_SIZE = 4

_classes: dict = {}


def _read(props, name: str, kind, default):
    if not props.has_property(name):
        return default
    value = props[name]
    if kind is bool:
        if not isinstance(value, bool):
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be a boolean "
                                f"(<boolean name=\"{name}\" value=\"true\"/>), got {value!r}")
    elif kind is int:
        if isinstance(value, bool) or not float(value).is_integer():
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be an integer "
                                f"(<integer name=\"{name}\" .../>), got {value!r}")
        value = int(value)
    else:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"radiosity integrator: parameter '{name}' must be a number, got {value!r}")
        value = float(value)
    return value


def _make_class():
    """The integrator class for the current Mitsuba variant (its base class is variant-specific)."""

    class RadiosityIntegrator(mi.SamplingIntegrator):
        def __init__(self, props=None):
            props = mi.Properties("radiosity") if props is None else props
            params = _parameters()
            unknown = [k for k in props.keys() if k not in params and k not in _BASE_PROPERTIES]
            if unknown:
                raise SettingsError(
                    f"radiosity integrator: unknown parameter '{unknown[0]}'; valid parameters are "
                    f"{', '.join(params)}")
            super().__init__(props)
            values = {name: _read(props, name, kind, default) for name, (kind, default) in params.items()}
            for name in params:
                if props.has_property(name):
                    props.mark_queried(name)
            from .settings import make_settings

            try:  # validate the solver options now, not at the first render
                make_settings(tolerance=values["tolerance"], samples_per_link=values["samples_per_link"],
                              seed=values["seed"])
            except SettingsError as exc:
                raise SettingsError(f"radiosity integrator: {exc}") from None
            if values["gather_rays"] < 1:
                raise SettingsError(f"radiosity integrator: gather_rays={values['gather_rays']} must be >= 1")
            self.tolerance = values["tolerance"]
            self.samples_per_link = values["samples_per_link"]
            self.seed = values["seed"]
            self.final_gather = values["final_gather"]
            self.smooth = values["smooth"]
            self.gather_rays = values["gather_rays"]
            self.shadow_textures = values["shadow_textures"]
            self._cache = {}  # id(mi.Scene) -> (mi.Scene, Shading)

        # --- the solution of a scene -----------------------------------------------------
        def set_solution(self, scene, solution) -> None:
            """Use ``solution`` for ``scene`` (an mi.Scene) instead of solving it."""
            from .display import Shading

            if solution.scene is None or solution.scene.mi_scene is not scene:
                from .scene import load_scene

                solution.attach(load_scene(scene))
            self._remember(scene, Shading(solution))

        def solution(self, scene):
            """The solution used for ``scene`` (solved on first use, then cached)."""
            return self._shading(scene).solution

        def _remember(self, scene, shading) -> None:
            self._cache[id(scene)] = (scene, shading)
            while len(self._cache) > _CACHE_SIZE:
                self._cache.pop(next(iter(self._cache)))

        def _shading(self, scene):
            entry = self._cache.get(id(scene))
            if entry is not None and entry[0] is scene:
                return entry[1]
            from . import solve
            from .display import Shading
            from .scene import load_scene

            loaded = load_scene(scene)
            sol = solve(loaded, tolerance=self.tolerance, samples_per_link=self.samples_per_link,
                        seed=self.seed, shadow_textures=self.shadow_textures, variant=mi.variant())
            shading = Shading(sol)
            self._remember(scene, shading)
            return shading

        # --- Mitsuba interface -------------------------------------------------------------
        def sample(self, scene, sampler, ray, medium=None, active=True):
            shading = self._shading(scene)
            active = mi.Bool(active)
            # ---------------- camera rays: Mitsuba's own geometry ----------------
            si = scene.ray_intersect(ray, active)
            valid = active & si.is_valid()
            # ---------------- the leaf under each hit point ----------------------
            color, leaf, found = shading.radiance(si, ray.d, valid, smooth=self.smooth)
            if self.final_gather:
                gathered = shading.gathered_radiance(si, ray.d, leaf, found, valid,
                                                     rays=self.gather_rays, seed=self.seed)
                color = dr.select(found, gathered, color)
            color = dr.select(valid, color, 0.0)
            # ---------------- rays that leave the scene --------------------------
            env = scene.environment()
            if env is not None and not self.hide_emitters:
                color = dr.select(valid, color, env.eval(si, active & ~valid))
            return color, valid, []

        def aov_names(self):
            return []

        def to_string(self):
            return (f"RadiosityIntegrator[tolerance={self.tolerance}, samples_per_link="
                    f"{self.samples_per_link}, seed={self.seed}, final_gather={self.final_gather}, "
                    f"smooth={self.smooth}, gather_rays={self.gather_rays}, "
                    f"shadow_textures={self.shadow_textures}]")

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
