"""Write the plant canopy: procedural leaves over a ground plane, lit by a sun and a sky.

Five plants, each a crown of flat two-sided leaves (a diamond of 2 triangles, 16 x 7 cm) at
random positions and orientations (fixed seed) inside an ellipsoid; a 10 x 10 m ground grid;
a ``directional`` sun and a ``constant`` sky. About 2,200 triangles.
Run from anywhere: ``python scenes/plant-canopy/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import diamond_leaves, diffuse, grid, ply_shape, sensor, write_ply  # noqa: E402

LEAVES_PER_PLANT = 210
PLANTS = [(0.0, 0.0, 1.3), (1.4, 0.6, 1.0), (-1.2, 0.9, 1.1), (0.5, -1.4, 0.9), (-0.9, -1.1, 1.2)]
LEAF_LENGTH, LEAF_WIDTH = 0.16, 0.07


def leaves(rng, cx, cy, height):
    n = LEAVES_PER_PLANT
    # centres uniform in an ellipsoid crown (radius 0.45 m, half-height 0.35 m) around (cx, cy, height)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.random(n) ** (1 / 3)
    centre = np.array([cx, cy, height]) + d * r[:, None] * np.array([0.45, 0.45, 0.35])
    # leaf frame: normal mostly upward (random inclination), random azimuth of the midrib
    v, first, second = diamond_leaves(rng, centre, LEAF_LENGTH, LEAF_WIDTH)
    return v, np.concatenate([first, second])


def main() -> None:
    rng = np.random.default_rng(7)
    body = (diffuse("leaf", (0.08, 0.35, 0.06), twosided=True) + diffuse("soil", (0.25, 0.2, 0.15)) + "\n")
    body += sensor((3.2, -3.4, 2.3), (0.0, 0.0, 0.8), fov=55, width=256, height=192) + "\n"
    body += ('    <emitter type="directional" id="sun">\n        <vector name="direction" value="-0.35, 0.3, -0.89"/>\n'
             '        <rgb name="irradiance" value="5.0, 4.7, 4.2"/>\n    </emitter>\n'
             '    <emitter type="constant" id="sky">\n        <rgb name="radiance" value="0.25, 0.32, 0.45"/>\n'
             '    </emitter>\n\n')
    total = size = 0
    ground = grid((-5, -5, 0), (10, 0, 0), (0, 10, 0), 10, 10)
    size += write_ply(HERE / "ground.ply", ground)
    total += len(ground[1])
    body += ply_shape("ground", "ground.ply", "soil")
    for k, (x, y, h) in enumerate(PLANTS, 1):
        mesh = leaves(rng, x, y, h)
        size += write_ply(HERE / f"plant-{k}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(f"plant-{k}", f"plant-{k}.ply", "leaf")
    text = (f'<scene version="3.0.0">\n    <!-- Plant canopy, written by make.py: {total} triangles. -->\n'
            f'    <integrator type="path"/>\n\n{body}</scene>\n')
    (HERE / "scene.xml").write_text(text)
    print(f"wrote {total} triangles, {size / 1024:.0f} KiB of PLY")


if __name__ == "__main__":
    main()
