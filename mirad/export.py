"""Files from a solution: PLY meshes, per-triangle and per-shape tables, EXR images and lightmaps.

Units: radiosity B and irradiance H in W/m^2 per channel, area in m^2, absorbed power in W.
Absorbed power of a triangle is (1 - rho) * H * A per side, front plus back (two-sided BSDFs):
the light a leaf of a plant model absorbs. Every file is written atomically.
"""

from __future__ import annotations

import csv
import io
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from .errors import OutputError, SettingsError
from .solution import atomic_write, display_colors

__all__ = ["write_ply", "triangle_table", "shape_summary", "write_table", "write_shape_summary",
           "bake_lightmaps", "write_lightmaps", "exr_bytes", "png_bytes", "read_exr", "read_points",
           "write_probe_table", "TABLE_SUFFIXES", "PROBE_COLUMNS"]

#: Output suffixes of the per-triangle table.
TABLE_SUFFIXES = (".csv", ".npz")
_CHANNELS = "rgb"
#: Columns a probe file must have (any order, more columns are ignored).
PROBE_COLUMNS = ("x", "y", "z", "nx", "ny", "nz")


# ------------------------------------------------------------------------------------------
# PLY
# ------------------------------------------------------------------------------------------

def write_ply(solution, path) -> Path:
    """Binary PLY of the input mesh with per-vertex colours and float values.

    Vertex properties: ``red, green, blue, alpha`` (8-bit sRGB display colours of B/pi, the 99th
    percentile mapped to white), ``radiosity_r/g/b`` and ``irradiance_r/g/b`` (float32, W/m^2,
    area-weighted over the triangles around each vertex, front side) and ``error_r/g/b`` (the
    estimated error map of the radiosity, W/m^2, see ``Solution.triangle_error``).
    """
    import trimesh

    b = solution.vertex_radiosity
    h = _vertex_mean(solution, solution.triangle_irradiance)
    err = _vertex_mean(solution, solution.triangle_error)
    mesh = trimesh.Trimesh(vertices=solution.vertices, faces=solution.faces, process=False)
    mesh.visual.vertex_colors = display_colors(b)
    for c, name in enumerate(_CHANNELS[: b.shape[1]]):
        mesh.vertex_attributes[f"radiosity_{name}"] = b[:, c].astype(np.float32)
        mesh.vertex_attributes[f"irradiance_{name}"] = h[:, c].astype(np.float32)
        mesh.vertex_attributes[f"error_{name}"] = err[:, c].astype(np.float32)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True)
    path = Path(path)
    atomic_write(path, lambda handle: handle.write(data))
    return path


def _vertex_mean(solution, per_triangle: np.ndarray) -> np.ndarray:
    faces, area = solution.faces, solution.triangle_area
    n_vert = len(solution.vertices)
    idx = faces.ravel()
    w = np.repeat(area, 3)
    total = np.stack([np.bincount(idx, weights=w * np.repeat(per_triangle[:, c], 3), minlength=n_vert)
                      for c in range(per_triangle.shape[1])], 1)
    return total / np.maximum(np.bincount(idx, weights=w, minlength=n_vert), 1e-300)[:, None]


# ------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------

def _back_values(solution):
    """(back irradiance (T, C), back reflectance (T, C)); zero where a triangle is one-sided."""
    h_back = solution._side(solution._per_patch(solution._a["leaf_irradiance"]), 1)
    rho_back = solution._a.get("back_rho")
    if rho_back is None:
        rho_back = np.zeros_like(h_back)
    return h_back, rho_back


