"""Shared fixtures: tiny scenes built in code, tolerances, the variant."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import mirad  # noqa: F401  (sets up LLVM and the default variant before mitsuba is used)
import mitsuba as mi

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"

#: Closed-form checks (issue: within 1 %).
CLOSED_FORM_REL = 0.01
#: Reciprocity of sampled transfers on unoccluded pairs.
RECIPROCITY_REL = 0.02
#: Parallel unit squares at distance 1 and perpendicular unit squares sharing an edge (Howell).
F_PARALLEL = 0.199825
F_PERPENDICULAR = 0.200044


def load_script(path: Path, name: str):
    """The Python file at ``path`` (a validation script or a scene generator, not a package
    module) imported as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session", autouse=True)
def variant():
    """Run everything on the JIT variant mirad picks at import (CUDA where present, else LLVM)."""
    return mi.variant()


def square(to_world, *, rho=0.5, radiance=None, sid=None):
    d = {"type": "rectangle", "to_world": to_world,
         "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}}
    if radiance is not None:
        d["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": radiance}}
    if sid:
        d["id"] = sid
    return d


def closed_box(rho: float, radiance: float, *, size: float = 1.0, origin=(0.0, 0.0, 0.0)) -> dict:
    """A closed cube seen from inside: six rectangles, all emitting and reflecting."""
    T = mi.ScalarTransform4f
    o = list(origin)
    faces = {
        "floor": T().translate(o).scale(size).translate([0, 0, -1]),
        "ceiling": T().translate(o).scale(size).translate([0, 0, 1]).rotate([1, 0, 0], 180),
        "xp": T().translate(o).scale(size).translate([1, 0, 0]).rotate([0, 1, 0], -90),
        "xm": T().translate(o).scale(size).translate([-1, 0, 0]).rotate([0, 1, 0], 90),
        "yp": T().translate(o).scale(size).translate([0, 1, 0]).rotate([1, 0, 0], 90),
        "ym": T().translate(o).scale(size).translate([0, -1, 0]).rotate([1, 0, 0], -90),
    }
    scene = {"type": "scene"}
    for name, t in faces.items():
        scene[name] = square(t, rho=rho, radiance=radiance, sid=name)
    return scene


@pytest.fixture(scope="session")
def cornell():
    return mirad.load_scene(SCENES / "cornell-box" / "scene.xml")


def area_mean(values: np.ndarray, area: np.ndarray) -> np.ndarray:
    return (values * area[:, None]).sum(0) / area.sum()


def run_cli(*args, cwd=None):
    """Run ``mirad ARGS`` in a subprocess (text output, 300 s limit)."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "mirad.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)
