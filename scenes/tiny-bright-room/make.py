"""Write the tiny-bright-source room: a 5 x 5 x 3 m room lit only by a 2 cm square lamp.

Walls, floor and ceiling are grids of ~0.5 m cells; a table stands in the middle; the lamp is
a 2 x 2 cm area emitter 10 cm under the ceiling, facing down, of radiance 2e4 (about 25 W).
Run from anywhere: ``python scenes/tiny-bright-room/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import area_emitter, box, cells, diffuse, grid, merge, ply_shape, sensor, write_ply  # noqa: E402

L, W, H = 5.0, 5.0, 3.0
CELL = 0.5


def main() -> None:
    g = lambda c, u, v: grid(c, u, v, cells(sum(abs(x) for x in u), CELL), cells(sum(abs(x) for x in v), CELL))  # noqa: E731
    meshes = {
        "floor": (g((0, 0, 0), (L, 0, 0), (0, W, 0)), "grey"),
        "ceiling": (g((0, 0, H), (0, W, 0), (L, 0, 0)), "white"),
        "walls": (merge([g((0, 0, 0), (0, W, 0), (0, 0, H)), g((L, 0, 0), (0, 0, H), (0, W, 0)),
                         g((0, 0, 0), (0, 0, H), (L, 0, 0)), g((0, W, 0), (L, 0, 0), (0, 0, H))]), "white"),
        "table": (merge([box((1.8, 1.8, 0.7), (3.2, 3.2, 0.76), cell=0.35),
                         box((1.85, 1.85, 0), (1.95, 1.95, 0.7), skip=("-z", "+z")),
                         box((3.05, 1.85, 0), (3.15, 1.95, 0.7), skip=("-z", "+z")),
                         box((1.85, 3.05, 0), (1.95, 3.15, 0.7), skip=("-z", "+z")),
                         box((3.05, 3.05, 0), (3.15, 3.15, 0.7), skip=("-z", "+z"))]), "wood"),
    }
    body = (diffuse("white", (0.75, 0.75, 0.75)) + diffuse("grey", (0.4, 0.4, 0.4))
            + diffuse("wood", (0.5, 0.35, 0.2)) + "\n")
    body += sensor((4.6, 0.4, 2.2), (1.5, 3.5, 0.8), fov=75, width=256, height=192) + "\n"
    total = size = 0
    for sid, (mesh, material) in meshes.items():
        size += write_ply(HERE / f"{sid}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(sid, f"{sid}.ply", material)
    body += ('    <shape type="rectangle" id="lamp">\n        <transform name="to_world">\n'
             '            <scale value="0.01, 0.01, 1"/>\n            <rotate x="1" angle="180"/>\n'
             f'            <translate value="2.0, 3.0, {H - 0.1:g}"/>\n        </transform>\n'
             '        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>\n'
             + area_emitter((2.0e4, 2.0e4, 2.0e4)) + "    </shape>\n")
    text = (f'<scene version="3.0.0">\n    <!-- Tiny bright source in a room, written by make.py: {total + 2} '
            f'triangles. -->\n    <integrator type="path"/>\n\n{body}</scene>\n')
    (HERE / "scene.xml").write_text(text)
    print(f"wrote {total + 2} triangles, {size / 1024:.0f} KiB of PLY")


if __name__ == "__main__":
    main()
