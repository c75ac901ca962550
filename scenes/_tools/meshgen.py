"""Small mesh generators shared by the scenes' make.py scripts (numpy only, deterministic output).

Meshes are (vertices (V, 3) float, faces (F, 3) int) pairs; the front side of a triangle is the
side its counter-clockwise winding faces (as in Mitsuba). ``write_ply`` writes binary little-endian
PLY files that Mitsuba's ``ply`` shape reads.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def rotation(axis, degrees: float) -> np.ndarray:
    """(3, 3) right-handed rotation about ``axis`` (Rodrigues), like Mitsuba's <rotate>."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = np.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * (k @ k)


def transform(mesh, *, scale=1.0, rotate=(), translate=(0.0, 0.0, 0.0)):
    """Scale, then rotate (a list of (axis, degrees) in order), then translate: Mitsuba's XML order."""
    v, f = mesh
    v = v * np.asarray(scale, dtype=np.float64)
    for axis, deg in rotate:
        v = v @ rotation(axis, deg).T
    return v + np.asarray(translate, dtype=np.float64), f


def grid(corner, edge_u, edge_v, nu: int, nv: int):
    """Parallelogram corner + s u + t v as an nu x nv grid of cells, 2 triangles each, normal u x v."""
    corner, edge_u, edge_v = (np.asarray(x, dtype=np.float64) for x in (corner, edge_u, edge_v))
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    v = corner + s.reshape(-1, 1) * edge_u + t.reshape(-1, 1) * edge_v
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a = (i * (nv + 1) + j).ravel()
    b, c, d = a + (nv + 1), a + (nv + 1) + 1, a + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


def cells(length: float, size: float) -> int:
    """Number of grid cells of about ``size`` along ``length`` (at least 1)."""
    return max(1, int(round(length / size)))


def cube(cell: float, *, scale=(1.0, 1.0, 1.0), skip=()):
    """Mitsuba's cube [-1, 1]^3 (outward normals) scaled by ``scale``, each face a grid of ~cell cells.

    ``skip`` names faces to leave out: "-x", "+x", "-y", "+y", "-z", "+z".
    """
    scale = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    parts = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        for sign in (+1, -1):
            if f"{'+' if sign > 0 else '-'}{'xyz'[axis]}" in skip:
                continue
            eb, ec = np.zeros(3), np.zeros(3)
            eb[b], ec[c] = 2 * scale[b], 2 * scale[c]
            corner = -scale.copy()
            corner[axis] = sign * scale[axis]
            nb, nc = cells(eb[b], cell), cells(ec[c], cell)
            parts.append(grid(corner, eb, ec, nb, nc) if sign > 0 else grid(corner, ec, eb, nc, nb))
    return merge(parts)


def box(lo, hi, *, cell: float = 1e9, skip=()):
    """Axis-aligned box between corners lo and hi, outward normals (see ``cube`` for skip)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return transform(cube(cell, scale=(hi - lo) / 2, skip=skip), translate=(hi + lo) / 2)


def rectangle(cell: float, *, scale=(1.0, 1.0)):
    """Mitsuba's rectangle [-1, 1]^2 in z = 0 (normal +z) scaled in x, y, as a grid."""
    sx, sy = scale
    return grid((-sx, -sy, 0), (2 * sx, 0, 0), (0, 2 * sy, 0), cells(2 * sx, cell), cells(2 * sy, cell))


def merge(meshes):
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def diamond_leaves(rng, centre: np.ndarray, length: float, width: float):
    """Flat diamond leaves (2 triangles each) at centres (n, 3), inclined 0-70 degrees from up at
    random azimuths (two draws of ``rng``): (4n, 3) vertices and the first and second triangle
    of every leaf as two (n, 3) face arrays."""
    n = len(centre)
    incl = np.radians(rng.uniform(0, 70, n))
    az = rng.uniform(0, 2 * np.pi, n)
    normal = np.stack([np.sin(incl) * np.cos(az), np.sin(incl) * np.sin(az), np.cos(incl)], 1)
    ref = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0, 0, 1]], [[1, 0, 0]])
    along = np.cross(normal, ref)
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    side = np.cross(normal, along)
    tip, base = centre + along * length / 2, centre - along * length / 2
    left, right = centre + side * width / 2, centre - side * width / 2
    v = np.stack([base, right, tip, left], 1).reshape(-1, 3)
    k = np.arange(n)[:, None] * 4
    return v, k + [0, 1, 2], k + [0, 2, 3]


def write_ply(path, mesh) -> int:
    """Binary little-endian PLY (float32 x y z; uchar/int32 faces). Returns the byte size."""
    v, f = mesh
    v = np.ascontiguousarray(v, dtype="<f4")
    f = np.ascontiguousarray(f, dtype="<i4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rows = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rows["n"], rows["i"] = 3, f
    data = header + v.tobytes() + rows.tobytes()
    Path(path).write_bytes(data)
    return len(data)


SENSOR = """    <sensor type="perspective" id="sensor">
        <float name="fov" value="{fov}"/>
        <float name="near_clip" value="0.01"/>
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="{up}"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="64"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def sensor(origin, target, up=(0, 0, 1), *, fov=60, width=256, height=192) -> str:
    fmt = lambda x: ", ".join(f"{c:g}" for c in x)  # noqa: E731
    return SENSOR.format(fov=fov, origin=fmt(origin), target=fmt(target), up=fmt(up), width=width,
                         height=height)


def ply_shape(sid: str, filename: str, bsdf: str, emitter: str = "") -> str:
    """XML of a PLY shape with flat (face) normals and a BSDF reference or inline BSDF."""
    body = bsdf if bsdf.lstrip().startswith("<") else f'<ref id="{bsdf}"/>'
    return (f'    <shape type="ply" id="{sid}">\n        <string name="filename" value="{filename}"/>\n'
            f'        <boolean name="face_normals" value="true"/>\n        {body}\n{emitter}    </shape>\n')


def diffuse(bid: str, rgb, *, twosided: bool = False) -> str:
    value = ", ".join(f"{c:g}" for c in rgb)
    inner = f'<bsdf type="diffuse"><rgb name="reflectance" value="{value}"/></bsdf>'
    if twosided:
        return f'    <bsdf type="twosided" id="{bid}">{inner}</bsdf>\n'
    return f'    <bsdf type="diffuse" id="{bid}"><rgb name="reflectance" value="{value}"/></bsdf>\n'


def area_emitter(rgb) -> str:
    value = ", ".join(f"{c:g}" for c in rgb)
    return f'        <emitter type="area"><rgb name="radiance" value="{value}"/></emitter>\n'


def write_scene(folder, body: str, comment: str) -> None:
    text = f'<scene version="3.0.0">\n    <!-- {comment} -->\n    <integrator type="path"/>\n\n{body}</scene>\n'
    (Path(folder) / "scene.xml").write_text(text)
