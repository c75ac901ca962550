"""Write the shadow-case scenes (soft shadows by convolution, mirad/shadows.py).

* parallel.xml   source, square occluder and receiver in parallel planes (the exact case)
* tilted.xml     the same with the occluder tilted 35 degrees (a depth spread)
* table.xml      a table (top and four 3 cm legs) under a ceiling light, on a floor
* leaves.xml     a layer of 400 small tilted leaves over the ground under an area source

Receivers are single large rectangles (2 triangles each), so a solver either subdivides
them or gives their links shadow textures. Deterministic (fixed seed).
Run from anywhere: ``python scenes/shadow-cases/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import box, merge, ply_shape, sensor, write_ply  # noqa: E402

LEAVES = 400
LEAF_LENGTH, LEAF_WIDTH = 0.12, 0.06


def rect(sid, *, scale, translate, rotate="", rho=0.5, radiance=None, twosided=False):
    sx, sy = scale
    emitter = (f'        <emitter type="area"><rgb name="radiance" value="{radiance:g}"/></emitter>\n'
               if radiance is not None else "")
    bsdf = f'<bsdf type="diffuse"><rgb name="reflectance" value="{rho:g}"/></bsdf>'
    if twosided:
        bsdf = f'<bsdf type="twosided">{bsdf}</bsdf>'
    tx = ", ".join(f"{c:g}" for c in translate)
    return (f'    <shape type="rectangle" id="{sid}">\n        <transform name="to_world">\n'
            f'            <scale x="{sx:g}" y="{sy:g}"/>\n{rotate}'
            f'            <translate value="{tx}"/>\n        </transform>\n        {bsdf}\n{emitter}    </shape>\n')


DOWN = '            <rotate x="1" angle="180"/>\n'


def write(name, body, comment):
    text = f'<scene version="3.0.0">\n    <!-- {comment} -->\n    <integrator type="path"/>\n\n{body}</scene>\n'
    (HERE / name).write_text(text)


def leaf_layer(rng):
    """Diamond leaves (2 triangles) centred in [-1, 1]^2 x [1.0, 1.4], tilted up to 30 degrees."""
    n = LEAVES
    centre = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(1.0, 1.4, n)])
    yaw = rng.uniform(0, 2 * np.pi, n)
    tilt = np.radians(rng.uniform(0, 30, n))
    axis = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros(n)])
    side = np.column_stack([-np.sin(yaw) * np.cos(tilt), np.cos(yaw) * np.cos(tilt), np.sin(tilt)])
    a, b = centre - axis * LEAF_LENGTH / 2, centre + axis * LEAF_LENGTH / 2
    c, d = centre + side * LEAF_WIDTH / 2, centre - side * LEAF_WIDTH / 2
    verts = np.stack([a, c, b, d], 1).reshape(-1, 3)
    base = 4 * np.arange(n)[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return verts, faces


def main():
    light = rect("light", scale=(0.2, 0.2), translate=(0, 0, 2), rotate=DOWN, rho=0.0, radiance=10.0)
    floor = rect("floor", scale=(1.5, 1.5), translate=(0, 0, 0))
    cam = sensor((2.5, -2.5, 2.2), (0, 0, 0.3), fov=50)
    write("parallel.xml", cam + light + floor
          + rect("occluder", scale=(0.3, 0.3), translate=(0, 0, 1.2), twosided=True),
          "parallel planes: 0.4 m light at z=2, 0.6 m occluder at z=1.2, 3 m floor at z=0; "
          "penumbra 0.6 m, umbra 0.9 m wide")
    write("tilted.xml", cam + light + floor
          + rect("occluder", scale=(0.3, 0.3), translate=(0, 0, 1.2), twosided=True,
                 rotate='            <rotate y="1" angle="35"/>\n'),
          "the parallel case with the occluder tilted 35 degrees about y")

    top = box((-0.6, -0.4, 0.72), (0.6, 0.4, 0.76))
    legs = [box((x - 0.015, y - 0.015, 0.0), (x + 0.015, y + 0.015, 0.72), skip=("-z",))
            for x in (-0.55, 0.55) for y in (-0.35, 0.35)]
    write_ply(HERE / "table.ply", merge([top, *legs]))
    write("table.xml", sensor((3.0, -3.0, 2.2), (0, 0, 0.4), fov=50)
          + rect("light", scale=(0.3, 0.3), translate=(0, 0, 2.4), rotate=DOWN, rho=0.0, radiance=10.0)
          + rect("floor", scale=(2.0, 2.0), translate=(0, 0, 0))
          + ply_shape("table", "table.ply", '<bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>'),
          "a 1.2 x 0.8 m table with 3 cm legs under a 0.6 m ceiling light at z=2.4, on a 4 m floor")

    rng = np.random.default_rng(10)
    write_ply(HERE / "leaves.ply", leaf_layer(rng))
    write("leaves.xml", sensor((3.5, -3.5, 3.0), (0, 0, 0.5), fov=50)
          + rect("light", scale=(0.5, 0.5), translate=(0, 0, 3.0), rotate=DOWN, rho=0.0, radiance=10.0)
          + rect("ground", scale=(2.0, 2.0), translate=(0, 0, 0))
          + ply_shape("leaves", "leaves.ply",
                      '<bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.4"/></bsdf></bsdf>'),
          f"{LEAVES} tilted 12 x 6 cm leaves at z=1.0-1.4 over a 4 m ground, 1 m area light at z=3")


if __name__ == "__main__":
    main()