def triangle_table(solution) -> dict:
    """Per input triangle: dict of arrays, T rows each.

    ``shape`` (T,) int index into ``shape_ids``; ``shape_id`` (T,) str; ``triangle`` (T,) int global
    index; ``area`` (T,) m^2; ``radiosity``, ``irradiance`` (T, C) W/m^2 (front side);
    ``back_radiosity``, ``back_irradiance`` (T, C) W/m^2 (zero where one-sided);
    ``absorbed`` (T, C) W = (1 - rho) H A, front plus back; ``error`` (T, C) W/m^2, the
    estimated error of ``radiosity`` (the error map).
    """
    area = solution.triangle_area
    rho = solution._a["triangle_rho"]
    h = solution.triangle_irradiance
    h_back, rho_back = _back_values(solution)
    absorbed = ((1 - rho) * h + (1 - rho_back) * h_back) * area[:, None]
    shape = np.asarray(solution.triangle_shape, dtype=np.int64)
    return {
        "shape": shape,
        "shape_id": np.asarray(solution.shape_ids, dtype=str)[shape],
        "triangle": np.arange(len(area)),
        "area": area,
        "radiosity": solution.triangle_radiosity,
        "irradiance": h,
        "back_radiosity": solution.back_radiosity,
        "back_irradiance": h_back,
        "absorbed": absorbed,
        "error": solution.triangle_error,
    }


def shape_summary(solution) -> dict:
    """Per shape: dict of arrays, S rows each (S = len(shape_ids)).

    ``shape_id`` (S,) str; ``triangles`` (S,) int; ``area`` (S,) m^2; ``mean_radiosity`` (S, C)
    W/m^2, area-weighted over the front side; ``absorbed`` (S, C) W, total over front and back.
    """
    table = triangle_table(solution)
    n = len(solution.shape_ids)
    shape, area = table["shape"], table["area"]
    total_area = np.bincount(shape, weights=area, minlength=n)
    channels = table["radiosity"].shape[1]
    mean = np.stack([np.bincount(shape, weights=area * table["radiosity"][:, c], minlength=n)
                     for c in range(channels)], 1) / np.maximum(total_area, 1e-300)[:, None]
    absorbed = np.stack([np.bincount(shape, weights=table["absorbed"][:, c], minlength=n)
                         for c in range(channels)], 1)
    return {"shape_id": np.asarray(solution.shape_ids, dtype=str),
            "triangles": np.bincount(shape, minlength=n), "area": total_area,
            "mean_radiosity": mean, "absorbed": absorbed}


def _columns(table: dict) -> list:
    """Flatten (N, C) arrays into name_r, name_g, name_b columns: list of (name, values)."""
    cols = []
    for name, values in table.items():
        values = np.asarray(values)
        if values.ndim == 2:
            for c in range(values.shape[1]):
                cols.append((f"{name}_{_CHANNELS[c]}", values[:, c]))
        else:
            cols.append((name, values))
    return cols


def _csv_bytes(table: dict) -> bytes:
    cols = _columns(table)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow([name for name, _ in cols])
    formatted = [v.astype(str) if v.dtype.kind in "UOiu" else np.char.mod("%.9g", v) for _, v in cols]
    writer.writerows(zip(*formatted))
    return out.getvalue().encode()


def write_table(solution, path) -> Path:
    """Per-triangle table as .csv (one row per triangle) or .npz (arrays, plus the shape summary)."""
    path = Path(path)
    suffix = path.suffix.lower()
    table = triangle_table(solution)
    if suffix == ".csv":
        data = _csv_bytes(table)
    elif suffix == ".npz":
        summary = shape_summary(solution)
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **table, **{f"shape_summary_{k}": v for k, v in summary.items()})
        data = buffer.getvalue()
    else:
        raise OutputError(f"table output '{path}' must end in .csv or .npz")
    atomic_write(path, lambda handle: handle.write(data))
    return path


