"""The Dr.Jit shading lookup: from a surface point to the leaf element under it.

The shading of a point is the radiosity of the leaf element that contains it, as
radiance B / pi (flat), or the same values interpolated between the element
corners (smooth). Points are located with Mitsuba itself: the leaves of the
solution are uploaded once as one triangle mesh per side (front, back) in small
*locator* scenes, and a short ray along the surface normal, from just above the
point down through it, hits the leaf that contains it. This works for every
shape the same way: meshes, merged meshes (an ``mi.Scene`` loaded with
``optimize=True``), and analytic shapes whose true surface lies slightly off
their tessellation (the ray runs along the true normal, which is the radial
projection mirad uses for spheres and cylinders). Everything stays in Dr.Jit:
no loop over pixels, elements or links.

:func:`view_class` is a Mitsuba integrator that shows a given solution (``display.render``);
the ``radiosity`` plugin (``integrator.py``) extends it with solving on first use.
"""

from __future__ import annotations

import warnings

import numpy as np

from .arrays import LEAF_CORNER_UV, group_mean, scene_diagonal, to_float, to_uint
from .errors import SettingsError
from .scene import load_scene

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

#: Locator rays start this fraction of the scene diagonal above the surface point.
LOCATE_OFFSET = 1e-4
#: Leaf slot of leaves without shadow-texture detail.
NO_DETAIL = 0xFFFFFFFF
#: Extra search depth below curved surfaces, relative to their radius (tessellation sagitta).
CURVED_DEPTH = 0.05
#: Direct-light samples of sky and point emitters per final-gather pixel point.
PIXEL_DIRECT_SAMPLES = 64


def _leaf_mesh(name: str, verts: np.ndarray):
    """A Mitsuba mesh whose face i is leaf i (verts (L, 3, 3) float)."""
    count = len(verts)
    mesh = mi.Mesh(name, 3 * count, count)
    params = mi.traverse(mesh)
    params["vertex_positions"] = to_float(verts.reshape(-1))
    params["faces"] = to_uint(np.arange(3 * count))
    params.update()
    return mi.load_dict({"type": "scene", "leaves": mesh})


def corner_values(solution, values: np.ndarray) -> np.ndarray:
    """(L, 3, C) per-corner values of every leaf for smooth display.

    Corners that coincide (same shape, side and position, and the same normal on flat shapes)
    get the area-weighted mean of the leaf ``values`` around them: (L, C) one value per leaf,
    or (L, 3, C) one per leaf corner.
    """
    values = np.asarray(values)
    if values.ndim == 2:
        values = np.repeat(values[:, None], 3, axis=1)
    verts = solution.leaf_vertices
    n_leaf = len(verts)
    tri = solution.leaf_triangle
    shape = solution.leaf_shape
    side = solution.leaf_side
    curved = solution.triangle_curve[2][tri] > 0
    diag = scene_diagonal(solution.vertices)
    pos = np.round(verts.reshape(-1, 3) / (1e-6 * diag)).astype(np.int64)
    nrm = np.round(np.repeat(solution.leaf_normal, 3, axis=0) * 1e3).astype(np.int64)
    nrm[np.repeat(curved, 3)] = 0
    key = np.column_stack([np.repeat(shape, 3), np.repeat(side, 3), pos, nrm])
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    weight = np.repeat(solution.leaf_area, 3)
    n_key = inverse.max() + 1 if len(inverse) else 0
    c_count = values.shape[2]
    mean = group_mean(inverse, values.reshape(-1, c_count), n_key, weights=weight)
    return mean[inverse].reshape(n_leaf, 3, c_count)


