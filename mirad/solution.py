"""The result of a solve: per-leaf, per-triangle and per-vertex radiosity, queries, stats, files."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import OutputError, SolutionMismatch

#: Format version of saved .npz solutions.
FORMAT = 1


#: (u, v) of a leaf's corners v0, v1, v2 in its parametrisation y = v0 + u (v1 - v0) + v (v2 - v0).
LEAF_CORNER_UV = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


class Solution:
    """Radiosity solution of one scene (units: W/m^2; radiance = radiosity / pi).

    Attributes
    ----------
    shape_ids : list[str]             Mitsuba ids, in ``mi.Scene.shapes()`` order
    triangle_radiosity : (T, C) float front-side radiosity per input triangle
    triangle_irradiance : (T, C) float front-side irradiance per input triangle
    back_radiosity : (T, C) float     back-side radiosity (zero where one-sided)
    triangle_area : (T,) float        m^2
    triangle_shape : (T,) int         index into shape_ids
    vertex_radiosity : (V, C) float   smooth per-vertex radiosity (front side), with the
                                      shadow-texture detail at the vertex where a leaf has one
    stats : dict                      elements, links, rays, seconds, estimated_error, features, variant
    """

    def __init__(self, *, arrays: dict, stats: dict, shape_ids: list, fingerprint: str, scene=None):
        self._a = arrays
        self.stats = stats
        self.shape_ids = list(shape_ids)
        self.fingerprint = fingerprint
        self.scene = scene

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def from_solve(cls, scene, prob, leaves, b_leaf, h_leaf, err_leaf, stats, detail=None) -> "Solution":
        e = prob.elements
        channels = scene.channels
        widen = (lambda x: np.repeat(x, channels, axis=1)) if b_leaf.shape[1] == 1 else (lambda x: x)
        b_leaf, h_leaf, err_leaf = widen(b_leaf), widen(h_leaf), widen(err_leaf)
        patch = e.patch[leaves]
        arrays = {
            "leaf_verts": e.verts[leaves].astype(np.float64),
            "leaf_patch": patch.astype(np.int32),
            "leaf_normal": prob.patch_normal[patch],
            "leaf_radiosity": b_leaf,
            "leaf_irradiance": h_leaf,
            "leaf_error": err_leaf,
            "patch_tri": scene.patch_tri.astype(np.int64),
            "patch_side": scene.patch_side.astype(np.int8),
            "curve_center": scene.curve_center, "curve_axis": scene.curve_axis,
            "curve_radius": scene.curve_radius,
            "vertices": scene.vertices, "faces": scene.faces,
            "triangle_area": scene.tri_area, "triangle_shape": scene.tri_shape,
            "triangle_rho": scene.tri_rho, "triangle_emission": scene.tri_emission,
            "back_rho": scene.back_rho,
        }
        if scene.vertex_uv is not None:
            arrays["vertex_uv"] = scene.vertex_uv
        if detail is not None and len(detail[0]):
            rows, tex = detail
            arrays["detail_leaf"] = np.asarray(rows, np.int32)
            arrays["leaf_detail"] = np.repeat(tex, channels, axis=3) if tex.shape[3] == 1 else tex
        return cls(arrays=arrays, stats=stats, shape_ids=scene.shape_ids,
                   fingerprint=scene.fingerprint, scene=scene)

    # --- per-leaf data -----------------------------------------------------------------------
    @property
    def leaf_radiosity(self) -> np.ndarray:
        """(L, C) radiosity of the finest elements."""
        return self._a["leaf_radiosity"]

    @property
    def leaf_vertices(self) -> np.ndarray:
        """(L, 3, 3) corners of the finest elements."""
        return self._a["leaf_verts"]

    @property
    def leaf_area(self) -> np.ndarray:
        v = self._a["leaf_verts"]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    @property
    def detail_leaves(self) -> np.ndarray:
        """(T,) rows of the leaves that carry shadow-texture detail (empty without textures)."""
        return self._a.get("detail_leaf", np.zeros(0, np.int32))

    def detail_at(self, leaf, uv) -> np.ndarray:
        """(P, C) shadow-texture detail of radiosity, W/m^2, at points with parameters uv (P, 2)
        on leaves ``leaf`` (P,) (y = v0 + u (v1 - v0) + v (v2 - v0) over ``leaf_vertices``);
        zero on leaves without texture links. Its mean over each leaf is zero: the leaf's
        radiosity already holds the texture links' mean transfer."""
        leaf = np.asarray(leaf, np.int64)
        c = self._a["leaf_radiosity"].shape[1]
        out = np.zeros((len(leaf), c))
        rows = self.detail_leaves
        if not len(rows) or not len(leaf):
            return out
        slot = np.full(len(self._a["leaf_radiosity"]), -1, np.int64)
        slot[rows] = np.arange(len(rows))
        k = slot[leaf]
        has = k >= 0
        if has.any():
            from .shadows import bilinear

            out[has] = bilinear(self._a["leaf_detail"], k[has], np.asarray(uv)[has])
        return out

    def radiosity_at(self, leaf, uv) -> np.ndarray:
        """(P, C) radiosity at points (leaf (P,), uv (P, 2)): the leaf's value plus its shadow
        detail (``detail_at``), W/m^2."""
        return self._a["leaf_radiosity"][np.asarray(leaf, np.int64)] + self.detail_at(leaf, uv)

    # --- per triangle / shape / vertex --------------------------------------------------------
    def _per_patch(self, values: np.ndarray) -> np.ndarray:
        patch = self._a["leaf_patch"]
        n_patch = len(self._a["patch_tri"])
        area = self.leaf_area
        total = np.stack([np.bincount(patch, weights=area * values[:, c], minlength=n_patch)
                          for c in range(values.shape[1])], 1)
        return total / np.maximum(np.bincount(patch, weights=area, minlength=n_patch), 1e-300)[:, None]

    def _side(self, per_patch: np.ndarray, side: int) -> np.ndarray:
        out = np.zeros((len(self._a["faces"]), per_patch.shape[1]))
        mask = self._a["patch_side"] == side
        out[self._a["patch_tri"][mask]] = per_patch[mask]
        return out

    @property
    def triangle_radiosity(self) -> np.ndarray:
        return self._side(self._per_patch(self._a["leaf_radiosity"]), 0)

    @property
    def triangle_irradiance(self) -> np.ndarray:
        return self._side(self._per_patch(self._a["leaf_irradiance"]), 0)

    @property
    def triangle_error(self) -> np.ndarray:
        """(T, C) estimated absolute error of triangle_radiosity, W/m^2."""
        return self._side(self._per_patch(self._a["leaf_error"]), 0)

    @property
    def back_radiosity(self) -> np.ndarray:
        return self._side(self._per_patch(self._a["leaf_radiosity"]), 1)

    @property
    def triangle_area(self) -> np.ndarray:
        return self._a["triangle_area"]

    @property
    def triangle_shape(self) -> np.ndarray:
        return self._a["triangle_shape"]

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) mesh vertices of all shapes (world space)."""
        return self._a["vertices"]

    @property
    def faces(self) -> np.ndarray:
        """(T, 3) vertex indices of the input triangles."""
        return self._a["faces"]

    @property
    def vertex_radiosity(self) -> np.ndarray:
        """(V, C) area-weighted mean of the radiosity of the triangles around each vertex."""
        faces, area = self._a["faces"], self._a["triangle_area"]
        b = self.triangle_radiosity
        n_vert = len(self._a["vertices"])
        idx = faces.ravel()
        w = np.repeat(area, 3)
        total = np.stack([np.bincount(idx, weights=w * np.repeat(b[:, c], 3), minlength=n_vert)
                          for c in range(b.shape[1])], 1)
        total += self._vertex_detail(n_vert)
        return total / np.maximum(np.bincount(idx, weights=w, minlength=n_vert), 1e-300)[:, None]

    def _vertex_detail(self, n_vert: int) -> np.ndarray:
        """(V, C) triangle-area-weighted shadow-texture detail at the input vertices: for each
        front-side textured leaf with a corner on a vertex of its triangle, the detail there."""
        a = self._a
        rows = self.detail_leaves
        out = np.zeros((n_vert, a["leaf_radiosity"].shape[1]))
        rows = rows[a["patch_side"][a["leaf_patch"][rows]] == 0]
        if not len(rows):
            return out
        tri = a["patch_tri"][a["leaf_patch"][rows]]
        corners = a["leaf_verts"][rows]                                     # (T, 3 corners, 3)
        tri_verts = a["vertices"][a["faces"][tri]]                          # (T, 3 vertices, 3)
        diag = float(np.linalg.norm(a["vertices"].max(0) - a["vertices"].min(0))) or 1.0
        dist = np.linalg.norm(corners[:, :, None] - tri_verts[:, None], axis=-1)
        t, k, j = np.nonzero(dist < 1e-9 * diag)
        detail = self.detail_at(rows[t], LEAF_CORNER_UV[k])
        np.add.at(out, a["faces"][tri[t], j], a["triangle_area"][tri[t], None] * detail)
        return out

    def shape_radiosity(self, shape_id: str) -> np.ndarray:
        """(C,) area-weighted mean radiosity over the shape's front side, W/m^2."""
        index = self._shape_index(shape_id)
        mask = self._a["triangle_shape"] == index
        area = self._a["triangle_area"][mask]
        return (self.triangle_radiosity[mask] * area[:, None]).sum(0) / area.sum()

    def _shape_index(self, shape_id: str) -> int:
        try:
            return self.shape_ids.index(shape_id)
        except ValueError:
            raise KeyError(f"no shape with id {shape_id!r}; ids are {self.shape_ids}") from None

    # --- queries ---------------------------------------------------------------------------------
    def irradiance_at(self, points, normals, *, rays: int = 4, seed: int = 0) -> np.ndarray:
        """Irradiance (P, C), W/m^2, at points (P, 3) facing normals (P, 3).

        A local gather over every leaf element of the solution (Lambert form factor to the
        leaf times its radiosity, with ``rays`` shadow rays per leaf), plus the direct light
        of point, spot, directional and environment emitters.
        """
        from .emitters import direct_irradiance
        from .visibility import Geometry, gather_at_points

        scene = self._require_scene()
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        normals = np.atleast_2d(np.asarray(normals, dtype=np.float64))
        if points.shape[1:] != (3,) or normals.shape != points.shape:
            raise ValueError(f"points and normals must both be (P, 3) arrays; got {points.shape} and {normals.shape}")
        if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
            raise ValueError("points and normals must be finite")
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        if np.any(length == 0):
            raise ValueError("every normal must be non-zero")
        normals = normals / length
        a = self._a
        tri = a["patch_tri"][a["leaf_patch"]]
        geo = Geometry.upload(a["leaf_verts"], a["leaf_normal"], a["curve_center"][tri],
                              a["curve_axis"][tri], a["curve_radius"][tri], scene.diagonal)
        h = gather_at_points(scene.mi_scene, points, normals, geo, a["leaf_radiosity"], rays=rays, seed=seed)
        if scene.light_emitters:
            # a tiny triangle around each point stands in for the point
            r = 1e-7 * scene.diagonal
            t1 = np.cross(normals, np.where(np.abs(normals[:, :1]) < 0.9, [[1, 0, 0]], [[0, 1, 0]]))
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            t2 = np.cross(normals, t1)
            tri_pts = np.stack([points + r * t1, points + r * t2, points - r * (t1 + t2)], 1)
            zero = np.zeros((len(points), 3))
            hd, _ = direct_irradiance(scene, tri_pts, normals, (zero, zero, np.zeros(len(points))),
                                      samples=64, seed=seed, keys=np.arange(len(points)))
            h = h + hd
        return h

    def _require_scene(self):
        if self.scene is None:
            raise SolutionMismatch("this solution was loaded from a file without its scene; "
                                   "call solution.attach(mirad.load_scene(...)) first")
        return self.scene

    def attach(self, scene) -> "Solution":
        """Bind a loaded solution to its scene (checks the scene fingerprint)."""
        from .scene import load_scene

        scene = load_scene(scene)
        if scene.fingerprint != self.fingerprint:
            raise SolutionMismatch(
                f"the solution belongs to a scene with fingerprint {self.fingerprint}, but "
                f"'{scene.source or '<scene>'}' has {scene.fingerprint}; solve this scene again"
            )
        self.scene = scene
        return self

    # --- files -----------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the solution, chosen by suffix; atomic.

        .npz: everything, reloadable with ``mirad.load_solution``; .ply: mesh with vertex colours and
        float radiosity; .csv: per-triangle table (``mirad.export``); .exr: image from the scene's
        sensor (``mirad.render``, needs the scene), with a PNG beside it.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix == ".npz":
            atomic_write(path, self._write_npz)
        elif suffix == ".ply":
            from .export import write_ply

            write_ply(self, path)
        elif suffix == ".csv":
            from .export import write_table

            write_table(self, path)
        elif suffix == ".exr":
            from .display import render, write_image

            write_image(path, render(self._require_scene(), self))
        else:
            raise OutputError(f"cannot save a solution as '{path.suffix}' ({path}); use .npz, .ply, .csv or .exr")
        return path

    def _write_npz(self, handle) -> None:
        meta = {"format": FORMAT, "fingerprint": self.fingerprint, "shape_ids": self.shape_ids,
                "stats": self.stats}
        np.savez_compressed(handle, __meta__=np.frombuffer(json.dumps(meta, default=str).encode(), np.uint8),
                            **self._a)

    def summary(self) -> str:
        """One paragraph: elements, links, rays, time, estimated error."""
        s = self.stats
        sec = s["seconds"]
        return (f"{s['leaves']} elements ({s['elements']} in the hierarchy), {s['links']} links, "
                f"{s['rays']:,} rays; {sec['total']:.2f} s (refine {sec['refine']:.2f}, visibility "
                f"{sec['visibility']:.2f}, solve {sec['solve']:.2f}); estimated error "
                f"{100 * s['estimated_error']:.2f} % (tolerance {100 * s['settings']['tolerance']:.2g} %); "
                f"{s['solver']} solver, {s['solver_iterations']} iterations; "
                + (f"{s['clusters']} clusters of patches as sources; " if s.get("clusters") else "")
                + f"variant {s['variant']}.")


