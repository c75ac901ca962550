"""mirad: hierarchical radiosity for Mitsuba 3 scenes.

>>> import mirad                                                     # doctest: +SKIP
>>> sol = mirad.solve("scenes/cornell-box/scene.xml", tolerance=0.02)  # doctest: +SKIP
>>> sol.shape_radiosity("floor")                                     # doctest: +SKIP
"""

from __future__ import annotations

from . import _runtime  # noqa: F401  (must run before mitsuba is imported)
from .errors import (BandTableError, EnvironmentProblem, MiradError, OutputError, SceneError, SettingsError,
                     SolutionMismatch)
from .errors import warn as _warn
from .scene import Scene, load_scene
from .bands import read_band_table, with_bands
from .options import check_render, default
from .settings import Settings, make_settings
from .solution import Solution, load_solution

__all__ = ["load_scene", "solve", "render", "load_solution", "with_bands", "read_band_table", "Scene", "Solution",
           "Settings", "MiradError", "SceneError", "SettingsError", "EnvironmentProblem", "SolutionMismatch",
           "OutputError", "BandTableError"]
__version__ = "0.1.0"


def _default_variant() -> None:
    """Like Sionna: pick cuda_ad_rgb (GPU) else llvm_ad_rgb when no variant is set yet."""
    import mitsuba as mi

    if mi.variant() is None:
        try:
            _runtime.choose_variant(None)
        except EnvironmentProblem:
            pass  # reported with its fix when a solve starts


_default_variant()


def _register_plugin() -> None:
    """Make ``<integrator type="radiosity">`` (mirad/integrator.py) and ``<bsdf type="leaf">``
    (mirad/leaf.py) available in every variant."""
    from .integrator import install
    from .leaf import install as install_leaf

    install()
    install_leaf()


_register_plugin()


def render(scene, solution=None, *, spp: int = default("spp"), seed: int = 0, smooth: bool = default("smooth"),
           final_gather: bool = default("final_gather"), gather_rays: int = default("gather_rays"), sensor: int = 0,
           quiet: bool = True, **options):
    """Image (H, W, 3) float32 of a radiosity solution, radiance in W/(m^2 sr), from the scene's sensor.

    ``solution`` None solves the scene first with ``options`` (fields of mirad.Settings; ``seed``
    seeds both); the display options are those of mirad.options.RENDER (see mirad.display.render).
    ``quiet`` hides the progress bars of the solve and of the final gather.
    """
    from .display import render as _render

    check_render(spp=spp, gather_rays=gather_rays, smooth=smooth, final_gather=final_gather)
    loaded = load_scene(scene, variant=options.get("variant"))
    bands = loaded.band_names or (solution.stats.get("bands") if solution is not None else None)
    if bands:
        raise SettingsError(f"render shows RGB radiance, and this is a band solve ({', '.join(bands)}); "
                            "write its bands with mirad.export (tables, PLY, lightmaps) instead")
    if solution is None:
        solution = solve(loaded, seed=seed, quiet=quiet, **options)
    elif options:
        raise SettingsError(f"options {sorted(options)} only apply when render() solves; "
                            "drop them or pass solution=None")
    return _render(loaded, solution, spp=spp, seed=seed, smooth=smooth, final_gather=final_gather,
                   gather_rays=gather_rays, sensor=sensor, quiet=quiet)


def solve(scene, *, quiet: bool = True, **options) -> Solution:
    """Solve the radiosity of a scene (XML path, Mitsuba dict, mi.Scene or mirad Scene).

    Parameters
    ----------
    scene : the scene
    quiet : hide progress bars (the API is quiet unless told otherwise; the CLI is not)
    **options : fields of mirad.Settings (``tolerance``, ``samples_per_link``, ``seed``, ``solver``,
        ``oracle``, ``clustering``, ``max_links``, ``workers``, ...); each one's meaning, unit and
        default are documented there once, and any other name is an error

    Returns
    -------
    Solution
    """
    from .solver import solve_problem

    settings = make_settings(quiet=quiet, **options)
    loaded = load_scene(scene, variant=settings.variant)
    sol = solve_problem(loaded, settings)
    # what the diffuse, opaque model loses of non-diffuse or transmitting BSDFs: it does not
    # shrink with refinement, so it is reported beside the estimate, not refined against
    model = float(loaded.model_error(sol.triangle_irradiance, sol.back_irradiance,
                                     leaf_transmission=sol.stats.get("leaf_transmission") == "carried"))
    sol.stats["model_error"] = model
    sol.stats["total_error"] = float(sol.stats["estimated_error"]) + model
    if model > settings.tolerance:
        _warn(f"the scene's non-diffuse or transmitting BSDFs put this solution about {model:.1%} off "
              f"Mitsuba's path tracer whatever the tolerance ({settings.tolerance}): mirad models every "
              "surface as opaque and diffuse (see the loader's warnings and stats['model_error'])")
    return sol
