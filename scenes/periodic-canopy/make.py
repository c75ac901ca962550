"""Write a periodic canopy pattern: a plot of plants whose ground is exactly the pattern box.

``write_canopy(folder, ...)`` writes ``scene.xml`` and its PLY meshes: a soil ``ground`` grid
covering the box [-half, half]^2 (z up), the ``leaves`` of ``plants`` crowns (flat diamond leaves,
2 triangles each, translucent ``leaf`` BSDF with its own underside reflectance) kept inside the box,
a sun and a sky (``constant`` or the CIE overcast ``envmap`` of ``mirad.sky``). With ``tiles`` =
n (odd) it also writes ``ground-tiles`` and ``leaves-tiles``: the n x n - 1 copies of the pattern
around it, so that the middle tile of the large field is the pattern itself (the brute-force
check of the periodic solve, ``tests/test_periodic.py``, ``validation/bench_periodic.py``).
Solve the pattern with ``periodic="-half,-half,half,half"``.

Run ``python scenes/periodic-canopy/make.py`` to write the default pattern here (4 x 4 m, 5 plants).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "_tools"))

from meshgen import diamond_leaves, grid, write_ply  # noqa: E402

LEAF = """    <bsdf type="twosided" id="leaf">
        <boolean name="allow_transmission" value="true"/>
        <bsdf type="leaf">
            <rgb name="reflectance" value="0.08, 0.35, 0.06"/>
            <rgb name="transmittance" value="0.05, 0.25, 0.04"/>
        </bsdf>
        <bsdf type="leaf">
            <rgb name="reflectance" value="0.12, 0.40, 0.10"/>
            <rgb name="transmittance" value="0.05, 0.25, 0.04"/>
        </bsdf>
    </bsdf>
    <bsdf type="diffuse" id="soil"><rgb name="reflectance" value="0.25, 0.2, 0.15"/></bsdf>
"""
SUN = """    <emitter type="directional" id="sun">
        <vector name="direction" value="-0.35, 0.3, -0.89"/>
        <rgb name="irradiance" value="5.0, 4.7, 4.2"/>
    </emitter>
"""
CONSTANT_SKY = """    <emitter type="constant" id="sky">
        <rgb name="radiance" value="0.25, 0.32, 0.45"/>
    </emitter>
"""


def pattern(*, half: float, plants: int, leaves_per_plant: int, seed: int, leaf_length: float = 0.16,
            leaf_width: float = 0.07, crown: float = 0.45):
    """(ground mesh, leaves mesh) of one pattern: crowns at random positions inside the box (kept
    a crown radius plus half a leaf from its sides), heights 0.6-1.3 m."""
    rng = np.random.default_rng(seed)
    margin = crown + leaf_length
    ground = grid((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), max(1, int(2 * half / 0.5)),
                  max(1, int(2 * half / 0.5)))
    verts, faces = [], []
    for _ in range(plants):
        cx, cy = rng.uniform(-half + margin, half - margin, 2)
        h = rng.uniform(0.6, 1.3)
        d = rng.normal(size=(leaves_per_plant, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = rng.random(leaves_per_plant) ** (1 / 3)
        centre = np.array([cx, cy, h]) + d * r[:, None] * np.array([crown, crown, 0.35])
        v, first, second = diamond_leaves(rng, centre, leaf_length, leaf_width)
        faces.append(np.concatenate([first, second]) + sum(len(x) for x in verts))
        verts.append(v)
    return ground, (np.concatenate(verts), np.concatenate(faces))


def _tile(mesh, half: float, tiles: int):
    v, f = mesh
    vs, fs = [], []
    r = tiles // 2
    for i in range(-r, r + 1):
        for j in range(-r, r + 1):
            if (i, j) == (0, 0):
                continue
            fs.append(f + len(vs) * len(v))
            vs.append(v + np.array([2 * half * i, 2 * half * j, 0.0]))
    return np.concatenate(vs), np.concatenate(fs)


def _shape(sid: str, bsdf: str) -> str:
    return (f'    <shape type="ply" id="{sid}">\n        <string name="filename" value="{sid}.ply"/>\n'
            f'        <boolean name="face_normals" value="true"/>\n        <ref id="{bsdf}"/>\n    </shape>\n')


def write_canopy(folder, *, half: float = 2.0, plants: int = 5, leaves_per_plant: int = 120, seed: int = 7,
                 tiles: int = 1, sky: str = "constant", sky_irradiance: float = 100.0) -> Path:
    """Write the pattern (and with ``tiles`` > 1 its copies) into ``folder``; returns scene.xml's path.

    sky : "constant" (a constant sky of radiance (0.25, 0.32, 0.45)) or "overcast" (the CIE
    standard overcast sky of horizontal irradiance ``sky_irradiance`` W/m^2, written as
    ``sky.exr`` beside the scene), either with the sun of scenes/plant-canopy.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if tiles < 1 or tiles % 2 == 0:
        raise ValueError(f"tiles={tiles}: give an odd number >= 1 (the pattern sits in the middle)")
    ground, leaves = pattern(half=half, plants=plants, leaves_per_plant=leaves_per_plant, seed=seed)
    body = LEAF + SUN
    if sky == "constant":
        body += CONSTANT_SKY
    elif sky == "overcast":
        from mirad import sky as skies

        snippet = skies.write_sky({"sky": skies.overcast_sky(sky_irradiance, up="+z")}, folder / "sky.exr")
        body += "    " + snippet.replace(f'value="{folder / "sky.exr"}"', 'value="sky.exr"').replace("\n", "\n    ")
        body = body.rstrip(" ") + "\n"
    else:
        raise ValueError(f"sky={sky!r}: choose 'constant' or 'overcast'")
    write_ply(folder / "ground.ply", ground)
    write_ply(folder / "leaves.ply", leaves)
    body += _shape("ground", "soil") + _shape("leaves", "leaf")
    if tiles > 1:
        write_ply(folder / "ground-tiles.ply", _tile(ground, half, tiles))
        write_ply(folder / "leaves-tiles.ply", _tile(leaves, half, tiles))
        body += _shape("ground-tiles", "soil") + _shape("leaves-tiles", "leaf")
    path = folder / "scene.xml"
    path.write_text(f'<scene version="3.0.0">\n    <!-- Periodic canopy pattern (box [-{half}, {half}]^2 m, '
                    f'{tiles} x {tiles} tiles), written by scenes/periodic-canopy/make.py -->\n'
                    f'    <integrator type="path"/>\n\n{body}</scene>\n')
    return path


if __name__ == "__main__":
    print(write_canopy(HERE))
