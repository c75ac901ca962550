"""Files from a solution: PLY meshes, per-triangle, per-organ and per-shape tables, EXR images and lightmaps.

Units: radiosity B and irradiance H in W/m^2 per channel, area in m^2, absorbed power in W.
Absorbed power of a triangle is (1 - rho - tau) * H * A per side, front plus back (two-sided
BSDFs), with tau the diffuse transmittance of a translucent leaf's side (zero elsewhere): the light
a leaf of a plant model absorbs, neither reflected nor transmitted. Organs (``organ_table``) are shapes, connected pieces
of a mesh or face groups of its file (``mirad.organs``). Every file is written atomically.

Columns per channel are named ``radiosity_r``, ``_g``, ``_b``, or by band in a band solution
(``mirad.with_bands``): ``radiosity_PAR``, ``absorbed_NIR``; a band solution's .npz holds those
columns one array each, with ``bands`` naming the bands in order (``mirad.bands.channel_names``).
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from .arrays import group_mean, group_sum, to_bool, to_point3, to_uint, to_vector3
from .bands import channel_names, is_band_result
from .errors import OutputError, SettingsError
from .files import atomic_write, display_colors, exr_bytes, png_bytes, read_csv_text, read_exr
from .organs import ORGAN_KINDS, triangle_components, triangle_groups

__all__ = ["write_ply", "refined_mesh", "absorbed_power", "triangle_table", "shape_summary", "write_table", "write_shape_summary",
           "organ_table", "write_organ_table", "check_organ_options", "ORGAN_KINDS",
           "bake_lightmaps", "write_lightmaps", "exr_bytes", "png_bytes", "read_exr", "read_points",
           "write_probe_table", "lightmap_names", "TABLE_SUFFIXES", "PROBE_COLUMNS", "PLY_MESHES"]

#: Output suffixes of the per-triangle table.
TABLE_SUFFIXES = (".csv", ".npz")
_CHANNELS = "rgb"
#: (N, 3) table columns that are positions: written as name_x, name_y, name_z.
_POSITIONS = ("centroid",)
#: What ``write_ply`` writes: the input mesh or the refined mesh of the solution's leaves.
PLY_MESHES = ("input", "refined")
#: Columns a probe file must have (any order, more columns are ignored).
PROBE_COLUMNS = ("x", "y", "z", "nx", "ny", "nz")


# ------------------------------------------------------------------------------------------
# PLY
# ------------------------------------------------------------------------------------------

def write_ply(solution, path, *, mesh: str = "input", exposure: str = "scene") -> Path:
    """Binary PLY with per-vertex colours and float values, W/m^2.

    ``mesh="input"``: the input mesh; vertex values are area-weighted over the triangles around
    each vertex (front side). ``mesh="refined"``: the solution's own mesh, the front-side leaf
    elements with three unshared vertices each, so every element shows its own radiosity (flat,
    as radiosity tools export their solutions; shadow-texture detail at the corners).

    Vertex properties: ``red, green, blue, alpha`` (8-bit sRGB display colours of B/pi),
    ``radiosity_r/g/b``, ``irradiance_r/g/b`` and ``error_r/g/b`` (float32: radiosity, irradiance
    and the estimated error map of the radiosity, see ``Solution.triangle_error``). The colours
    map the 99th percentile to white over the non-emitting surfaces (``exposure="scene"``,
    so a light in view does not darken everything else) or over all (``exposure="all"``).
    """
    import trimesh

    if mesh not in PLY_MESHES:
        raise SettingsError(f"PLY mesh={mesh!r} must be one of {', '.join(PLY_MESHES)}")
    if exposure not in ("scene", "all"):
        raise SettingsError(f"PLY exposure={exposure!r} must be 'scene' (ignore emitters) or 'all'")
    if mesh == "input":
        verts, faces = solution.vertices, solution.faces
        b = solution.vertex_radiosity
        h = _vertex_mean(solution, solution.triangle_irradiance)
        err = _vertex_mean(solution, solution.triangle_error)
        emitting = _vertex_mean(solution, solution.triangle_emission).max(1) > 0
    else:
        verts, faces, b, h, err, emitting = refined_mesh(solution)
    if solution.scene is not None:
        verts = solution.scene.to_user(verts)    # a scene far from the origin is solved moved
    trimesh_mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    bands = is_band_result(solution)
    shown = b.mean(axis=1, keepdims=True) if bands else b       # bands: grey colours of their mean
    trimesh_mesh.visual.vertex_colors = display_colors(shown, exclude=emitting if exposure == "scene" else None)
    for c, name in enumerate(channel_names(solution) if bands else _CHANNELS[: b.shape[1]]):
        trimesh_mesh.vertex_attributes[f"radiosity_{name}"] = b[:, c].astype(np.float32)
        trimesh_mesh.vertex_attributes[f"irradiance_{name}"] = h[:, c].astype(np.float32)
        trimesh_mesh.vertex_attributes[f"error_{name}"] = err[:, c].astype(np.float32)
    data = trimesh.exchange.ply.export_ply(trimesh_mesh, encoding="binary", include_attributes=True)
    return atomic_write(Path(path), lambda handle: handle.write(data))


def refined_mesh(solution) -> tuple:
    """The front-side leaf elements as a mesh with unshared vertices.

    Returns (vertices (3N, 3) m, faces (N, 3) int, radiosity (3N, C), irradiance (3N, C),
    error (3N, C) W/m^2, emitting (3N,) bool); radiosity carries the shadow-texture detail at
    each corner of a textured leaf.
    """
    from .arrays import LEAF_CORNER_UV

    rows = np.flatnonzero(solution.leaf_side == 0)
    n = len(rows)
    leaf = np.repeat(rows, 3)
    uv = np.tile(LEAF_CORNER_UV, (n, 1))
    b = solution.radiosity_at(leaf, uv)
    h = solution.leaf_irradiance[leaf]
    err = solution.leaf_error[leaf]
    emitting = solution.triangle_emission[solution.leaf_triangle[leaf]].max(1) > 0
    verts = solution.leaf_vertices[rows].reshape(-1, 3)
    return verts, np.arange(3 * n).reshape(n, 3), b, h, err, emitting


def _vertex_mean(solution, per_triangle: np.ndarray) -> np.ndarray:
    """(V, C) area-weighted mean over the triangles around each vertex of per-triangle values (T, C)."""
    return group_mean(solution.faces.ravel(), np.repeat(per_triangle, 3, axis=0), len(solution.vertices),
                      weights=np.repeat(solution.triangle_area, 3))


# ------------------------------------------------------------------------------------------
# Tables
# ------------------------------------------------------------------------------------------

def absorbed_power(solution, irradiance: np.ndarray, back_irradiance: np.ndarray) -> np.ndarray:
    """(T, C) float, W: power absorbed by each input triangle, front plus back,
    (1 - rho - tau) H A per side, from its irradiance (T, C) and back irradiance (T, C), W/m^2.

    rho is the side's reflectance and tau its diffuse transmittance (a translucent leaf's; zero on
    opaque surfaces, which absorb (1 - rho) H A). The one definition every table uses.
    """
    area = solution.triangle_area[:, None]
    front = 1 - solution.triangle_reflectance - solution.triangle_transmittance   # x - 0 is x: opaque
    back = 1 - solution.back_reflectance - solution.back_transmittance            # scenes bitwise as before
    return (front * irradiance + back * back_irradiance) * area


def triangle_table(solution) -> dict:
    """Per input triangle: dict of arrays, T rows each.

    ``shape`` (T,) int index into ``shape_ids``; ``shape_id`` (T,) str; ``triangle`` (T,) int
    scene-wide index (shapes in order); ``area`` (T,) m^2; ``radiosity``, ``irradiance`` (T, C) W/m^2 (front side);
    ``back_radiosity``, ``back_irradiance`` (T, C) W/m^2 (zero where one-sided);
    ``absorbed`` (T, C) W = (1 - rho - tau) H A per side, front plus back, tau the side's diffuse
    transmittance (``Solution.triangle_transmittance``, ``back_transmittance``: translucent leaves;
    zero elsewhere, so opaque surfaces absorb (1 - rho) H A); ``error`` (T, C) W/m^2, the
    estimated error of ``radiosity`` (the error map); ``triangle_in_shape`` (T,) int, the
    triangle's index within its shape (the shape's own face order; last, so earlier columns keep
    their place).
    """
    area = solution.triangle_area
    h, h_back = solution.triangle_irradiance, solution.back_irradiance
    absorbed = absorbed_power(solution, h, h_back)
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
        "triangle_in_shape": solution.triangle_in_shape,
    }


def shape_summary(solution) -> dict:
    """Per shape: dict of arrays, S rows each (S = len(shape_ids)).

    ``shape_id`` (S,) str; ``triangles`` (S,) int; ``area`` (S,) m^2; ``mean_radiosity`` (S, C)
    W/m^2, area-weighted over the front side; ``absorbed`` (S, C) W, total over front and back
    of (1 - rho - tau) H A (``absorbed_power``), the sum of ``triangle_table``'s column.
    """
    table = triangle_table(solution)
    n = len(solution.shape_ids)
    shape, area = table["shape"], table["area"]
    total_area = np.bincount(shape, weights=area, minlength=n)
    mean = group_mean(shape, table["radiosity"], n, weights=area)
    absorbed = group_sum(shape, table["absorbed"], n)
    return {"shape_id": np.asarray(solution.shape_ids, dtype=str),
            "triangles": np.bincount(shape, minlength=n), "area": total_area,
            "mean_radiosity": mean, "absorbed": absorbed}


def _columns(table: dict, channels=None) -> list:
    """Flatten (N, C) arrays into name_r, name_g, name_b columns (or name_PAR, ... with ``channels``
    the band names): list of (name, values)."""
    cols = []
    for name, values in table.items():
        values = np.asarray(values)
        if values.ndim == 2:
            suffixes = "xyz" if name in _POSITIONS else (channels or _CHANNELS)
            for c in range(values.shape[1]):
                cols.append((f"{name}_{suffixes[c]}", values[:, c]))
        else:
            cols.append((name, values))
    return cols


def _csv_bytes(table: dict, channels=None) -> bytes:
    cols = _columns(table, channels)
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
    bands = _bands(solution)
    if suffix == ".csv":
        data = _csv_bytes(table, bands)
    elif suffix == ".npz":
        summary = shape_summary(solution)
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **_npz_arrays(table, bands),
                            **{f"shape_summary_{k}": v for k, v in _npz_arrays(summary, bands).items()
                               if k != "bands"})
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
    data = _csv_bytes(shape_summary(solution), _bands(solution))
    atomic_write(path, lambda handle: handle.write(data))
    return path


def _bands(solution):
    """The band names of a band solution (column suffixes), None for RGB."""
    return channel_names(solution) if is_band_result(solution) else None


def _npz_arrays(table: dict, bands) -> dict:
    """The arrays of a table for .npz: as they are (RGB), or with bands one column per band
    (``radiosity_PAR``) and ``bands`` naming them in order."""
    if bands is None:
        return table
    out = {name: values for name, values in _columns(table, bands)}
    out["bands"] = np.asarray(bands, dtype=str)
    return out


# ------------------------------------------------------------------------------------------
# Organs
# ------------------------------------------------------------------------------------------

def check_organ_options(*, by: str = "component", property: str | None = None) -> None:
    """Refuse an unknown ``by`` or a ``property`` given where it has no use (SettingsError)."""
    if by not in ORGAN_KINDS:
        raise SettingsError(f"organs by={by!r} is unknown; choose one of {', '.join(ORGAN_KINDS)} (component: "
                            "connected pieces of each mesh, such as leaves; group: face groups of the mesh "
                            "files; shape: whole shapes)")
    if property is not None and by != "group":
        raise SettingsError(f"a groups property ({property!r}) only applies to organs by group, not by {by!r}; "
                            "drop it or count organs by group")
    if property is not None and (not isinstance(property, str) or not property.strip()):
        raise SettingsError(f"groups property {property!r} must be the name of an integer PLY face property, "
                            "e.g. 'organ'")


def organ_table(solution, *, by: str = "component", property: str | None = None) -> dict:
    """Per organ: dict of arrays, N rows each (N organs, C channels).

    ``by``: what an organ is (``mirad.organs``): ``"component"``, a connected piece of a shape's
    mesh (a leaf); ``"group"``, a face group of its mesh file (the integer PLY face property named
    by ``property``, or OBJ ``g``/``o`` groups; shapes without groups are one group named by the
    shape id); ``"shape"``, the whole shape (every shape has a row, even one without triangles).
    Needs the solution's scene (``solution.attach``).

    Columns: ``shape`` (N,) int index into ``shape_ids``; ``shape_id`` (N,) str; ``component``
    (N,) int, the piece's index within its shape (by component) or ``group`` (N,) str, the group's
    name (by group); ``triangles`` (N,) int; ``area`` (N,) m^2; ``absorbed`` (N, C) W, front plus
    back, as in ``triangle_table``; ``incident`` (N, C) W, irradiance times area, front plus back;
    ``mean_radiosity``, ``mean_irradiance``, ``mean_back_irradiance`` (N, C) W/m^2, area-weighted
    (front side; back side, zero where one-sided), so that incident = (mean_irradiance +
    mean_back_irradiance) * area; ``centroid`` (N, 3) m, area-weighted, in the user's coordinates
    (NaN for a shape without triangles). Sums over the rows of a shape are the shape's totals.

    >>> table = organ_table(sol, by="component")          # doctest: +SKIP
    >>> table["absorbed"].shape                            # doctest: +SKIP
    (12, 3)
    """
    check_organ_options(by=by, property=property)
    scene = solution.require_scene()
    table = triangle_table(solution)
    shape, area = table["shape"], table["area"]
    extra = {}
    if by == "shape":
        organ, count = shape, len(solution.shape_ids)
        organ_shape = np.arange(count)
    elif by == "component":
        organ, organ_shape, index = triangle_components(solution.vertices, solution.faces, shape)
        count, extra = len(organ_shape), {"component": index}
    else:
        organ, organ_shape, names = triangle_groups(scene, property=property)
        count, extra = len(organ_shape), {"group": names}
    h, h_back = table["irradiance"], table["back_irradiance"]
    centre = solution.vertices[solution.faces].mean(axis=1)
    triangles = np.bincount(organ, minlength=count)
    centroid = scene.to_user(group_mean(organ, centre, count, weights=area))
    centroid[triangles == 0] = np.nan
    return {
        "shape": organ_shape,
        "shape_id": np.asarray(solution.shape_ids, dtype=str)[organ_shape],
        **extra,
        "triangles": triangles,
        "area": group_sum(organ, area, count),
        "absorbed": group_sum(organ, table["absorbed"], count),
        "incident": group_sum(organ, h + h_back, count, weights=area),
        "mean_radiosity": group_mean(organ, table["radiosity"], count, weights=area),
        "mean_irradiance": group_mean(organ, h, count, weights=area),
        "mean_back_irradiance": group_mean(organ, h_back, count, weights=area),
        "centroid": centroid,
    }


def write_organ_table(solution, path, *, by: str = "component", property: str | None = None) -> Path:
    """Per-organ table (``organ_table``) as .csv (one row per organ; (N, 3) columns as
    ``_r, _g, _b`` or ``centroid_x, _y, _z``) or .npz (the arrays as they are)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in TABLE_SUFFIXES:
        raise OutputError(f"organ table '{path}' must end in .csv or .npz")
    table = organ_table(solution, by=by, property=property)
    bands = _bands(solution)
    if suffix == ".csv":
        data = _csv_bytes(table, bands)
    else:
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **_npz_arrays(table, bands))
        data = buffer.getvalue()
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
    text = read_csv_text(path, "points file", ",".join(PROBE_COLUMNS), SettingsError)
    rows = [row for row in csv.reader(io.StringIO(text, newline="")) if row and any(cell.strip() for cell in row)]
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