class Shading:
    """Solution data resident in Dr.Jit, and the point-to-leaf lookup.

    Parameters
    ----------
    solution : Solution with its scene attached (``solution.scene``)
    """

    def __init__(self, solution):
        scene = solution.require_scene()
        self.solution = solution
        self.scene = scene
        b = np.asarray(solution.leaf_radiosity, dtype=np.float64)
        if b.shape[1] == 1:
            b = np.repeat(b, 3, axis=1)
        side = solution.leaf_side
        tri = solution.leaf_triangle
        self.n_leaf = len(b)
        self.leaf_tri = tri
        self.leaf_side = side
        # per-side locator scenes and their leaf numbering
        self.locators = []
        self.rows = []
        # Each leaf is lifted a quarter of the lookup offset along its own normal, so leaves of
        # different shapes that coincide (a box standing on the floor: its bottom face and the
        # floor under it) are apart and the downward lookup ray meets its own side's leaf first.
        lift = 0.25 * LOCATE_OFFSET * scene.diagonal
        lifted = solution.leaf_vertices + lift * solution.leaf_normal[:, None, :]
        for s in (0, 1):
            rows = np.flatnonzero(side == s)
            self.rows.append(rows)
            self.locators.append(_leaf_mesh(f"leaves_{s}", lifted[rows]) if len(rows) else None)
        self.row_dr = [to_uint(r) if len(r) else None for r in self.rows]
        # values per leaf (flat) and per leaf corner (smooth), radiance = B / pi
        self.flat = [to_float(b[:, c] / np.pi) for c in range(3)]
        # a leaf with shadow-texture detail brings its value at each corner, not its mean,
        # so the smooth leaves around a textured one meet its shadow instead of its average
        at_corner = np.repeat(b[:, None], 3, axis=1)
        rows = solution.detail_leaves
        for k, uv in enumerate(LEAF_CORNER_UV):
            d = solution.detail_at(rows, np.tile(uv, (len(rows), 1)))
            at_corner[rows, k] += np.repeat(d, 3, axis=1) if d.shape[1] == 1 else d
        corners = corner_values(solution, np.maximum(at_corner, 0.0)) / np.pi    # (L, 3, 3)
        self.corners = [to_float(corners[:, :, c].reshape(-1)) for c in range(3)]
        # shadow-texture detail (solver shadow_textures): a slot per leaf, bilinear textures
        rows = solution.detail_leaves
        self.detail_res = 0
        if len(rows):
            detail = np.asarray(solution.leaf_detail, np.float64)           # (T, R, R, C)
            if detail.shape[3] == 1:
                detail = np.repeat(detail, 3, axis=3)
            slot = np.full(self.n_leaf, NO_DETAIL, np.uint32)
            slot[rows] = np.arange(len(rows), dtype=np.uint32)
            self.detail_slot = to_uint(slot)
            self.detail_res = detail.shape[1]
            self.detail = [to_float(detail[..., c].reshape(-1) / np.pi) for c in range(3)]
        # shape of each leaf, and Mitsuba shape pointer -> mirad shape index
        self.leaf_shape = to_uint(solution.leaf_shape)
        shapes = list(scene.mi_scene.shapes())
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        table = np.full(max(ids) + 1, 0xFFFFFFFF, np.uint32)
        table[ids] = np.arange(len(shapes), dtype=np.uint32)
        self.shape_table = to_uint(table)
        radius = np.zeros(len(shapes))
        np.maximum.at(radius, solution.triangle_shape, solution.triangle_curve[2])
        self.shape_depth = to_float(CURVED_DEPTH * radius)
        # fallback: mean radiance of each shape side
        area = solution.leaf_area
        shp = solution.leaf_shape
        means = np.stack([group_mean(shp[side == s], b[side == s], len(shapes), weights=area[side == s])
                          for s in (0, 1)])
        self.shape_mean = [[to_float(means[s, :, c] / np.pi) for c in range(3)] for s in (0, 1)]
        self.offset = LOCATE_OFFSET * scene.diagonal
        # per-leaf reflectance and emission of the side (final gather)
        rho_front = solution.triangle_reflectance[tri]
        self.leaf_rho = np.where(side[:, None] == 1, solution.back_reflectance[tri], rho_front)
        self.leaf_emission = np.where(side[:, None] == 1, 0.0, solution.triangle_emission[tri])

    # --- lookup ------------------------------------------------------------------------------
    def shape_index(self, shape_ptr) -> "mi.UInt32":
        """mirad shape index of Mitsuba shape pointers (0xFFFFFFFF where none)."""
        reg = dr.reinterpret_array(mi.UInt32, shape_ptr)
        n = dr.width(self.shape_table)
        return dr.gather(mi.UInt32, self.shape_table, dr.minimum(reg, n - 1), reg < n)

    def locate(self, p, n, back, shape, active):
        """Leaf under surface points.

        Parameters
        ----------
        p, n : mi.Point3f, mi.Vector3f   points and their front (geometric) normals
        back : mi.Bool                   True where the back side is seen
        shape : mi.UInt32                mirad shape index of each point
        active : mi.Bool

        Returns
        -------
        (leaf mi.UInt32, barycentric mi.Point2f, found mi.Bool)
        """
        depth = dr.gather(mi.Float, self.shape_depth, dr.minimum(shape, dr.width(self.shape_depth) - 1))
        leaf = dr.zeros(mi.UInt32, dr.width(p))
        uv = dr.zeros(mi.Point2f, dr.width(p))
        found = dr.zeros(mi.Bool, dr.width(p))
        # each ray query on another mi.Scene gets a kernel of its own: OptiX (cuda_ad_rgb) refuses
        # two scenes' queries in one kernel and drops the second (the plugin rendered black there)
        dr.eval(p, n, back, shape, active, depth)
        for s, locator in enumerate(self.locators):
            if locator is None:
                continue
            side_active = active & (back if s == 1 else ~back)
            for sign in (1.0, -1.0):  # from above, then (for the rare miss) from below
                todo = side_active & ~found
                ray = mi.Ray3f(p + n * (sign * self.offset), n * (-sign))
                ray.maxt = 2 * self.offset + depth
                pi = locator.ray_intersect_preliminary(ray, todo)
                hit = todo & pi.is_valid()
                row = dr.gather(mi.UInt32, self.row_dr[s], pi.prim_index, hit)
                ok = hit & (dr.gather(mi.UInt32, self.leaf_shape, row, hit) == shape)
                leaf = dr.select(ok, row, leaf)
                uv = dr.select(ok, pi.prim_uv, uv)
                found |= ok
                dr.eval(leaf, uv, found)
        return leaf, uv, found

    def radiance(self, si, ray_d, active, *, smooth: bool):
        """Displayed radiance (Color3f) at surface interactions seen along ray_d."""
        shape = self.shape_index(si.shape)
        back = dr.dot(si.n, ray_d) > 0
        leaf, uv, found = self.locate(si.p, si.n, back, shape, active)
        vals = [dr.gather(mi.Float, ch, leaf, found) for ch in self.flat]
        textured = dr.zeros(mi.Bool, dr.width(leaf))
        if self.detail_res:
            # a leaf with shadow textures shows its own variation (flat value + texture detail),
            # which interpolating between corners would count a second time
            detail, textured = self.detail_radiance(leaf, uv, found)
            vals = [v + d for v, d in zip(vals, detail)]
        if smooth:
            w0 = 1 - uv.x - uv.y
            base = leaf * 3
            vals = [dr.select(textured, v, w0 * dr.gather(mi.Float, ch, base, found)
                              + uv.x * dr.gather(mi.Float, ch, base + 1, found)
                              + uv.y * dr.gather(mi.Float, ch, base + 2, found))
                    for v, ch in zip(vals, self.corners)]
        # fallback (no leaf found: a crack or a shape without elements): the shape side's mean
        safe = dr.minimum(shape, dr.width(self.shape_mean[0][0]) - 1)
        out = []
        for c in range(3):
            mean = dr.select(back, dr.gather(mi.Float, self.shape_mean[1][c], safe, active),
                             dr.gather(mi.Float, self.shape_mean[0][c], safe, active))
            out.append(dr.select(found, vals[c], mean))
        return mi.Color3f(*out), leaf, found

    def detail_radiance(self, leaf, uv, found) -> list:
        """Shadow-texture detail of the radiance (3 mi.Float) at leaf parameters uv (bilinear,
        clamped at the texture border, as ``shadows.bilinear``; zero on leaves without), and
        which points lie on leaves with detail (mi.Bool)."""
        r = self.detail_res
        slot = dr.gather(mi.UInt32, self.detail_slot, leaf, found)
        has = found & (slot != NO_DETAIL)
        x = dr.clip(uv.x * r - 0.5, 0.0, r - 1.0)
        y = dr.clip(uv.y * r - 0.5, 0.0, r - 1.0)
        i0 = dr.minimum(mi.UInt32(dr.floor(x)), max(r - 2, 0))
        j0 = dr.minimum(mi.UInt32(dr.floor(y)), max(r - 2, 0))
        tx, ty = x - mi.Float(i0), y - mi.Float(j0)
        i1, j1 = dr.minimum(i0 + 1, r - 1), dr.minimum(j0 + 1, r - 1)
        base = slot * (r * r)
        out = []
        for ch in self.detail:
            g = lambda i, j, ch=ch: dr.gather(mi.Float, ch, base + i * r + j, has)  # noqa: E731
            out.append(dr.lerp(dr.lerp(g(i0, j0), g(i0, j1), ty), dr.lerp(g(i1, j0), g(i1, j1), ty), tx))
        return out, has

    def gathered_radiance(self, si, ray_d, leaf, found, active, *, rays: int, seed: int, quiet: bool = True):
        """One bounce of final gathering: (E + rho * H(x)) / pi with H gathered from all leaves
        (a progress bar over the hit points unless ``quiet``)."""
        back = dr.dot(si.n, ray_d) > 0
        n = dr.select(back, -si.n, si.n)
        valid = found & active
        dr.eval(si.p, n, leaf, valid)
        mask = np.asarray(valid.numpy(), dtype=bool)
        width = dr.width(si.p)
        pts = np.stack([np.asarray(si.p[i].numpy(), np.float64) for i in range(3)], 1)
        nrm = np.stack([np.asarray(n[i].numpy(), np.float64) for i in range(3)], 1)
        lf = np.asarray(leaf.numpy(), np.int64)
        result = np.zeros((width, 3))
        idx = np.flatnonzero(mask)
        if len(idx):
            with tqdm(total=len(idx), desc="final gather", unit="point", unit_scale=True, disable=quiet,
                      leave=False) as bar:
                # a pixel's gather is one sample of an image that averages many: the direct light of
                # sky and point emitters keeps a fixed budget per point (a probe's error control
                # would take up to 65,536 samples at each)
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", message=".*probes stay above the relative standard error tolerance")
                    h = self.solution.irradiance_at(pts[idx], nrm[idx], rays=rays, seed=seed, progress=bar.update,
                                                    max_samples=PIXEL_DIRECT_SAMPLES)
            if h.shape[1] == 1:
                h = np.repeat(h, 3, axis=1)
            result[idx] = (self.leaf_emission[lf[idx]] + self.leaf_rho[lf[idx]] * h) / np.pi
        return mi.Color3f(*[to_float(result[:, c]) for c in range(3)])




