"""Write the finely tessellated Cornell box: every wall and box face a regular grid (~10k triangles).

Same geometry, materials, light and sensor as scenes/cornell-box (mitsuba.cornell_box()), except
that the walls and the two boxes are PLY grids and the boxes have no bottom face (it lies on the
floor and is never lit). Run from anywhere: ``python scenes/cornell-box-fine/make.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import cube, diffuse, ply_shape, rectangle, transform, write_ply  # noqa: E402

WALL_CELL = 2.0 / 24      # walls: 24 x 24 cells
BOX_CELL = 0.05           # box faces: 5 cm cells

WALLS = {  # id: (material, rotations, translation) of the unit rectangle, as in the coarse box
    "floor": ("white", [((1, 0, 0), -90)], (0, -1, 0)),
    "ceiling": ("white", [((1, 0, 0), 90)], (0, 1, 0)),
    "back": ("white", [], (0, 0, -1)),
    "green-wall": ("green", [((0, 1, 0), -90)], (1, 0, 0)),
    "red-wall": ("red", [((0, 1, 0), 90)], (-1, 0, 0)),
}
BOXES = {  # id: (scale, y rotation in degrees, translation)
    "small-box": ((0.3, 0.3, 0.3), -17, (0.335, -0.7, 0.38)),
    "large-box": ((0.3, 0.61, 0.3), 18.25, (-0.33, -0.4, -0.28)),
}

HEADER = """    <sensor type="perspective" id="sensor">
        <string name="fov_axis" value="smaller"/>
        <float name="near_clip" value="0.001"/>
        <float name="far_clip" value="100.0"/>
        <float name="fov" value="39.3077"/>
        <transform name="to_world">
            <lookat origin="0, 0, 3.9" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="64"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="256"/>
            <integer name="height" value="256"/>
            <rfilter type="box"/>
        </film>
    </sensor>

    <shape type="rectangle" id="light">
        <transform name="to_world">
            <scale value="0.23, 0.19, 0.19"/>
            <rotate x="1" angle="90"/>
            <translate value="0, 0.99, 0.01"/>
        </transform>
        <ref id="white"/>
        <emitter type="area">
            <rgb name="radiance" value="18.387, 13.9873, 6.75357"/>
        </emitter>
    </shape>
"""


def main() -> None:
    body = (diffuse("white", (0.885809, 0.698859, 0.666422)) + diffuse("green", (0.105421, 0.37798, 0.076425))
            + diffuse("red", (0.570068, 0.0430135, 0.0443706)) + "\n" + HEADER)
    total = size = 0
    for sid, (material, rot, trans) in WALLS.items():
        mesh = transform(rectangle(WALL_CELL), rotate=rot, translate=trans)
        size += write_ply(HERE / f"{sid}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(sid, f"{sid}.ply", material)
    for sid, (scale, angle, trans) in BOXES.items():
        # the cube's -y face is the bottom (it rests on the floor y = -1)
        mesh = transform(cube(BOX_CELL, scale=scale, skip=("-y",)), rotate=[((0, 1, 0), angle)],
                         translate=trans)
        size += write_ply(HERE / f"{sid}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(sid, f"{sid}.ply", "white")
    text = ('<scene version="3.0.0">\n    <!-- Finely tessellated Cornell box, written by make.py: '
            f'{total + 2} triangles. -->\n    <integrator type="path">\n        <integer name="max_depth" '
            f'value="8"/>\n    </integrator>\n\n{body}</scene>\n')
    (HERE / "scene.xml").write_text(text)
    print(f"wrote {total + 2} triangles, {size / 1024:.0f} KiB of PLY")


if __name__ == "__main__":
    main()