def write_probe_table(path, points: np.ndarray, normals: np.ndarray, irradiance: np.ndarray,
                      error: np.ndarray | None = None, *, bands=None) -> Path:
    """CSV with x,y,z,nx,ny,nz, irradiance_r,g,b (W/m^2) and, given ``error`` (P, C), its standard
    error err_r,g,b (W/m^2, ``Solution.irradiance_at(..., with_error=True)``) per point; with
    ``bands`` (C names, ``mirad.bands.channel_names``) irradiance_PAR, err_PAR, ..."""
    path = Path(path)
    table = {name: col for name, col in zip(PROBE_COLUMNS, np.column_stack([points, normals]).T)}
    table["irradiance"] = np.asarray(irradiance, dtype=np.float64)
    if error is not None:
        table["err"] = np.asarray(error, dtype=np.float64)
    data = _csv_bytes(table, list(bands) if bands is not None else None)
    return atomic_write(path, lambda handle: handle.write(data))


# ------------------------------------------------------------------------------------------
# Lightmaps
# ------------------------------------------------------------------------------------------

def default_supersample(resolution: int) -> int:
    """Points per texel side when none is given: at least 2, and at least 256 points across the map,
    so a coarse map still averages each texel's footprint (64 -> 4, 128 and up -> 2)."""
    return max(2, -(-256 // int(resolution)))


def bake_lightmaps(solution, *, resolution: int = 256, supersample: int | None = None,
                   dilate: int = 8, quantity: str = "radiosity", quiet: bool = True) -> dict:
    """Radiosity (W/m^2) baked into a (resolution, resolution, 3) texture per shape with UVs
    (``quantity="error"``: the estimated error map instead, W/m^2).

    Leaves with shadow textures (``shadow_textures=True``) show their shadow detail inside.
    Texel (row i, column j) covers u in [j, j+1)/R and v in [i, i+1)/R: row 0 is v = 0, as
    Mitsuba's ``bitmap`` texture reads it, so a map can texture the same shape directly. Each
    texel averages ``supersample``^2 points, each showing the radiosity of the leaf element under
    it (default ``default_supersample(resolution)``, the same for the API and the CLI); empty
    texels next to covered ones are filled from their neighbours ``dilate`` times so bilinear
    lookups at island edges do not pull in black. Shapes without UVs are left out; ``quiet=False``
    shows a progress bar over the shapes.
    Returns {shape_id: image}.
    """
    from tqdm.auto import tqdm

    from .shading import Shading

    if isinstance(resolution, bool) or int(resolution) != resolution or not 1 <= resolution <= 16384:
        raise SettingsError(f"lightmap resolution={resolution!r} must be an integer in [1, 16384], e.g. 256")
    resolution = int(resolution)
    if supersample is None:
        supersample = default_supersample(resolution)
    if isinstance(supersample, bool) or int(supersample) != supersample or not 1 <= supersample <= 64:
        raise SettingsError(f"lightmap supersample={supersample!r} must be an integer in [1, 64], e.g. 2")
    uv_all = solution.vertex_uv
    if uv_all is None:
        return {}
    faces, shape_of = solution.faces, solution.triangle_shape
    tri_uv = uv_all[faces]                                              # (T, 3, 2)
    has_uv = np.all(np.isfinite(tri_uv), axis=(1, 2))
    if quantity not in ("radiosity", "error"):
        raise SettingsError(f"lightmap quantity={quantity!r} must be 'radiosity' or 'error'")
    shading = Shading(solution)
    b_leaf = np.asarray(solution.leaf_radiosity if quantity == "radiosity" else solution.leaf_error_share,
                        np.float64)
    b_tri = solution.triangle_radiosity if quantity == "radiosity" else solution.triangle_error
    maps = {}
    baked = [s for s in range(len(solution.shape_ids)) if np.any((shape_of == s) & has_uv)]
    for s in tqdm(baked, desc=f"lightmaps ({quantity})", unit="shape", disable=quiet, leave=False):
        sid = solution.shape_ids[s]                 # one vectorised bake per shape
        tris = np.flatnonzero((shape_of == s) & has_uv)
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
        leaf, leaf_uv, found = shading.locate(
            to_point3(p), to_vector3(normal), dr.zeros(mi.Bool, len(p)), to_uint(np.full(len(p), s)), to_bool(np.ones(len(p), bool)))
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
    return dilate_islands(image, filled, dilate).astype(np.float32)


def dilate_islands(image: np.ndarray, filled: np.ndarray, passes: int) -> np.ndarray:
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


def lightmap_names(shape_ids) -> dict:
    """A file stem per shape id, unique even where ids differ only in characters that are not
    safe in file names or in letter case (``wall 1`` and ``wall_1`` -> ``wall_1``, ``wall_1~2``):
    {shape_id: stem}, in the order given."""
    stems, taken = {}, set()
    for sid in shape_ids:
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", sid).strip(".") or "shape"
        stem, k = base, 1
        while stem.lower() in taken:
            k += 1
            stem = f"{base}~{k}"
        taken.add(stem.lower())
        stems[sid] = stem
    return stems


#: File in a lightmap folder that maps shape ids to lightmap files.
LIGHTMAP_INDEX = "lightmaps.csv"


def write_lightmaps(solution, folder, *, resolution: int = 256, supersample: int | None = None, dilate: int = 8,
                    error: bool = False, quiet: bool = True) -> list:
    """Bake lightmaps and write ``<folder>/<stem>.exr`` (R, G, B float, W/m^2; a band solution: one
    channel per band, named by it) per shape with UVs,
    and ``<folder>/lightmaps.csv`` mapping each shape id to its file (stems are unique, see
    ``lightmap_names``); with ``error``, also ``<stem>.error.exr``, the estimated error map (W/m^2).
    Returns the paths written."""
    folder = Path(folder)
    if not folder.is_dir():
        raise OutputError(f"lightmap folder '{folder}' does not exist; create it first")
    maps = bake_lightmaps(solution, resolution=resolution, supersample=supersample, dilate=dilate, quiet=quiet)
    if not maps:
        raise OutputError("no shape in the scene has texture coordinates (UVs); there is nothing to bake")
    stems = lightmap_names(solution.shape_ids)
    bands = _bands(solution)
    if bands is None:
        rgb = lambda img: {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]}  # noqa: E731
    else:                                   # a band solution: one EXR channel per band, named by it
        rgb = lambda img: {name: img[..., c] for c, name in enumerate(bands)}  # noqa: E731
    blobs = {f"{stems[sid]}.exr": exr_bytes(rgb(img)) for sid, img in maps.items()}
    index = {"shape_id": list(maps), "file": [f"{stems[sid]}.exr" for sid in maps]}
    if error:
        errors = bake_lightmaps(solution, resolution=resolution, supersample=supersample, dilate=dilate,
                                quantity="error", quiet=quiet)
        blobs.update({f"{stems[sid]}.error.exr": exr_bytes(rgb(img)) for sid, img in errors.items()})
        index["error_file"] = [f"{stems[sid]}.error.exr" for sid in maps]
    blobs[LIGHTMAP_INDEX] = _csv_bytes({k: np.asarray(v, dtype=str) for k, v in index.items()})
    return [atomic_write(folder / name, lambda handle, blob=blob: handle.write(blob))  # one file per map
            for name, blob in blobs.items()]