def write_shape_summary(solution, path) -> Path:
    """Per-shape summary as .csv (one row per shape)."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        raise OutputError(f"shape summary '{path}' must end in .csv")
    data = _csv_bytes(shape_summary(solution))
    atomic_write(path, lambda handle: handle.write(data))
    return path


# ------------------------------------------------------------------------------------------
# Probes
# ------------------------------------------------------------------------------------------

def read_points(path) -> tuple:
    """Sensor points from a CSV file with a header naming x, y, z, nx, ny, nz.

    Returns (points (P, 3) float, normals (P, 3) float). Raises SettingsError naming the file and
    the problem (missing columns, a value that is not a finite number, a zero normal).
    """
    from .errors import SettingsError

    path = Path(path)
    if not path.is_file():
        raise SettingsError(f"points file '{path}' does not exist; give a CSV with columns {','.join(PROBE_COLUMNS)}")
    with open(path, newline="") as handle:
        rows = [row for row in csv.reader(handle) if row and any(cell.strip() for cell in row)]
    if not rows:
        raise SettingsError(f"points file '{path}' is empty; give a header {','.join(PROBE_COLUMNS)} and one row per point")
    header = [cell.strip().lower() for cell in rows[0]]
    missing = [c for c in PROBE_COLUMNS if c not in header]
    if missing:
        raise SettingsError(f"points file '{path}' lacks column(s) {', '.join(missing)} (its header is "
                            f"{','.join(header)}); the header must name {','.join(PROBE_COLUMNS)}")
    if len(rows) < 2:
        raise SettingsError(f"points file '{path}' has a header but no points")
    index = [header.index(c) for c in PROBE_COLUMNS]
    values = np.empty((len(rows) - 1, 6))
    for line, row in enumerate(rows[1:], start=2):  # parsing text: one row at a time
        try:
            values[line - 2] = [float(row[i]) for i in index]
        except (ValueError, IndexError):
            raise SettingsError(f"points file '{path}', line {line}: expected numbers in columns "
                                f"{','.join(PROBE_COLUMNS)}, got {row}") from None
    if not np.all(np.isfinite(values)):
        raise SettingsError(f"points file '{path}': every coordinate must be a finite number")
    bad = np.flatnonzero(np.linalg.norm(values[:, 3:], axis=1) == 0)
    if len(bad):
        raise SettingsError(f"points file '{path}', line {bad[0] + 2}: the normal (nx, ny, nz) is zero; "
                            "give the direction the sensor faces")
    return values[:, :3], values[:, 3:]


def write_probe_table(path, points: np.ndarray, normals: np.ndarray, irradiance: np.ndarray) -> Path:
    """CSV with x,y,z,nx,ny,nz and irradiance_r,g,b (W/m^2) per point."""
    path = Path(path)
    table = {name: col for name, col in zip(PROBE_COLUMNS, np.column_stack([points, normals]).T)}
    table["irradiance"] = np.asarray(irradiance, dtype=np.float64)
    data = _csv_bytes(table)
    atomic_write(path, lambda handle: handle.write(data))
    return path


# ------------------------------------------------------------------------------------------
# Lightmaps
# ------------------------------------------------------------------------------------------

def bake_lightmaps(solution, *, resolution: int = 256, supersample: int | None = None,
                   dilate: int = 8, quantity: str = "radiosity") -> dict:
    """Radiosity (W/m^2) baked into a (resolution, resolution, 3) texture per shape with UVs
    (``quantity="error"``: the estimated error map instead, W/m^2).

    Leaves with shadow textures (``shadow_textures=True``) show their shadow detail inside.
    Texel (row i, column j) covers u in [j, j+1)/R and v in [i, i+1)/R: row 0 is v = 0, as
    Mitsuba's ``bitmap`` texture reads it, so a map can texture the same shape directly. Each
    texel averages ``supersample``^2 points, each showing the radiosity of the leaf element under
    it (default: enough for at least 1024 points across the map, so a coarse map of a finely
    refined solution still averages each texel's footprint); empty texels next to covered ones are filled from their neighbours ``dilate`` times so
    bilinear lookups at island edges do not pull in black. Shapes without UVs are left out.
    Returns {shape_id: image}.
    """
    from .display import Shading

    if isinstance(resolution, bool) or int(resolution) != resolution or not 1 <= resolution <= 16384:
        raise SettingsError(f"lightmap resolution={resolution!r} must be an integer in [1, 16384], e.g. 256")
    resolution = int(resolution)
    if supersample is None:
        supersample = max(2, -(-1024 // resolution))
    a = solution._a
    uv_all = a.get("vertex_uv")
    if uv_all is None:
        return {}
    faces, shape_of = a["faces"], a["triangle_shape"]
    tri_uv = uv_all[faces]                                              # (T, 3, 2)
    has_uv = np.all(np.isfinite(tri_uv), axis=(1, 2))
    if quantity not in ("radiosity", "error"):
        raise SettingsError(f"lightmap quantity={quantity!r} must be 'radiosity' or 'error'")
    shading = Shading(solution)
    b_leaf = np.asarray(a[f"leaf_{quantity}"], np.float64)
    b_tri = solution.triangle_radiosity if quantity == "radiosity" else solution.triangle_error
    maps = {}
    for s, sid in enumerate(solution.shape_ids):   # one vectorised bake per shape
        tris = np.flatnonzero((shape_of == s) & has_uv)
        if len(tris) == 0:
            continue
        maps[sid] = _bake_shape(solution, shading, s, tris, tri_uv[tris], b_leaf, b_tri,
                                resolution, supersample, dilate, detail=quantity == "radiosity")
    return maps


def _bake_shape(solution, shading, s, tris, uv, b_leaf, b_tri, res, ss, dilate, *, detail: bool):
    import drjit as dr
    import mitsuba as mi

    n = res * ss
    uv = uv.copy()
    # analytic shapes tessellated by mirad have one periodic uv axis (u = phi / 2 pi for spheres
    # and cylinders, v = phi / 2 pi for disks): unwrap the triangles across its seam
    kind = solution.scene.shape_types[s]
    periodic = {"Sphere": (0,), "Cylinder": (0,), "Disk": (1,)}.get(kind, ())
    for axis in periodic:
        span = uv[:, :, axis].max(1) - uv[:, :, axis].min(1)
        wrap = span > 0.5
        low = wrap[:, None] & (uv[:, :, axis] < 0.5)
        uv[:, :, axis] = np.where(low, uv[:, :, axis] + 1.0, uv[:, :, axis])
    # ---------------- candidate sample points: every grid point in each triangle's bbox -------
    lo = np.floor(uv.min(1) * n - 0.5).astype(np.int64)
    hi = np.ceil(uv.max(1) * n - 0.5).astype(np.int64)
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    count = nx * ny
    owner = np.repeat(np.arange(len(tris)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    gx = lo[owner, 0] + local % nx[owner]
    gy = lo[owner, 1] + local // nx[owner]
    q = np.stack([(gx + 0.5) / n, (gy + 0.5) / n], 1)
    # ---------------- barycentrics in uv, keep the points inside ------------------------------
    t = uv[owner]
    e1, e2, d = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0], q - t[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-20
    det = np.where(ok, det, 1.0)
    w1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
    w2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
    eps = 1e-9
    inside = ok & (w1 >= -eps) & (w2 >= -eps) & (w1 + w2 <= 1 + eps)
    owner, w1, w2 = owner[inside], w1[inside], w2[inside]
    gx, gy = gx[inside] % n, gy[inside] % n
    # ---------------- 3D points, the leaf under each, its radiosity ----------------------------
    tri = tris[owner]
    corners = solution.vertices[solution.faces[tri]]
    p = (1 - w1 - w2)[:, None] * corners[:, 0] + w1[:, None] * corners[:, 1] + w2[:, None] * corners[:, 2]
    normal = solution.scene.tri_normal[tri]
    value = b_tri[tri].copy()
    if len(p):
        f = lambda x: mi.Float(np.ascontiguousarray(x, np.float32))  # noqa: E731
        leaf, leaf_uv, found = shading.locate(
            mi.Point3f(f(p[:, 0]), f(p[:, 1]), f(p[:, 2])), mi.Vector3f(f(normal[:, 0]), f(normal[:, 1]), f(normal[:, 2])),
            dr.zeros(mi.Bool, len(p)), mi.UInt32(np.full(len(p), s, np.uint32)), mi.Bool(np.ones(len(p), bool)))
        leaf, found = np.asarray(leaf.numpy(), np.int64), np.asarray(found.numpy(), bool)
        value[found] = b_leaf[leaf[found]]
        if detail and len(solution.detail_leaves):     # shadow-texture detail inside the leaf
            leaf_uv = np.stack([np.asarray(leaf_uv.x.numpy()), np.asarray(leaf_uv.y.numpy())], 1)
            value[found] += solution.detail_at(leaf[found], leaf_uv[found])
    # ---------------- texels: mean of their points, then edge dilation -------------------------
    texel = (gy // ss) * res + gx // ss
    channels = value.shape[1]
    total = np.stack([np.bincount(texel, weights=value[:, c], minlength=res * res) for c in range(channels)], 1)
    hits = np.bincount(texel, minlength=res * res).astype(np.float64)
    image = (total / np.maximum(hits, 1)[:, None]).reshape(res, res, channels)
    filled = (hits > 0).reshape(res, res)
    return _dilate(image, filled, dilate).astype(np.float32)


def _dilate(image: np.ndarray, filled: np.ndarray, passes: int) -> np.ndarray:
    """Fill empty texels with the mean of their filled 8-neighbours, ``passes`` rings deep."""
    image = image.copy()
    filled = filled.copy()
    for _ in range(passes):  # a few rings, each a whole-image numpy operation
        if filled.all():
            break
        pad_v = np.pad(image * filled[..., None], ((1, 1), (1, 1), (0, 0)))
        pad_f = np.pad(filled.astype(np.float64), 1)
        acc = np.zeros_like(image)
        cnt = np.zeros(filled.shape)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy or dx:
                    sl = (slice(1 + dy, 1 + dy + filled.shape[0]), slice(1 + dx, 1 + dx + filled.shape[1]))
                    acc += pad_v[sl]
                    cnt += pad_f[sl]
        grow = ~filled & (cnt > 0)
        image[grow] = acc[grow] / cnt[grow][:, None]
        filled |= grow
    return image


def _safe_name(shape_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", shape_id) or "shape"


def write_lightmaps(solution, folder, *, resolution: int = 256, supersample: int = 2, dilate: int = 8,
                    error: bool = False) -> list:
    """Bake lightmaps and write ``<folder>/<shape_id>.exr`` (R, G, B float, W/m^2) per shape with UVs;
    with ``error``, also ``<shape_id>.error.exr``, the estimated error map (W/m^2)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise OutputError(f"lightmap folder '{folder}' does not exist; create it first")
    maps = bake_lightmaps(solution, resolution=resolution, supersample=supersample, dilate=dilate)
    if not maps:
        raise OutputError("no shape in the scene has texture coordinates (UVs); there is nothing to bake")
    blobs = {f"{_safe_name(sid)}.exr": exr_bytes({"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
             for sid, img in maps.items()}
    if error:
        errors = bake_lightmaps(solution, resolution=resolution, supersample=supersample, dilate=dilate,
                                quantity="error")
        blobs.update({f"{_safe_name(sid)}.error.exr": exr_bytes({"R": img[..., 0], "G": img[..., 1],
                                                                 "B": img[..., 2]})
                      for sid, img in errors.items()})
    written = []
    for name, blob in blobs.items():  # one file per shape (and map)
        path = folder / name
        atomic_write(path, lambda handle, blob=blob: handle.write(blob))
        written.append(path)
    return written


# ------------------------------------------------------------------------------------------
# Image files
# ------------------------------------------------------------------------------------------

def exr_bytes(channels: dict) -> bytes:
    """An OpenEXR file (float32 channels, ZIP compression) as bytes; channels: name -> (H, W)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {name: np.ascontiguousarray(values, dtype=np.float32) for name, values in channels.items()}
    with tempfile.TemporaryDirectory() as tmp:
        name = os.path.join(tmp, "image.exr")
        with OpenEXR.File(header, data) as exr:
            exr.write(name)
        with open(name, "rb") as handle:
            return handle.read()


def read_exr(path) -> dict:
    """Channels of an OpenEXR file: name -> (H, W) float32."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as exr:
        return {name: np.array(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}


def png_bytes(rgb8: np.ndarray) -> bytes:
    """An 8-bit RGB PNG as bytes."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8, dtype=np.uint8), "RGB").save(buffer, format="PNG")
    return buffer.getvalue()
