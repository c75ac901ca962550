"""Procedural plant canopy at any size: the scale benchmark's scenes (1k, 10k, 100k leaf triangles).

A field of ``plants`` plants on a jittered square grid (2 m spacing), each a crown of
flat two-sided leaves (a diamond of 2 triangles, 16 x 7 cm, mostly facing up) inside an
ellipsoid, over a ground grid, lit by a ``directional`` sun and a ``constant`` sky, as in
scenes/plant-canopy. One PLY per plant (shape ids ``plant-1`` ...); leaf j of a plant is
triangles 2j and 2j+1 of that shape, so the per-triangle table of ``mirad export -o t.csv``
(``absorbed_*`` columns, W) gives the power absorbed per leaf by summing triangle pairs.

Files are generated on demand (100k triangles is ~2.5 MB of PLY); the default output folder
``scenes/canopy-scale/generated/`` is git-ignored.

    python scenes/canopy-scale/make.py --triangles 10000              # -> generated/canopy-10000/
    python scenes/canopy-scale/make.py --plants 4 --leaves 125 --seed 3 --out out/canopy

From Python: ``make_canopy(out_dir, plants=..., leaves=..., seed=...)`` returns the XML path.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import diamond_leaves, diffuse, grid, ply_shape, sensor, write_ply  # noqa: E402

LEAF_LENGTH, LEAF_WIDTH = 0.16, 0.07
SPACING = 2.0          # m between plants
CROWN = (0.45, 0.45, 0.35)


def plan(triangles: int) -> tuple[int, int]:
    """(plants, leaves per plant) for about ``triangles`` leaf triangles: plants grow like
    sqrt(leaves), so crowns get denser as well as the field larger."""
    leaves = max(1, int(round(triangles / 2)))
    plants = max(1, int(round(math.sqrt(leaves / 60))))
    return plants, max(1, int(round(leaves / plants)))


def leaves(rng, n: int, centre_xyz) -> tuple[np.ndarray, np.ndarray]:
    """(4n, 3) vertices and (2n, 3) faces of n diamond leaves in an ellipsoid crown."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.random(n) ** (1 / 3)
    # crowns grow with their leaf count (about the leaf density of scenes/plant-canopy)
    crown = np.array(CROWN) * max(1.0, n / 210) ** (1 / 3)
    centre = np.asarray(centre_xyz) + d * r[:, None] * crown
    v, first, second = diamond_leaves(rng, centre, LEAF_LENGTH, LEAF_WIDTH)
    f = np.stack([first, second], 1).reshape(-1, 3)    # leaf j: faces 2j, 2j+1
    return v, f


def make_canopy(out_dir, *, plants: int, leaves_per_plant: int, seed: int = 0) -> Path:
    """Write scene.xml, ground.ply and plant-K.ply into out_dir; returns the XML path."""
    if plants < 1 or leaves_per_plant < 1:
        raise ValueError("plants and leaves per plant must be >= 1")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    side = int(math.ceil(math.sqrt(plants)))
    half = 0.5 * side * SPACING + 1.0
    body = diffuse("leaf", (0.08, 0.35, 0.06), twosided=True) + diffuse("soil", (0.25, 0.2, 0.15)) + "\n"
    body += sensor((half * 0.9, -half * 1.1, 1.2 + half * 0.6), (0.0, 0.0, 0.8), fov=55, width=256,
                   height=192) + "\n"
    body += ('    <emitter type="directional" id="sun">\n        <vector name="direction" value="-0.35, 0.3, -0.89"/>\n'
             '        <rgb name="irradiance" value="5.0, 4.7, 4.2"/>\n    </emitter>\n'
             '    <emitter type="constant" id="sky">\n        <rgb name="radiance" value="0.25, 0.32, 0.45"/>\n'
             '    </emitter>\n\n')
    cells = max(4, 2 * side)
    ground = grid((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), cells, cells)
    write_ply(out / "ground.ply", ground)
    body += ply_shape("ground", "ground.ply", "soil")
    total = 0
    for k in range(plants):
        gx, gy = k % side, k // side
        x = (gx - 0.5 * (side - 1)) * SPACING + rng.uniform(-0.2, 0.2)
        y = (gy - 0.5 * (side - 1)) * SPACING + rng.uniform(-0.2, 0.2)
        h = rng.uniform(0.9, 1.3) * max(1.0, leaves_per_plant / 210) ** (1 / 3)
        mesh = leaves(rng, leaves_per_plant, (x, y, h))
        write_ply(out / f"plant-{k + 1}.ply", mesh)
        total += len(mesh[1])
        body += ply_shape(f"plant-{k + 1}", f"plant-{k + 1}.ply", "leaf")
    text = (f'<scene version="3.0.0">\n    <!-- Canopy written by scenes/canopy-scale/make.py: {plants} plants x '
            f'{leaves_per_plant} leaves, seed {seed}: {total} leaf triangles + {len(ground[1])} ground. -->\n'
            f'    <integrator type="path"/>\n\n{body}</scene>\n')
    path = out / "scene.xml"
    path.write_text(text)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--triangles", type=int, default=None,
                        help="about this many leaf triangles (picks --plants and --leaves)")
    parser.add_argument("--plants", type=int, default=None, help="number of plants")
    parser.add_argument("--leaves", type=int, default=None, help="leaves (2 triangles each) per plant")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--out", default=None, help="output folder (default generated/canopy-<triangles>)")
    args = parser.parse_args(argv)
    plants, per = plan(args.triangles if args.triangles else 1000)
    plants = args.plants or plants
    per = args.leaves or per
    out = args.out or HERE / "generated" / f"canopy-{args.triangles or 2 * plants * per}"
    path = make_canopy(out, plants=plants, leaves_per_plant=per, seed=args.seed)
    print(f"wrote {path}: {plants} plants x {per} leaves = {2 * plants * per} leaf triangles")


if __name__ == "__main__":
    main()
