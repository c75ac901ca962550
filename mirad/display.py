"""Images of a radiosity solution from the scene's sensor, and image files.

``render(scene, solution)`` draws the solution with the view integrator of ``shading.py``
(the point-to-leaf lookup in Dr.Jit); ``mirad.render`` solves first when no solution is given.
``write_image`` writes linear EXR and a tonemapped sRGB PNG beside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import OutputError, SettingsError
from .files import atomic_write, exr_bytes, png_bytes, srgb8
from .options import check_render, default
from .scene import load_scene
from .shading import view_class

import mitsuba as mi  # noqa: E402

__all__ = ["render", "write_image", "check_spp", "srgb8"]


def render(scene, solution, *, spp: int = default("spp"), seed: int = 0, smooth: bool = default("smooth"),
           final_gather: bool = default("final_gather"), gather_rays: int = default("gather_rays"),
           sensor: int = 0, quiet: bool = True) -> np.ndarray:
    """Image (H, W, 3) float32 of a radiosity solution, radiance in W/(m^2 sr), from the scene's sensor.

    Parameters
    ----------
    scene : mirad Scene, XML path, Mitsuba dict or mi.Scene
    solution : Solution of that scene (its scene fingerprint must match)
    spp : samples per pixel (>= 1)
    seed : seed of the pixel samples and of the final gather (same seed -> same image)
    smooth : interpolate between element corners (True) or show flat elements (False)
    final_gather : one bounce of gathering from the solution at each pixel's hit point
    gather_rays : shadow rays per leaf element in the final gather
    sensor : index of the sensor in the scene
    quiet : no progress bar (the final gather shows one unless quiet)

    >>> img = render(scene, sol, spp=1)   # doctest: +SKIP
    >>> img.shape                         # doctest: +SKIP
    (256, 256, 3)
    """
    check_render(spp=spp, gather_rays=gather_rays, smooth=smooth, final_gather=final_gather)
    loaded = load_scene(scene)
    if solution.scene is not loaded:
        solution.attach(loaded)
    sensors = loaded.mi_scene.sensors()
    if not sensors:
        raise SettingsError(f"'{loaded.source or '<scene>'}' has no sensor; add a <sensor> to render it")
    if not (0 <= sensor < len(sensors)):
        raise SettingsError(f"sensor={sensor} is out of range; the scene has {len(sensors)} sensor(s)")
    integrator = view_class()()
    integrator.smooth, integrator.final_gather = bool(smooth), bool(final_gather)
    integrator.gather_rays, integrator.seed, integrator.quiet = int(gather_rays), int(seed), bool(quiet)
    integrator.set_solution(loaded.mi_scene, solution)
    image = mi.render(loaded.mi_scene, integrator=integrator, sensor=sensor, spp=int(spp), seed=int(seed))
    return np.array(image, dtype=np.float32)[..., :3]


def check_spp(spp) -> int:
    """spp as an int; SettingsError unless it is an integer >= 1."""
    check_render(spp=spp)
    return int(spp)


def write_image(path, image: np.ndarray, *, png: bool = True, exposure: float = 0.0) -> list:
    """Write an image (H, W, 3) as OpenEXR (linear float RGB), and a tonemapped sRGB PNG beside it. Atomic.

    Returns the paths written.
    """
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise OutputError(f"image output '{path}' must end in .exr (linear float RGB)")
    data = exr_bytes({"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]})
    png_data = png_bytes(srgb8(image, exposure=exposure)) if png else None
    written = [atomic_write(path, lambda handle: handle.write(data))]
    if png:
        written.append(atomic_write(path.with_suffix(".png"), lambda handle: handle.write(png_data)))
    return written