def load_solution(path, scene=None) -> Solution:
    """Load a solution saved as .npz; with ``scene``, check it belongs to that scene."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"solution file '{path}' does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["__meta__"]).decode())
            arrays = {k: data[k] for k in data.files if k != "__meta__"}
    except Exception as exc:
        raise SolutionMismatch(f"'{path}' is not a mirad solution file ({exc}); save one with sol.save('x.npz')") from None
    sol = Solution(arrays=arrays, stats=meta["stats"], shape_ids=meta["shape_ids"],
                   fingerprint=meta["fingerprint"])
    if scene is not None:
        sol.attach(scene)
    return sol


def display_colors(radiosity: np.ndarray) -> np.ndarray:
    """8-bit sRGB RGBA colours of radiance B/pi, exposed so the 99th percentile maps to white."""
    radiance = np.asarray(radiosity, dtype=np.float64) / np.pi
    if radiance.shape[1] == 1:
        radiance = np.repeat(radiance, 3, axis=1)
    scale = np.percentile(radiance.max(axis=1), 99) if len(radiance) else 1.0
    x = np.clip(radiance / (scale if scale > 0 else 1.0), 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    rgba = np.concatenate([np.round(srgb * 255), np.full((len(x), 1), 255)], axis=1)
    return rgba.astype(np.uint8)


def atomic_write(path, writer) -> None:
    """Call writer(binary handle) on a temporary file beside path, then rename it into place."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(f"cannot write '{path}': folder '{folder}' does not exist; create it first")
    if not os.access(folder, os.W_OK):
        raise OutputError(f"cannot write '{path}': folder '{folder}' is not writable; choose another output path")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=folder)
    try:
        with os.fdopen(fd, "wb") as handle:
            writer(handle)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
