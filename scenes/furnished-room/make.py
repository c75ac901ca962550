"""Write the furnished room: tables, chairs and shelves as meshes, a window and a ceiling light.

A 6 x 4 x 2.8 m room (z up) with walls, floor and ceiling as grids of ~0.4 m cells, two tables,
eight chairs and two shelves built from boxes (no bottom faces where they stand on the floor),
a window area light on the wall x = 0 and a square ceiling light. About 2,000 triangles.
Run from anywhere: ``python scenes/furnished-room/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import (area_emitter, box, cells, diffuse, grid, merge, ply_shape, sensor, transform,  # noqa: E402
                     write_ply)

L, W, H = 6.0, 4.0, 2.8
CELL = 0.4
#: Set-back (m) of a part standing on or between others, so that no edge is shared by > 2 faces.
INSET = 0.01


def room():
    """Inward-facing floor, ceiling and four walls."""
    g = lambda c, u, v: grid(c, u, v, cells(sum(abs(x) for x in u), CELL), cells(sum(abs(x) for x in v), CELL))  # noqa: E731
    return {
        "floor": (g((0, 0, 0), (L, 0, 0), (0, W, 0)), "floor-wood"),
        "ceiling": (g((0, 0, H), (0, W, 0), (L, 0, 0)), "ceiling-white"),
        "wall-window": (g((0, 0, 0), (0, W, 0), (0, 0, H)), "wall-white"),        # x = 0, faces +x
        "wall-far": (g((L, 0, 0), (0, 0, H), (0, W, 0)), "wall-white"),           # x = L, faces -x
        "wall-left": (g((0, 0, 0), (0, 0, H), (L, 0, 0)), "wall-white"),          # y = 0, faces +y
        "wall-right": (g((0, W, 0), (L, 0, 0), (0, 0, H)), "wall-white"),         # y = W, faces -y
    }


def table(x, y, *, length=1.6, depth=0.9, height=0.74, top=0.05, leg=0.06):
    parts = [box((x - length / 2, y - depth / 2, height - top), (x + length / 2, y + depth / 2, height))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = x + sx * (length / 2 - 0.1), y + sy * (depth / 2 - 0.1)
            parts.append(box((cx - leg / 2, cy - leg / 2, 0), (cx + leg / 2, cy + leg / 2, height - top),
                             skip=("-z", "+z")))
    return merge(parts)


def chair(x, y, angle, *, seat=0.45, height=0.45, leg=0.04):
    # the back stands on the seat 1 cm in from its sides and rear, without a bottom face: a back
    # flush with the seat's edges would put four faces on one edge (non-manifold)
    parts = [box((-seat / 2, -seat / 2, height - 0.04), (seat / 2, seat / 2, height)),
             box((-seat / 2 + INSET, seat / 2 - 0.04 - INSET, height),
                 (seat / 2 - INSET, seat / 2 - INSET, height + 0.45), skip=("-z",))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (seat / 2 - 0.03), sy * (seat / 2 - 0.03)
            parts.append(box((cx - leg / 2, cy - leg / 2, 0), (cx + leg / 2, cy + leg / 2, height - 0.04),
                             skip=("-z", "+z")))
    return transform(merge(parts), rotate=[((0, 0, 1), angle)], translate=(x, y, 0))


def shelf(x, y, angle, *, width=1.0, depth=0.35, height=1.9, boards=5, t=0.025):
    # the back sits between the sides 1 cm in from their rear edges, without the faces that touch
    # them: flush with the sides' rear it would put three or four faces on one edge (non-manifold)
    back = depth - INSET
    parts = [box((-width / 2, 0, 0), (-width / 2 + t, depth, height), skip=("-z",)),
             box((width / 2 - t, 0, 0), (width / 2, depth, height), skip=("-z",)),
             box((-width / 2 + t, back - t, 0), (width / 2 - t, back, height), skip=("-z", "-x", "+x"))]
    for k in range(boards):
        z = 0.05 + k * (height - 0.1) / (boards - 1)
        parts.append(box((-width / 2 + t, 0, z), (width / 2 - t, back - t, z + t)))
    return transform(merge(parts), rotate=[((0, 0, 1), angle)], translate=(x, y, 0))


def main() -> None:
    body = (diffuse("floor-wood", (0.45, 0.3, 0.18)) + diffuse("ceiling-white", (0.8, 0.8, 0.8))
            + diffuse("wall-white", (0.7, 0.68, 0.62)) + diffuse("wood", (0.5, 0.35, 0.2))
            + diffuse("fabric", (0.55, 0.12, 0.1)) + diffuse("paint", (0.3, 0.45, 0.6)) + "\n")
    body += sensor((5.6, 3.6, 1.9), (1.5, 1.0, 0.6), fov=70, width=256, height=192) + "\n"
    meshes = {sid: value for sid, value in room().items()}
    meshes["table-1"] = (table(2.2, 1.4), "wood")
    meshes["table-2"] = (table(4.2, 2.7, length=1.2, depth=0.8), "wood")
    chairs = [(2.2 - 0.45, 0.7, 0), (2.2 + 0.45, 0.7, 0), (2.2 - 0.45, 2.1, 180), (2.2 + 0.45, 2.1, 180),
              (4.2 - 0.3, 2.05, 0), (4.2 + 0.3, 3.35, 180), (4.95, 2.7, 90), (3.45, 2.7, -90)]
    for k, (x, y, a) in enumerate(chairs, 1):
        meshes[f"chair-{k}"] = (chair(x, y, a), "fabric")
    meshes["shelf-1"] = (shelf(5.2, 0.02, 0), "paint")
    meshes["shelf-2"] = (shelf(0.5, 3.98, 180, width=0.8), "paint")
    total = size = 0
    for sid, (mesh, material) in meshes.items():
        size += write_ply(HERE / f"{sid}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(sid, f"{sid}.ply", material)
    # window (sky light) 1 cm inside the wall x = 0, facing +x; ceiling light facing down
    body += ('    <shape type="rectangle" id="window">\n        <transform name="to_world">\n'
             '            <scale value="0.8, 0.6, 1"/>\n            <rotate y="1" angle="90"/>\n'
             '            <translate value="0.01, 1.6, 1.6"/>\n        </transform>\n'
             '        <bsdf type="diffuse"><rgb name="reflectance" value="0.1"/></bsdf>\n'
             + area_emitter((4.0, 4.6, 5.5)) + "    </shape>\n")
    body += ('    <shape type="rectangle" id="ceiling-light">\n        <transform name="to_world">\n'
             '            <scale value="0.3, 0.3, 1"/>\n            <rotate x="1" angle="180"/>\n'
             f'            <translate value="3.0, 2.0, {H - 0.01:g}"/>\n        </transform>\n'
             '        <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf>\n'
             + area_emitter((30.0, 26.0, 20.0)) + "    </shape>\n")
    text = (f'<scene version="3.0.0">\n    <!-- Furnished room, written by make.py: {total + 4} triangles. -->\n'
            f'    <integrator type="path"/>\n\n{body}</scene>\n')
    (HERE / "scene.xml").write_text(text)
    print(f"wrote {total + 4} triangles, {size / 1024:.0f} KiB of PLY")


if __name__ == "__main__":
    main()
