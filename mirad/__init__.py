"""mirad: hierarchical radiosity for Mitsuba 3 scenes.

>>> import mirad                                                     # doctest: +SKIP
>>> sol = mirad.solve("scenes/cornell-box/scene.xml", tolerance=0.02)  # doctest: +SKIP
>>> sol.shape_radiosity("floor")                                     # doctest: +SKIP
"""

from __future__ import annotations

from . import _runtime  # noqa: F401  (must run before mitsuba is imported)
from .errors import (EnvironmentProblem, MiradError, OutputError, SceneError, SettingsError,
                     SolutionMismatch)
from .scene import Scene, load_scene
from .settings import Settings, make_settings
from .solution import Solution, load_solution

__all__ = ["load_scene", "solve", "render", "load_solution", "Scene", "Solution", "Settings", "MiradError",
           "SceneError", "SettingsError", "EnvironmentProblem", "SolutionMismatch", "OutputError"]
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
    """Make ``<integrator type="radiosity">`` available in every variant (mirad/integrator.py)."""
    from .integrator import install

    install()


_register_plugin()


def render(scene, solution=None, *, spp: int = 4, **options):
    """Image (H, W, 3) of a radiosity solution from the scene's sensor; see mirad.display.render."""
    from .display import render as _render

    return _render(scene, solution, spp=spp, **options)


def solve(scene, *, tolerance: float = 0.03, samples_per_link: int = 16, seed: int = 0,
          solver: str | None = None, variant: str | None = None, quiet: bool = True,
          **options) -> Solution:
    """Solve the radiosity of a scene (XML path, Mitsuba dict, mi.Scene or mirad Scene).

    Parameters
    ----------
    tolerance : target relative error of the solution (see mirad.settings)
    samples_per_link : shadow rays and receiver quadrature points per link
    seed : random seed (same seed, same input, same variant -> bitwise same output)
    solver : "gmres" (default), "gauss-seidel" or "jacobi"
    variant : Mitsuba variant; default cuda_ad_rgb with a GPU, else llvm_ad_rgb
    quiet : hide progress bars
    **options : further fields of mirad.Settings

    Returns
    -------
    Solution
    """
    from .solver import solve_problem

    settings = make_settings(tolerance=tolerance, samples_per_link=samples_per_link, seed=seed,
                             solver=solver, variant=variant, quiet=quiet, **options)
    loaded = load_scene(scene, variant=settings.variant)
    return solve_problem(loaded, settings)