# ------------------------------------------------------------------------------------------
# An integrator that shows a given solution
# ------------------------------------------------------------------------------------------

#: At most this many scene objects keep a solution per integrator.
CACHE_SIZE = 4

_view_classes: dict = {}


def _make_view_class():
    """The view integrator class for the current Mitsuba variant (its base class is variant-specific)."""

    class RadiosityView(mi.SamplingIntegrator):
        """Shows the solution set for a scene (``set_solution``): each camera ray is traced by
        Mitsuba and the pixel shows the radiance B/pi of the leaf element under its hit point,
        smooth or flat, optionally with one bounce of final gathering. ``smooth``,
        ``final_gather``, ``gather_rays``, ``seed`` and ``quiet`` (no final-gather progress bar)
        are plain attributes."""

        def __init__(self, props=None):
            super().__init__(mi.Properties("radiosity") if props is None else props)
            self.smooth = True
            self.final_gather = False
            self.gather_rays = 4
            self.seed = 0
            self.quiet = True
            self._cache = {}  # id(mi.Scene) -> (mi.Scene, Shading)

        # --- the solution of a scene -----------------------------------------------------
        def set_solution(self, scene, solution) -> None:
            """Use ``solution`` (with its mirad Scene attached, whose ``mi_scene`` is ``scene``)."""
            if solution.scene is None or solution.scene.mi_scene is not scene:
                solution.attach(load_scene(scene))
            self._remember(scene, Shading(solution))

        def solution(self, scene):
            """The solution used for ``scene`` (an mi.Scene)."""
            return self._shading(scene).solution

        def _remember(self, scene, shading) -> None:
            self._cache[id(scene)] = (scene, shading)
            while len(self._cache) > CACHE_SIZE:
                self._cache.pop(next(iter(self._cache)))

        def _cached(self, scene):
            entry = self._cache.get(id(scene))
            return entry[1] if entry is not None and entry[0] is scene else None

        def _shading(self, scene):
            shading = self._cached(scene)
            if shading is None:
                raise SettingsError("no radiosity solution was set for this scene; call set_solution first")
            return shading

        # --- Mitsuba interface -------------------------------------------------------------
        def sample(self, scene, sampler, ray, medium=None, active=True):
            shading = self._shading(scene)
            active = mi.Bool(active)
            # ---------------- camera rays: Mitsuba's own geometry ----------------
            si = scene.ray_intersect(ray, active)
            valid = active & si.is_valid()
            # ---------------- the leaf under each hit point ----------------------
            color, leaf, found = shading.radiance(si, ray.d, valid, smooth=self.smooth)
            if self.final_gather:
                gathered = shading.gathered_radiance(si, ray.d, leaf, found, valid,
                                                     rays=self.gather_rays, seed=self.seed, quiet=self.quiet)
                color = dr.select(found, gathered, color)
            color = dr.select(valid, color, 0.0)
            # ---------------- rays that leave the scene --------------------------
            env = scene.environment()
            if env is not None and not self.hide_emitters:
                color = dr.select(valid, color, env.eval(si, active & ~valid))
            return color, valid, []

        def aov_names(self):
            return []

    return RadiosityView


def view_class():
    """The view integrator class of the current variant (subclass it for more behaviour)."""
    variant = mi.variant()
    if variant not in _view_classes:
        _view_classes[variant] = _make_view_class()
    return _view_classes[variant]
