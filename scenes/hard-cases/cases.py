"""Numerical hard cases of THEORY.md §8 as Mitsuba scene dicts (shared by tests and the benchmark).

Each builder writes its meshes as PLY files into ``folder`` and returns a Mitsuba scene dict whose
shapes all carry ids. Rooms are closed, seen from inside, metres; ``xform`` (a (4, 4) matrix applied
to every vertex) gives the scaled or moved copies of the invariance tests. Geometry is numpy only and
deterministic. Usage::

    from cases import corner_room
    scene = mirad.load_scene(corner_room(tmp_path))
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "_tools"))
from meshgen import grid, merge, rotation, write_ply  # noqa: E402

#: Radiance of the 0.5 x 0.5 m ceiling light of a 2 m room (W/m^2/sr); tiny lights keep its power.
CEILING_RADIANCE = 10.0


def part(mesh, rho, radiance=None, twosided=False):
    return {"mesh": mesh, "rho": rho, "radiance": radiance, "twosided": twosided}


def to_dict(folder, parts: dict, xform=None) -> dict:
    """Write every part as ``folder/<id>.ply`` (vertices through ``xform``) and return the scene dict."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    scene = {"type": "scene"}
    for sid, p in parts.items():
        v, f = p["mesh"]
        if xform is not None:
            v = v @ xform[:3, :3].T + xform[:3, 3]
        write_ply(folder / f"{sid}.ply", (v, f))
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": p["rho"]}}
        if p["twosided"]:
            bsdf = {"type": "twosided", "material": bsdf}
        shape = {"type": "ply", "id": sid, "filename": str(folder / f"{sid}.ply"), "face_normals": True,
                 "bsdf": bsdf}
        if p["radiance"] is not None:
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": p["radiance"]}}
        scene[sid] = shape
    return scene


def room_parts(size=2.0, cells=4, rho=0.6, light_half=0.25, radiance=CEILING_RADIANCE, skip=()):
    """A closed size^3 room (inward normals, each face cells x cells) and a square ceiling light of
    half-width ``light_half`` centred under the ceiling, facing down."""
    s, n = size, cells
    faces = {
        "floor": grid((0, 0, 0), (s, 0, 0), (0, s, 0), n, n),
        "ceiling": grid((0, 0, s), (0, s, 0), (s, 0, 0), n, n),
        "wall-x0": grid((0, 0, 0), (0, s, 0), (0, 0, s), n, n),
        "wall-x1": grid((s, 0, 0), (0, 0, s), (0, s, 0), n, n),
        "wall-y0": grid((0, 0, 0), (0, 0, s), (s, 0, 0), n, n),
        "wall-y1": grid((0, s, 0), (s, 0, 0), (0, 0, s), n, n),
    }
    parts = {sid: part(m, rho) for sid, m in faces.items() if sid not in skip}
    c, h = s / 2, light_half
    z = s * (1 - 1e-3)
    parts["light"] = part(grid((c - h, c - h, z), (0, 2 * h, 0), (2 * h, 0, 0), 1, 1), 0.0, radiance)
    return parts


def corner_room(folder, *, xform=None, cells=4):
    """Room with a plate hinged on the floor at 10 degrees (an acute wedge) beside the 90 degree
    corners and shared edges of the gridded walls. The plate (two-sided) and the floor are meshed
    finely near the hinge line x = 0.5."""
    parts = room_parts(cells=cells)
    # floor: finer strips near the hinge (x in [0.25, 1.0]) so per-triangle errors near the edge are seen
    xs = np.array([0.0, 0.25, 0.4, 0.5, 0.6, 0.75, 1.0, 1.5, 2.0])
    floor = merge([grid((a, 0, 0), (b - a, 0, 0), (0, 2.0, 0), 1, 4) for a, b in zip(xs[:-1], xs[1:])])
    parts["floor"] = part(floor, 0.6)
    # plate: from the hinge (x = 0.5) rising at 10 degrees towards +x, 1 m long, y in [0.5, 1.5]
    plate = grid((0, 0, 0), (0, 1.0, 0), (1.0, 0, 0), 4, 4)     # normal -z (faces down into the wedge)
    v = plate[0] @ rotation((0, 1, 0), -10).T + np.array([0.5, 0.5, 0.0])
    parts["plate"] = part((v, plate[1]), 0.7, twosided=True)
    return to_dict(folder, parts, xform)


def sliver_room(folder, *, aspect=1000.0):
    """Room whose floor has a strip of 1000:1 triangles under the light (2 m long, 2 mm wide)."""
    parts = room_parts()
    w = 2.0 / aspect
    xs = [0.0, 1.0 - w, 1.0, 1.0 + w, 2.0]
    floor = merge([grid((a, 0, 0), (b - a, 0, 0), (0, 2.0, 0), 1, 1) for a, b in zip(xs[:-1], xs[1:])])
    parts["floor"] = part(floor, 0.6)
    return to_dict(folder, parts)


def tiny_light_room(folder, *, fraction=1e-6):
    """Room lit by a square light of area ``fraction`` x the room's surface area, emitting the same
    power as the 0.5 x 0.5 m ceiling light of ``room_parts``."""
    area = 6 * 2.0 ** 2 * fraction
    half = np.sqrt(area) / 2
    radiance = CEILING_RADIANCE * (0.5 ** 2) / area
    return to_dict(folder, room_parts(light_half=half, radiance=radiance))


def pierced_room(folder):
    """Room split at x = 1 by a two-sided wall from 0.3 m below the floor to 0.1 m above the ceiling
    (it pierces both), lit on the x < 1 side only: the x > 1 side is closed and dark. Floor cells
    straddle the wall."""
    parts = room_parts(cells=5)
    parts["light"]["mesh"] = grid((0.3, 0.75, 1.998), (0, 0.5, 0), (0.5, 0, 0), 1, 1)
    parts["wall"] = part(grid((1.0, 0, -0.3), (0, 0, 2.4), (0, 2.0, 0), 5, 4), 0.6, twosided=True)
    return to_dict(folder, parts)


def sheet_room(folder, *, xform=None, flip=False):
    """A leaf: a two-sided sheet (0.8 x 0.8 m at z = 0.8, front facing up; ``flip``: down) in the lit room."""
    parts = room_parts()
    v, f = grid((0.6, 0.6, 0.8), (0.8, 0, 0), (0, 0.8, 0), 2, 2)
    parts["sheet"] = part((v, f[:, ::-1] if flip else f), 0.5, twosided=True)
    return to_dict(folder, parts, xform)


def many_lights_room(folder, *, count=1000, size=2.0):
    """Room whose black ceiling carries ``count`` separate 1 cm square area lights (one shape each), each
    of radiance 1 (so the emitted power is count * pi * 1e-4 W). The ceiling is black so that no light
    reaches the lamps' black backs 2 mm below it: every watt is absorbed by a front side, where
    ``(1 - rho) H`` counts it (an energy balance with a closed form)."""
    parts = room_parts(skip=())
    del parts["light"]
    parts["ceiling"]["rho"] = 0.0
    side = int(np.ceil(np.sqrt(count)))
    k = np.arange(count)
    centres = np.stack([(k % side + 0.5) / side * size, (k // side + 0.5) / side * size], 1)
    h = 0.005
    for i, (x, y) in enumerate(centres):
        parts[f"lamp-{i:04d}"] = part(grid((x - h, y - h, size * (1 - 1e-3)), (0, 2 * h, 0), (2 * h, 0, 0), 1, 1),
                                       0.0, 1.0)
    return to_dict(folder, parts)
