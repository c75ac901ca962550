"""Write the wall-that-pierces-the-floor scene (light leaks under walls).

A closed 4 x 4 x 2.5 m room lit by a ceiling light on its x < 2 side. A two-sided partition wall
at x = 2 spans the room's width and runs from 0.4 m *below* the floor up to 1.8 m, so it crosses
the floor plane. The floor grid's cells straddle the wall (x = 2 falls in the middle of a cell) and
the wall's cells straddle the floor (z = 0 in the middle of a cell): an element that crosses the
wall and gathers light from both sides leaks light to the dark side.
Run from anywhere: ``python scenes/wall-pierce/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import area_emitter, diffuse, grid, merge, ply_shape, sensor, write_ply  # noqa: E402

L, W, H = 4.0, 4.0, 2.5


def main() -> None:
    meshes = {
        "floor": (grid((0, 0, 0), (L, 0, 0), (0, W, 0), 9, 8), "white"),     # x = 2 mid-cell
        "ceiling": (grid((0, 0, H), (0, W, 0), (L, 0, 0), 8, 8), "white"),
        "walls": (merge([grid((0, 0, 0), (0, W, 0), (0, 0, H), 8, 5), grid((L, 0, 0), (0, 0, H), (0, W, 0), 5, 8),
                         grid((0, 0, 0), (0, 0, H), (L, 0, 0), 5, 8), grid((0, W, 0), (L, 0, 0), (0, 0, H), 8, 5)]),
                  "white"),
        # faces -x; two-sided BSDF: both sides reflect. z from -0.4 to 1.8 in 5 cells: z = 0 mid-cell
        "partition": (grid((2.0, 0, -0.4), (0, 0, 2.2), (0, W, 0), 5, 8), "partition-paint"),
    }
    body = (diffuse("white", (0.7, 0.7, 0.7)) + diffuse("partition-paint", (0.6, 0.5, 0.4), twosided=True) + "\n")
    body += sensor((3.9, 0.15, 2.4), (0.8, 3.0, 0.0), fov=80, width=256, height=192) + "\n"
    total = size = 0
    for sid, (mesh, material) in meshes.items():
        size += write_ply(HERE / f"{sid}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(sid, f"{sid}.ply", material)
    body += ('    <shape type="rectangle" id="light">\n        <transform name="to_world">\n'
             '            <scale value="0.3, 0.3, 1"/>\n            <rotate x="1" angle="180"/>\n'
             f'            <translate value="1.0, 2.0, {H - 0.01:g}"/>\n        </transform>\n'
             '        <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf>\n'
             + area_emitter((20.0, 20.0, 20.0)) + "    </shape>\n")
    text = (f'<scene version="3.0.0">\n    <!-- Wall piercing the floor, written by make.py: {total + 2} '
            f'triangles. -->\n    <integrator type="path"/>\n\n{body}</scene>\n')
    (HERE / "scene.xml").write_text(text)
    print(f"wrote {total + 2} triangles, {size / 1024:.0f} KiB of PLY")


if __name__ == "__main__":
    main()
