"""The result of a solve: per-leaf, per-triangle and per-vertex radiosity, queries, stats, files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .arrays import LEAF_CORNER_UV, group_mean, group_sum, scene_diagonal
from .errors import OutputError, SettingsError, SolutionMismatch, warn
from .files import atomic_write

#: Format version of saved .npz solutions.
FORMAT = 1

#: Probes (``Solution.irradiance_at``): direct-light samples per point in the first round, the cap
#: on them (as ``Settings.samples_per_link``'s bound) and the relative tolerance when neither the
#: call nor the solve gives one.
PROBE_FIRST_SAMPLES = 64
PROBE_MAX_SAMPLES = 1 << 16
PROBE_TOLERANCE = 0.01
#: Probes aim their direct-light samples at this fraction of the tolerance (1/sqrt 2: up to 2x the
#: samples the pilot predicts, so that the round kept seldom misses the tolerance).
PROBE_MARGIN = 0.5 ** 0.5


#: Arrays every solution holds (keys of the saved .npz).
_REQUIRED = ("leaf_verts", "leaf_patch", "leaf_normal", "leaf_radiosity", "leaf_irradiance", "leaf_error",
             "patch_tri", "patch_side", "curve_center", "curve_axis", "curve_radius", "vertices", "faces",
             "triangle_area", "triangle_shape", "triangle_rho", "triangle_emission")



class Solution:
    """Radiosity solution of one scene (units: W/m^2; radiance = radiosity / pi).

    Built from arrays (:meth:`from_arrays`) or loaded from a file (:func:`load_solution`); every
    array is a read-only view through a documented property. Sizes: L leaf elements (the finest
    elements of the refined hierarchy, front and back sides), P patches (input triangles and
    the back sides of two-sided ones), T input triangles, V input vertices, S shapes, C channels
    (1 for a grey scene, else 3; a band scene's bands, named in ``stats["bands"]``).

    Attributes
    ----------
    shape_ids : list[str]             Mitsuba ids, in ``mi.Scene.shapes()`` order
    stats : dict                      elements, links, rays, seconds, estimated_error, features, variant
    fingerprint : str                 fingerprint of the scene it was solved for
    scene : mirad Scene or None       the scene, once attached
    """

    def __init__(self, *, arrays: dict, stats: dict, shape_ids: list, fingerprint: str, scene=None):
        missing = [k for k in _REQUIRED if k not in arrays]
        if missing:
            raise SolutionMismatch(f"solution arrays lack {', '.join(missing)}")
        self._arrays = dict(arrays)
        self.stats = stats
        self.shape_ids = list(shape_ids)
        self.fingerprint = fingerprint
        self.scene = scene

    # --- construction ---------------------------------------------------------------------
    @classmethod
    def from_arrays(cls, scene, *, leaf_vertices, leaf_patch, leaf_normal, leaf_radiosity, leaf_irradiance,
                    leaf_error, stats: dict, detail_leaves=None, leaf_detail=None,
                    leaf_error_share=None) -> "Solution":
        """A solution of ``scene`` (a mirad Scene) from per-leaf arrays.

        Parameters
        ----------
        leaf_vertices : (L, 3, 3) float, m        corners of the leaf elements
        leaf_patch : (L,) int                     patch of each leaf (index into ``scene.patch_tri``)
        leaf_normal : (L, 3) float                unit normal of each leaf's side
        leaf_radiosity, leaf_irradiance, leaf_error : (L, C) or (L, 1) float, W/m^2
            radiosity, irradiance and estimated absolute error of the radiosity per leaf
            (one channel is widened to the scene's C)
        stats : dict                              solve statistics (see ``Solution.stats``)
        leaf_error_share : (L, C) or (L, 1) float or None, W/m^2
            each leaf's share of its input triangle's estimated error (its leaves' independent
            errors partly cancel in the triangle's mean); None: ``leaf_error``
        detail_leaves : (D,) int or None          leaves with shadow-texture detail
        leaf_detail : (D, R, R, C) or (D, R, R, 1) float or None, W/m^2   their detail textures
        """
        channels = scene.channels

        def widen(x, axis=1):
            x = np.asarray(x)
            return np.repeat(x, channels, axis=axis) if x.shape[axis] == 1 else x

        arrays = {
            "leaf_verts": np.asarray(leaf_vertices, np.float64),
            "leaf_patch": np.asarray(leaf_patch).astype(np.int32),
            "leaf_normal": np.asarray(leaf_normal),
            "leaf_radiosity": widen(leaf_radiosity),
            "leaf_irradiance": widen(leaf_irradiance),
            "leaf_error": widen(leaf_error),
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
        if scene.diffuse_transmission:      # translucent leaves only: other solutions keep their arrays
            leaf = scene.tri_leaf[:, None]
            arrays["triangle_tau"] = np.where(leaf, scene.tri_transmittance, 0.0)
            arrays["back_tau"] = np.where(leaf, scene.back_transmittance, 0.0)
        if leaf_error_share is not None:
            arrays["leaf_error_share"] = widen(leaf_error_share)
        if detail_leaves is not None and len(detail_leaves):
            arrays["detail_leaf"] = np.asarray(detail_leaves, np.int32)
            arrays["leaf_detail"] = widen(leaf_detail, axis=3)
        if scene.band_names:                # a band scene (mirad.with_bands): outputs name their columns by band
            stats["bands"] = list(scene.band_names)
        return cls(arrays=arrays, stats=stats, shape_ids=scene.shape_ids,
                   fingerprint=scene.fingerprint, scene=scene)

    @classmethod
    def from_solve(cls, scene, prob, leaves, b_leaf, h_leaf, err_leaf, stats, detail=None) -> "Solution":
        """Compatibility for the solver cores: reads ``prob.elements.verts/patch`` and
        ``prob.patch_normal``; prefer :meth:`from_arrays`."""
        e = prob.elements
        patch = e.patch[leaves]
        rows, tex = detail if detail is not None else (None, None)
        return cls.from_arrays(scene, leaf_vertices=e.verts[leaves], leaf_patch=patch,
                               leaf_normal=prob.patch_normal[patch], leaf_radiosity=b_leaf,
                               leaf_irradiance=h_leaf, leaf_error=err_leaf, stats=stats,
                               detail_leaves=rows, leaf_detail=tex)

    # --- per-leaf data -----------------------------------------------------------------------
    @property
    def channels(self) -> int:
        """Number of colour channels C (1 for a grey scene, 3 for RGB)."""
        return self._arrays["leaf_radiosity"].shape[1]

    @property
    def leaf_vertices(self) -> np.ndarray:
        """(L, 3, 3) float, m: corners v0, v1, v2 of the leaf elements."""
        return self._arrays["leaf_verts"]

    @property
    def leaf_patch(self) -> np.ndarray:
        """(L,) int: patch of each leaf (index into ``patch_triangle``/``patch_side``)."""
        return self._arrays["leaf_patch"]

    @property
    def leaf_normal(self) -> np.ndarray:
        """(L, 3) float: unit normal of the side each leaf belongs to."""
        return self._arrays["leaf_normal"]

    @property
    def leaf_radiosity(self) -> np.ndarray:
        """(L, C) float, W/m^2: radiosity of the leaf elements."""
        return self._arrays["leaf_radiosity"]

    @property
    def leaf_irradiance(self) -> np.ndarray:
        """(L, C) float, W/m^2: irradiance of the leaf elements."""
        return self._arrays["leaf_irradiance"]

    @property
    def leaf_error(self) -> np.ndarray:
        """(L, C) float, W/m^2: estimated absolute error of ``leaf_radiosity`` (on the
        hierarchical core each channel's in proportion to the leaf's light in it: the errors
        are of transfers, which carry every channel alike)."""
        return self._arrays["leaf_error"]

    @property
    def leaf_error_share(self) -> np.ndarray:
        """(L, C) float, W/m^2: each leaf's share of its input triangle's estimated error, whose
        area mean over the triangle is ``triangle_error`` (the leaves' independent errors add in
        quadrature over the triangle); ``leaf_error`` where the solve gave no shares."""
        return self._arrays.get("leaf_error_share", self.leaf_error)

    @property
    def leaf_area(self) -> np.ndarray:
        """(L,) float, m^2: area of the leaf elements."""
        v = self._arrays["leaf_verts"]
        return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)

    @property
    def leaf_triangle(self) -> np.ndarray:
        """(L,) int: input triangle each leaf lies on."""
        return self._arrays["patch_tri"][self._arrays["leaf_patch"]]

    @property
    def leaf_side(self) -> np.ndarray:
        """(L,) int8: 0 front side, 1 back side (two-sided BSDFs)."""
        return self._arrays["patch_side"][self._arrays["leaf_patch"]]

    @property
    def leaf_shape(self) -> np.ndarray:
        """(L,) int: shape of each leaf (index into ``shape_ids``)."""
        return self._arrays["triangle_shape"][self.leaf_triangle]

    @property
    def detail_leaves(self) -> np.ndarray:
        """(D,) int: the leaves that carry shadow-texture detail (empty without textures)."""
        return self._arrays.get("detail_leaf", np.zeros(0, np.int32))

    @property
    def leaf_detail(self) -> np.ndarray:
        """(D, R, R, C) float, W/m^2: shadow-texture detail of ``detail_leaves`` (texel (i, j) at
        leaf parameters u = (i + 0.5) / R, v = (j + 0.5) / R); (0, 0, 0, C) without textures."""
        return self._arrays.get("leaf_detail", np.zeros((0, 0, 0, self.channels)))

    def detail_at(self, leaf, uv) -> np.ndarray:
        """(P, C) shadow-texture detail of radiosity, W/m^2, at points with parameters uv (P, 2)
        on leaves ``leaf`` (P,) (y = v0 + u (v1 - v0) + v (v2 - v0) over ``leaf_vertices``);
        zero on leaves without texture links. Its mean over each leaf is zero: the leaf's
        radiosity already holds the texture links' mean transfer."""
        leaf = np.asarray(leaf, np.int64)
        out = np.zeros((len(leaf), self.channels))
        rows = self.detail_leaves
        if not len(rows) or not len(leaf):
            return out
        slot = np.full(len(self.leaf_radiosity), -1, np.int64)
        slot[rows] = np.arange(len(rows))
        k = slot[leaf]
        has = k >= 0
        if has.any():
            from .shadows import bilinear

            out[has] = bilinear(self._arrays["leaf_detail"], k[has], np.asarray(uv)[has])
        return out

    def radiosity_at(self, leaf, uv) -> np.ndarray:
        """(P, C) radiosity at points (leaf (P,), uv (P, 2)): the leaf's value plus its shadow
        detail (``detail_at``), W/m^2."""
        return self.leaf_radiosity[np.asarray(leaf, np.int64)] + self.detail_at(leaf, uv)

    # --- patches and input mesh ---------------------------------------------------------------
    @property
    def patch_triangle(self) -> np.ndarray:
        """(P,) int: input triangle of each patch."""
        return self._arrays["patch_tri"]

    @property
    def patch_side(self) -> np.ndarray:
        """(P,) int8: side of each patch, 0 front, 1 back."""
        return self._arrays["patch_side"]

    @property
    def vertices(self) -> np.ndarray:
        """(V, 3) float, m: mesh vertices of all shapes (world space)."""
        return self._arrays["vertices"]

    @property
    def faces(self) -> np.ndarray:
        """(T, 3) int: vertex indices of the input triangles."""
        return self._arrays["faces"]

    @property
    def vertex_uv(self) -> np.ndarray | None:
        """(V, 2) float texture coordinates (NaN on shapes without UVs), or None."""
        return self._arrays.get("vertex_uv")

    @property
    def triangle_area(self) -> np.ndarray:
        """(T,) float, m^2: area of the input triangles."""
        return self._arrays["triangle_area"]

    @property
    def triangle_shape(self) -> np.ndarray:
        """(T,) int: shape of each input triangle (index into ``shape_ids``)."""
        return self._arrays["triangle_shape"]

    @property
    def triangle_in_shape(self) -> np.ndarray:
        """(T,) int: index of each input triangle within its shape (0-based, the shape's face order)."""
        shape = np.asarray(self.triangle_shape, np.int64)
        order = np.argsort(shape, kind="stable")
        first = np.searchsorted(shape[order], shape[order], side="left")
        out = np.empty(len(shape), np.int64)
        out[order] = np.arange(len(shape)) - first
        return out

    @property
    def triangle_reflectance(self) -> np.ndarray:
        """(T, C) float: diffuse reflectance (albedo) of the front side of each triangle."""
        return self._arrays["triangle_rho"]

    @property
    def back_reflectance(self) -> np.ndarray:
        """(T, C) float: reflectance of the back side (zero where one-sided)."""
        back = self._arrays.get("back_rho")
        return np.zeros_like(self.triangle_reflectance) if back is None else back

    @property
    def triangle_transmittance(self) -> np.ndarray:
        """(T, C) float: diffuse transmittance tau of the front side of each triangle, the fraction of
        its irradiance a translucent leaf (``scene.tri_leaf``) hands to the other side; zero on every
        other surface (mirad's model absorbs what glass or a mask would let through)."""
        return self._transmittance("triangle_tau", "tri_transmittance")

    @property
    def back_transmittance(self) -> np.ndarray:
        """(T, C) float: diffuse transmittance of the back side (zero where not a translucent leaf)."""
        return self._transmittance("back_tau", "back_transmittance")

    def _transmittance(self, key: str, scene_key: str) -> np.ndarray:
        if key in self._arrays:
            return self._arrays[key]
        scene = self.scene           # a solution saved before it kept tau: its scene, once attached
        if scene is not None and scene.diffuse_transmission:
            return np.where(scene.tri_leaf[:, None], getattr(scene, scene_key), 0.0)
        return np.zeros_like(self.triangle_reflectance)

    @property
    def triangle_emission(self) -> np.ndarray:
        """(T, C) float, W/m^2: emitted radiosity E of the front side of each triangle."""
        return self._arrays["triangle_emission"]

    @property
    def triangle_curve(self) -> tuple:
        """(centre (T, 3), axis (T, 3), radius (T,)) of the analytic surface under each triangle
        (radius 0 on flat shapes), m: mirad projects points of spheres and cylinders onto it."""
        a = self._arrays
        return a["curve_center"], a["curve_axis"], a["curve_radius"]

    # --- per triangle / shape / vertex --------------------------------------------------------
    def _per_patch(self, values: np.ndarray) -> np.ndarray:
        return group_mean(self.leaf_patch, values, len(self.patch_triangle), weights=self.leaf_area)

    def _side(self, per_patch: np.ndarray, side: int) -> np.ndarray:
        out = np.zeros((len(self.faces), per_patch.shape[1]))
        mask = self.patch_side == side
        out[self.patch_triangle[mask]] = per_patch[mask]
        return out

    @property
    def triangle_radiosity(self) -> np.ndarray:
        """(T, C) float, W/m^2: front-side radiosity per input triangle (area-weighted over its leaves)."""
        return self._side(self._per_patch(self.leaf_radiosity), 0)

    @property
    def triangle_irradiance(self) -> np.ndarray:
        """(T, C) float, W/m^2: front-side irradiance per input triangle."""
        return self._side(self._per_patch(self.leaf_irradiance), 0)

    @property
    def triangle_error(self) -> np.ndarray:
        """(T, C) float, W/m^2: estimated absolute error of ``triangle_radiosity``: the area mean of
        its leaves' shares of it (independent errors of the leaves add in quadrature over the
        triangle; ``leaf_error`` is each leaf's own)."""
        return self._side(self._per_patch(self.leaf_error_share), 0)

    @property
    def back_radiosity(self) -> np.ndarray:
        """(T, C) float, W/m^2: back-side radiosity (zero where one-sided)."""
        return self._side(self._per_patch(self.leaf_radiosity), 1)

    @property
    def back_irradiance(self) -> np.ndarray:
        """(T, C) float, W/m^2: back-side irradiance (zero where one-sided)."""
        return self._side(self._per_patch(self.leaf_irradiance), 1)

    @property
    def vertex_radiosity(self) -> np.ndarray:
        """(V, C) float, W/m^2: area-weighted mean of the radiosity of the triangles around each
        vertex, with the shadow-texture detail at the vertex where a leaf has one."""
        n_vert = len(self.vertices)
        idx = self.faces.ravel()
        w = np.repeat(self.triangle_area, 3)
        total = group_sum(idx, np.repeat(self.triangle_radiosity, 3, axis=0), n_vert, weights=w)
        total += self.vertex_detail
        return total / np.maximum(np.bincount(idx, weights=w, minlength=n_vert), 1e-300)[:, None]

    @property
    def vertex_detail(self) -> np.ndarray:
        """(V, C) float, W/m^2 times m^2: triangle-area-weighted sum of the shadow-texture detail
        at each input vertex (for each front-side textured leaf with a corner on a vertex of its
        triangle, the detail there times the triangle's area); zero at vertices without one.
        ``vertex_radiosity`` divides it, with the triangles' radiosity, by the area around the vertex."""
        n_vert = len(self.vertices)
        rows = self.detail_leaves
        out = np.zeros((n_vert, self.channels))
        rows = rows[self.leaf_side[rows] == 0]
        if not len(rows):
            return out
        tri = self.leaf_triangle[rows]
        corners = self.leaf_vertices[rows]                                  # (T, 3 corners, 3)
        tri_verts = self.vertices[self.faces[tri]]                          # (T, 3 vertices, 3)
        diag = scene_diagonal(self.vertices)
        dist = np.linalg.norm(corners[:, :, None] - tri_verts[:, None], axis=-1)
        t, k, j = np.nonzero(dist < 1e-9 * diag)
        detail = self.detail_at(rows[t], LEAF_CORNER_UV[k])
        np.add.at(out, self.faces[tri[t], j], self.triangle_area[tri[t], None] * detail)
        return out

    def shape_radiosity(self, shape_id: str) -> np.ndarray:
        """(C,) area-weighted mean radiosity over the shape's front side, W/m^2."""
        index = self.shape_index(shape_id)
        mask = self.triangle_shape == index
        area = self.triangle_area[mask]
        return (self.triangle_radiosity[mask] * area[:, None]).sum(0) / area.sum()

    def shape_index(self, shape_id: str) -> int:
        """Index of a shape id in ``shape_ids``; KeyError listing the ids if there is none."""
        try:
            return self.shape_ids.index(shape_id)
        except ValueError:
            raise KeyError(f"no shape with id {shape_id!r}; ids are {self.shape_ids}") from None

    # --- queries ---------------------------------------------------------------------------------
    def irradiance_at(self, points, normals, *, rays: int = 4, seed: int = 0, tolerance: float | None = None,
                      max_samples: int = PROBE_MAX_SAMPLES, with_error: bool = False, progress=None):
        """Irradiance (P, C), W/m^2, at points (P, 3) facing normals (P, 3); with ``with_error``,
        (irradiance, standard error (P, C), W/m^2).

        A local gather over every leaf element of the solution (Lambert form factor to the
        leaf times its radiosity, with ``rays`` shadow rays per leaf), plus the direct light
        of point, spot, directional and environment emitters (``emitters.direct_irradiance``:
        Mitsuba's own ``Emitter.sample_direction`` for point, spot and directional lights, the
        receiver's cosine for skies) and one shadow ray per sample.

        The direct light starts from a pilot of ``PROBE_FIRST_SAMPLES`` (64) samples per point.
        Each point it finds noisy gets fresh samples (another seed) at the count its pilot predicts
        for ``tolerance`` (a power of 4 times 64), and rounds of 4x or more while its relative
        standard error stays above ``tolerance`` in some channel (one vectorised launch per count
        over the points that need it), up to ``max_samples``. The estimate kept never chose its own
        count, so the stopping rule adds no bias. The standard error combines both parts in
        quadrature: the direct light's sample standard deviation over sqrt(samples) and the
        gather's visibility noise (``visibility.gather_at_points``; zero where every leaf is fully
        visible or fully hidden, and with ``rays=1``). It is the noise of this estimate around the
        solution's one-bounce irradiance, not the solution's own error (``leaf_error``). Points
        left above the tolerance are counted and named in one warning: raise ``max_samples`` where
        the direct light stopped at it, ``rays`` where the gather's noise alone exceeds it.
        Point, spot and directional lights are sampled exactly (zero error at 64 samples), and a
        scene with area lights only has no direct part: both give what a fixed 64 samples gave.

        Parameters
        ----------
        points, normals : (P, 3) float          points (m, the user's frame) and the directions they face
        rays : int, default 4                    shadow rays per leaf and point in the gather
        seed : int, default 0                    same seed, same points: bitwise same result
        tolerance : float or None                relative standard error per point and channel, in (0, 1);
            default the solution's own tolerance (``stats["settings"]["tolerance"]``), else 0.01
        max_samples : int, default 65536         cap on the direct-light samples per point, 1 to 65536
            (64 or less: a fixed count, no error control)
        with_error : bool, default False         also return the standard error
        progress : callable or None              given the number of points gathered after each launch
            (e.g. a tqdm bar's ``update``)

        Returns
        -------
        (P, C) float, W/m^2, or with ``with_error`` a tuple of two (P, C) float arrays, W/m^2
        (C = 3 where the scene has point, spot, directional or environment emitters)

        >>> h, err = sol.irradiance_at([[0, 0, 0]], [[0, 0, 1]], with_error=True)   # doctest: +SKIP
        >>> bool(np.all(err <= 0.01 * h))                                            # doctest: +SKIP
        True
        """
        from .visibility import Geometry, gather_at_points

        scene = self.require_scene()
        if (self.stats or {}).get("periodic"):
            raise SettingsError("irradiance_at (probes) does not wrap its rays around the periodic box of this "
                                f"solution ({self.stats['periodic'].get('box')}) yet, so it would miss the light of "
                                "the neighbouring plots; read the per-triangle or per-organ irradiance of the "
                                "solution instead (export --organs), or solve without periodic to probe")
        tolerance = self._probe_tolerance(tolerance)
        if (isinstance(max_samples, bool) or not isinstance(max_samples, (int, np.integer))
                or not 1 <= max_samples <= PROBE_MAX_SAMPLES):
            raise SettingsError(f"max_samples={max_samples!r} must be an integer from 1 to {PROBE_MAX_SAMPLES} "
                                f"(direct-light samples per probe; e.g. {PROBE_MAX_SAMPLES})")
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        normals = np.atleast_2d(np.asarray(normals, dtype=np.float64))
        if points.shape[1:] != (3,) or normals.shape != points.shape:
            raise ValueError(f"points and normals must both be (P, 3) arrays; got {points.shape} and {normals.shape}")
        if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
            raise ValueError("points and normals must be finite")
        # points are in the user's coordinates; a scene far from the origin is solved moved
        points = scene.to_internal(points)
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        if np.any(length == 0):
            raise ValueError("every normal must be non-zero")
        normals = normals / length
        tri = self.leaf_triangle
        center, axis, radius = self.triangle_curve
        geo = Geometry.upload(self.leaf_vertices, self.leaf_normal, center[tri], axis[tri], radius[tri],
                              scene.diagonal)
        # the gather's noise costs one more launch of its rays: only when asked for or needed (the
        # direct light's samples are raised against the tolerance left beside it)
        gathered = gather_at_points(scene.mi_scene, points, normals, geo, self.leaf_radiosity, rays=rays,
                                    seed=seed, progress=progress, with_error=with_error or bool(scene.light_emitters))
        h, err = gathered if isinstance(gathered, tuple) else (gathered, None)
        if scene.light_emitters:
            h, err = self._probe_direct(scene, points, normals, h, err, tolerance=tolerance,
                                        max_samples=max_samples, seed=seed, rays=rays)
        return (h, err) if with_error else h

    def _probe_tolerance(self, tolerance) -> float:
        """The probes' relative tolerance: given, else the solve's, else 0.01 (SettingsError if outside (0, 1))."""
        if tolerance is None:
            tolerance = (self.stats.get("settings") or {}).get("tolerance") or PROBE_TOLERANCE
        if (isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating, np.integer))
                or not 0 < tolerance < 1):
            raise SettingsError(f"tolerance={tolerance!r} must be a relative standard error between 0 and 1 "
                                f"(exclusive), e.g. {PROBE_TOLERANCE}")
        return float(tolerance)

    @staticmethod
    def _probe_direct(scene, points, normals, h_gather, err_gather, *, tolerance, max_samples, seed, rays):
        """Direct light at probes (P, 3) and its standard error, W/m^2, added to the gather's (``irradiance_at``)."""
        from .emitters import direct_irradiance

        n_pts = len(points)
        # a tiny triangle around each point stands in for the point
        r = 1e-7 * scene.diagonal
        t1 = np.cross(normals, np.where(np.abs(normals[:, :1]) < 0.9, [[1, 0, 0]], [[0, 1, 0]]))
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(normals, t1)
        tri_pts = np.stack([points + r * t1, points + r * t2, points - r * (t1 + t2)], 1)
        zero = np.zeros((n_pts, 3))
        curve = (zero, zero, np.zeros(n_pts))
        keys = np.arange(n_pts)
        samples = np.full(n_pts, min(PROBE_FIRST_SAMPLES, max_samples), np.int64)
        hd, ed, _ = direct_irradiance(scene, tri_pts, normals, curve, samples=int(samples[0]), seed=seed,
                                      keys=keys, with_error=True)
        var_gather = err_gather * err_gather
        # the gather's noise is fixed by ``rays``: more direct samples cannot help where it alone is above
        gather_over = np.any(err_gather > tolerance * (h_gather + hd), axis=1)

        def above(idx):
            h = h_gather[idx] + hd[idx]
            return np.any(np.sqrt(var_gather[idx] + ed[idx] * ed[idx]) > tolerance * h, axis=1)

        # The first round is a pilot: every point whose direct light is sampled (non-zero error; point,
        # spot and directional lights are exact) and below the cap gets at least one more round of
        # fresh samples (another seed) at the count its pilot predicts: the estimate kept never chose
        # its own count, which would bias it (a point whose samples came out high looks converged
        # sooner). A round still above the tolerance predicts the next one, x4 at least.
        todo = np.flatnonzero(~gather_over & np.any(ed > 0, axis=1) & (samples < max_samples))
        rounds = 0
        while len(todo):
            # aim at PROBE_MARGIN x the tolerance, so that the round kept seldom fails it (a failed
            # round replaced by the next would bias the points whose samples came out low)
            allowed = np.square(PROBE_MARGIN * tolerance * (h_gather[todo] + hd[todo])) - var_gather[todo]
            ratio = np.divide(np.square(ed[todo]), allowed, out=np.full(allowed.shape, np.inf), where=allowed > 0)
            grow = np.maximum(np.max(ratio, axis=1), 1.0 if rounds == 0 else 4.0)
            steps = np.ceil(np.minimum(np.log(grow) / np.log(4.0), 16.0) - 1e-9)
            new = np.minimum(samples[todo] * 4.0 ** steps, max_samples).astype(np.int64)
            keep = (new > samples[todo]) | (rounds == 0)
            todo, new = todo[keep], new[keep]
            if not len(todo):
                break
            rounds += 1
            round_seed = (seed + 0x632BE5AB * rounds) % (1 << 32)
            for count in np.unique(new):          # one launch per count (powers of 4), over all its points
                idx = todo[new == count]
                hd[idx], ed[idx], _ = direct_irradiance(scene, tri_pts[idx], normals[idx], [c[idx] for c in curve],
                                                        samples=int(count), seed=round_seed, keys=keys[idx],
                                                        with_error=True)
            samples[todo] = new
            todo = todo[above(todo)]
        h = h_gather + hd
        err = np.sqrt(var_gather + ed * ed)
        over = np.flatnonzero(np.any(err > tolerance * h, axis=1))
        if len(over):
            capped = over[samples[over] >= max_samples]
            noisy = np.setdiff1d(over, capped)
            shown = ", ".join(map(str, over[:10])) + (f" and {len(over) - 10} more" if len(over) > 10 else "")
            why = []
            if len(capped):
                why.append(f"{len(capped)} reached max_samples={max_samples} direct-light samples")
            if len(noisy):
                why.append(f"{len(noisy)} have more gather noise than that with rays={rays} (give more rays)")
            warn(f"{len(over)} of {n_pts} probes stay above the relative standard error tolerance "
                 f"{tolerance:g} (probes {shown}): {'; '.join(why)}; their error is reported, "
                 "not hidden")
        return h, err

    def require_scene(self):
        """The attached mirad Scene; SolutionMismatch with the fix if none is attached."""
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

            write_image(path, render(self.require_scene(), self))
        else:
            raise OutputError(f"cannot save a solution as '{path.suffix}' ({path}); use .npz, .ply, .csv or .exr")
        return path

    def _write_npz(self, handle) -> None:
        meta = {"format": FORMAT, "fingerprint": self.fingerprint, "shape_ids": self.shape_ids,
                "stats": self.stats}
        np.savez_compressed(handle, __meta__=np.frombuffer(json.dumps(meta, default=str).encode(), np.uint8),
                            **self._arrays)

    def summary(self) -> str:
        """One paragraph: elements, links, rays, time per phase, estimated error."""
        s = self.stats
        sec = s.get("seconds", {})
        phases = ", ".join(f"{k} {v:.2f}" for k, v in sec.items() if k != "total" and isinstance(v, (int, float)))
        norm = estimate_norm(s)
        return (f"{s.get('leaves', '?')} elements ({s.get('elements', '?')} in the hierarchy), "
                f"{s.get('links', '?')} links, {s.get('rays', 0):,} rays; {sec.get('total', 0.0):.2f} s"
                + (f" ({phases})" if phases else "")
                + f"; estimated error {100 * s['estimated_error']:.2f} % of {norm} (tolerance "
                f"{100 * s['settings']['tolerance']:.2g} %); "
                + (f"{s['solver']} solver, {s.get('solver_iterations', '?')} iterations; " if "solver" in s else "")
                + (f"{s['clusters']} clusters of patches as sources; " if s.get("clusters") else "")
                + f"variant {s.get('variant', '?')}.")


def estimate_norm(stats: dict) -> str:
    """What a solution's ``stats["estimated_error"]`` is relative to, in words: the hierarchical
    core's estimate is of the irradiance, "mean(H)", the legacy core's of the reflected radiosity,
    "mean(B - E)"; "over" the shapes ``error_shapes`` named, where it was given."""
    norm = "mean(B - E)" if stats.get("core") == "legacy" else "mean(H)"
    shapes = stats.get("error_shapes")
    if shapes:
        norm += " over " + ", ".join(shapes[:6]) + (f" and {len(shapes) - 6} more shapes" if len(shapes) > 6 else "")
    return norm


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
