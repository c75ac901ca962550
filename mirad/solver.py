"""Hierarchical radiosity driver: link, refine, solve, repeat (multigridding).

    patches -> initial links (facing pairs, vectorised) -> evaluate (visibility.py)
    loop over passes with a threshold halving towards eps_target:
        refinement waves: BF oracle on every link, split ends, evaluate new links
        solve the leaf system (linear.py), warm-started
    -> Solution

See settings.py for how ``tolerance`` becomes the oracle threshold.
"""

from __future__ import annotations

import os
import time

import numpy as np
import scipy.sparse as sp
from tqdm.auto import tqdm

from ._runtime import exact_arithmetic  # (and the LLVM set-up before mitsuba)
from .hierarchy import Elements, Links, facing, triangle_normals
from .linear import LeafSystem, solve_system
from .oracle import choose_splits, transfer_bounds
from .errors import warn
from .scene import Scene
from .settings import Settings
from .arrays import RAY_OFFSET
from .visibility import Geometry, evaluate_links

#: Corners closer than this fraction of the diagonal to a plane count as in the plane.
PLANE_EPS = 1e-6
#: Pairs tested per chunk during initial linking.
_LINK_CHUNK = 1 << 22


class Problem:
    """Arrays of one solve: the scene's patches, the element hierarchy and its links."""

    def __init__(self, scene: Scene, settings: Settings):
        self.scene = scene
        self.settings = settings
        self.channels = 1 if scene.grey else scene.channels
        tris = scene.patch_tri
        side = scene.patch_side
        verts = scene.tri_vertices[tris].copy()
        verts[side == 1] = verts[side == 1][:, ::-1]           # back sides: reversed winding
        self.patch_normal = triangle_normals(verts)
        self.patch_rho = scene.patch_rho[:, : self.channels]
        self.patch_emission = scene.patch_emission[:, : self.channels]
        self.patch_curve = (scene.curve_center[tris], scene.curve_axis[tris], scene.curve_radius[tris])
        self.elements = Elements.from_patches(verts)
        self.clusters = None
        if settings.clustering == "on" or (settings.clustering == "auto"
                                           and len(verts) > settings.cluster_threshold):
            self._add_clusters(verts)
        self.diagonal = scene.diagonal
        self.total_area = float(scene.tri_area.sum())
        tol = settings.tolerance
        self.min_area = max(settings.min_area, (tol * settings.min_area_factor) ** 2) * self.total_area
        self.links = Links()
        self.culler = None
        cull = settings.shaft_culling == "on" or (settings.shaft_culling == "auto" and settings.oracle == "bound")
        if cull and not np.any(scene.curve_radius > 0):
            from .shaft import ShaftCuller

            self.culler = ShaftCuller(scene.tri_vertices, scene.diagonal)
        self._rho_max = np.zeros(0)
        self.stream = 0
        self.b_max_below = np.zeros(len(self.elements))
        self.rays = 0
        self.direct = np.zeros((len(self.elements), self.channels))   # irradiance from point/sky lights
        self.direct_error = np.zeros_like(self.direct)                   # its standard error, W/m^2
        self.direct_samples = np.zeros(len(self.elements), np.int64)     # points it was estimated from
        self.timing = {"link": 0.0, "refine": 0.0, "visibility": 0.0, "classify": 0.0, "solve": 0.0,
                       "direct": 0.0}
        self.classified = {"visible": 0, "blocked": 0, "tested": 0}
        self.max_links = settings.max_links or _memory_max_links()
        if settings.shadow_textures:
            self.timing["textures"] = 0.0
        self.textures = []           # (TextureLinks, ff_std, error share) of textured links, per wave
        self._executor = None   # Dask evaluator (distributed.py), made on the first wave

    def _add_clusters(self, verts: np.ndarray) -> None:
        """Bounding-volume hierarchy over the patches, appended as source-only elements."""
        from .cluster import ClusterGeometry, build_tree, cluster_boxes

        area = self.elements.area
        tree = build_tree(verts.mean(axis=1), area)
        if len(tree) == 0:
            return
        self.elements.add_clusters(tree)
        self.clusters = ClusterGeometry.upload(tree, area)
        self.cluster_lo, self.cluster_hi = cluster_boxes(tree, verts)
        # clusters holding an emitter are always opened (area sampling would rarely hit it)
        emits = np.concatenate([self.patch_emission.max(axis=1) > 0, np.zeros(len(tree), bool)])
        p = len(verts)
        for lev in range(int(tree.level.max()), -1, -1):
            nodes = np.flatnonzero(tree.level == lev)
            emits[p + nodes] = emits[tree.children[nodes, 0]] | emits[tree.children[nodes, 1]]
        self.cluster_emits = emits[p:]
        self.cluster_centre = 0.5 * (self.cluster_lo + self.cluster_hi)
        self.cluster_radius = 0.5 * np.linalg.norm(self.cluster_hi - self.cluster_lo, axis=1)

    def bounding_spheres(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre (M, 3) and radius (M,) of spheres around elements or clusters ids."""
        e = self.elements
        centre = e.verts[ids].mean(axis=1)
        radius = np.linalg.norm(e.verts[ids] - centre[:, None], axis=2).max(axis=1)
        cl = e.is_cluster(ids)
        if cl.any():
            k = ids[cl] - e.first_cluster
            centre[cl], radius[cl] = self.cluster_centre[k], self.cluster_radius[k]
        return centre, radius

    # --- geometry helpers -------------------------------------------------------------------
    def normals(self, ids=None) -> np.ndarray:
        patch = self.elements.patch if ids is None else self.elements.patch[ids]
        return self.patch_normal[patch]

    def rho(self, ids) -> np.ndarray:
        return self.patch_rho[self.elements.patch[ids]]

    @property
    def rho_max(self) -> np.ndarray:
        """(N,) largest reflectance over channels of every element."""
        if len(self._rho_max) != len(self.elements):
            self._rho_max = self.patch_rho.max(axis=1)[self.elements.patch]
        return self._rho_max

    def geometry(self) -> Geometry:
        e = self.elements
        c, a, r = (x[e.patch] for x in self.patch_curve)
        return Geometry.upload(e.verts, self.normals(), c, a, r, self.diagonal)

    def facing_pairs(self, recv: np.ndarray, src: np.ndarray) -> np.ndarray:
        e = self.elements
        return facing(e.verts[recv], self.normals(recv), e.verts[src], self.normals(src),
                      PLANE_EPS * self.diagonal)

    # --- links ------------------------------------------------------------------------------
    def initial_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Every patch <- the root cluster, or without clusters all ordered pairs of patches that
        face each other (chunked, vectorised)."""
        p = len(self.patch_normal)
        if self.clusters is not None:
            return np.arange(p, dtype=np.int32), np.full(p, self.elements.first_cluster, np.int32)
        recv_all, src_all = [], []
        rows_per_chunk = max(1, _LINK_CHUNK // max(p, 1))
        cols = np.arange(p)
        for start in range(0, p, rows_per_chunk):
            rows = np.arange(start, min(p, start + rows_per_chunk))
            r = np.repeat(rows, p)
            s = np.tile(cols, len(rows))
            keep = r != s
            r, s = r[keep], s[keep]
            ok = self.facing_pairs(r, s)
            recv_all.append(r[ok])
            src_all.append(s[ok])
        return np.concatenate(recv_all).astype(np.int32), np.concatenate(src_all).astype(np.int32)

    def evaluate(self, recv: np.ndarray, src: np.ndarray, geo: Geometry, *, stream: int = 0,
                 vclass: np.ndarray | None = None) -> Links:
        """Evaluate links; ``stream`` selects an independent random sequence.

        ``vclass`` holds classes inherited from parent links (shaft.py); links still unknown
        are tested for full visibility first and, when every sampled ray was blocked, for
        full blockage.
        """
        vclass = np.zeros(len(recv), np.int8) if vclass is None else vclass.astype(np.int8)
        unknown = self._unknown(src, vclass)
        if len(unknown):
            vclass[unknown[self._prove(recv[unknown], src[unknown], visible=True)]] = 1
        t = time.perf_counter()
        self.stream = stream
        seed = self.settings.seed + 0x10000 * stream
        if (self.settings.workers or self.settings.scheduler) and self._executor is None:
            from .distributed import DaskEvaluator

            self._executor = DaskEvaluator(self.scene, workers=self.settings.workers,
                                           scheduler=self.settings.scheduler)
        run = evaluate_links if self._executor is None else self._executor.evaluate_links
        wave = run(self.scene.mi_scene, geo, recv, src, samples=self.settings.samples_per_link, seed=seed,
                   clusters=self.clusters, vclass=vclass)
        self.timing["visibility"] += time.perf_counter() - t
        self.rays += wave.rays
        # a proven-blocked link whose lanes all missed the kernel reads vis 1 by convention
        wave.vis[vclass == 2] = 0.0
        wave.ff[vclass == 2] = 0.0
        dark = self._unknown(src, vclass)
        dark = dark[wave.vis[dark] <= 0]
        if len(dark):
            vclass[dark[self._prove(recv[dark], src[dark], visible=False)]] = 2
        return Links(recv.astype(np.int32), src.astype(np.int32), wave.ff, wave.ff_max, wave.vis,
                     wave.ff_std, wave.ff_range, wave.ff_lo, vclass)

    def _unknown(self, src: np.ndarray, vclass: np.ndarray) -> np.ndarray:
        """Indices of links whose visibility could still be proven (element sources, class 0)."""
        if self.culler is None:
            return np.zeros(0, np.int64)
        return np.flatnonzero((vclass == 0) & ~self.elements.is_cluster(src))

    def _prove(self, recv: np.ndarray, src: np.ndarray, *, visible: bool) -> np.ndarray:
        """(M,) bool: links proven fully visible (visible=True) or fully blocked (see shaft.py)."""
        from .shaft import lift, prove_blocked

        t = time.perf_counter()
        e = self.elements
        offset = RAY_OFFSET * self.diagonal
        r = lift(e.verts[recv], self.normals(recv), offset)
        s = lift(e.verts[src], self.normals(src), offset)
        if visible:
            tri = self.scene.patch_tri
            proven = self.culler.visible(r, s, tri[e.patch[recv]], tri[e.patch[src]])
        else:
            proven = prove_blocked(self.scene.mi_scene, r, s, self.culler.tol)
        self.classified["tested"] += len(recv)
        self.classified["visible" if visible else "blocked"] += int(proven.sum())
        self.timing["classify"] += time.perf_counter() - t
        return proven

    # --- direct light from non-area emitters ------------------------------------------------
    def update_direct(self, ids: np.ndarray, samples: int | None = None) -> None:
        """Direct irradiance (W/m^2) of point/spot/directional/sky lights on elements ids, and
        its standard error, from ``samples`` points each (default: samples_per_link)."""
        grown = len(self.elements) - len(self.direct)
        if grown > 0:
            self.direct = np.concatenate([self.direct, np.zeros((grown, self.channels))])
            self.direct_error = np.concatenate([self.direct_error, np.zeros((grown, self.channels))])
            self.direct_samples = np.concatenate([self.direct_samples, np.zeros(grown, np.int64)])
        ids = ids[~self.elements.is_cluster(ids)]
        if not self.scene.light_emitters or len(ids) == 0:
            return
        from .emitters import direct_irradiance

        t = time.perf_counter()
        samples = samples or self.settings.samples_per_link
        e = self.elements
        c, a, r = (x[e.patch[ids]] for x in self.patch_curve)
        h, err, rays = direct_irradiance(self.scene, e.verts[ids], self.normals(ids), (c, a, r),
                                         samples=samples, seed=self.settings.seed + samples, keys=ids,
                                         with_error=True)
        self.direct[ids] = h[:, : self.channels]
        self.direct_error[ids] = err[:, : self.channels]
        self.direct_samples[ids] = samples
        self.rays += rays
        self.timing["direct"] += time.perf_counter() - t

    def direct_power_errors(self, leaves: np.ndarray) -> np.ndarray:
        """(L,) sampling error of each leaf's direct light as power (W): A * rho * stderr(H)."""
        e = self.elements
        rho = self.patch_rho[e.patch[leaves]]
        return e.area[leaves] * (rho * self.direct_error[leaves]).max(axis=1)

    def direct_error_total(self, leaves: np.ndarray) -> float:
        """Expected L1 error (W) of the per-patch means from direct-light sampling noise.

        Independent leaf errors add in quadrature within a patch (they partly cancel in its
        mean); the expected |N(0, s)| is s * sqrt(2 / pi).
        """
        if not self.scene.light_emitters:
            return 0.0
        power = self.direct_power_errors(leaves)
        per_patch = np.bincount(self.elements.patch[leaves], weights=power * power)
        return float(np.sqrt(2.0 / np.pi) * np.sqrt(per_patch).sum())

    # --- the linear system ------------------------------------------------------------------
    def solve(self, system: LeafSystem, x0: np.ndarray):
        """Solve the leaf system from x0 (timed); returns (B (L, C), iterations, residual)."""
        t = time.perf_counter()
        b, iterations, residual = solve_system(system, x0, method=self.settings.solver,
                                               tol=self.settings.solver_tolerance,
                                               max_iterations=self.settings.max_iterations)
        self.timing["solve"] += time.perf_counter() - t
        # radiosity is never negative; Krylov round-off leaves ~1e-8 below zero on unlit leaves
        return np.maximum(b, 0.0), iterations, residual

    def _link_matrix(self) -> sp.csr_matrix:
        """(N, N) form factors; cluster links spread over the patches their samples saw."""
        n = len(self.elements)
        cluster = self.elements.is_cluster(self.links.src)
        if not cluster.any():
            return self.links.matrix(n)
        from .visibility import cluster_link_entries

        t = time.perf_counter()
        rows, cols, vals = cluster_link_entries(
            self.scene.mi_scene, self.geometry(), self.clusters, self.links.recv[cluster],
            self.links.src[cluster], samples=self.settings.samples_per_link,
            seed=self.settings.seed + 0x10000 * self.stream)
        self.timing["visibility"] += time.perf_counter() - t
        plain = self.links.select(~cluster)
        return sp.csr_matrix((np.concatenate([plain.ff.astype(np.float64), vals]),
                              (np.concatenate([plain.recv, rows]), np.concatenate([plain.src, cols]))),
                             shape=(n, n))

    def _cluster_row_stderr(self, n: int) -> np.ndarray:
        """(n,) standard error of each receiver's summed cluster-link form factors."""
        links = self.links
        cluster = self.elements.is_cluster(links.src)
        if not cluster.any():
            return np.zeros(n)
        var = links.ff_std[cluster].astype(np.float64) ** 2 / self.settings.samples_per_link
        return np.sqrt(np.bincount(links.recv[cluster], weights=var, minlength=n))

    def system(self, leaves: np.ndarray) -> LeafSystem:
        e = self.elements
        push = e.ancestor_matrix(leaves)
        area = e.area
        pull = sp.diags(1.0 / area) @ push.T.tocsr() @ sp.diags(area[leaves])
        rho = self.rho(leaves)
        # direct light of point/sky emitters: each leaf's own estimate (a split parent keeps its
        # old value, which must not be added on top of its children's)
        emission = self.patch_emission[e.patch[leaves]] + rho * self.direct[leaves]
        links = self._link_matrix()
        # Each link's visibility is estimated on its own, so behind occluders the sampled
        # form factors of one receiver can add up to a little more than 1 (up to ~9 % on the
        # closed Cornell box); scale such rows back to 1 (energy is never created). Cluster
        # links are Monte Carlo estimates with a known spread: a row may exceed 1 by twice
        # their standard error before it is scaled (clipping their noise at 1 would bias every
        # row low: 11.5 % of the power was lost in a room with 1,000 small lights).
        # The allowance stays below 90 % of the way to rho * row = 1, so every row still damps.
        row_sum = np.asarray(links.sum(axis=1)).ravel()
        rho_row = np.zeros(len(row_sum))
        rho_row[leaves] = rho.max(axis=1)
        headroom = 0.9 * (1.0 / np.maximum(rho_row, 1e-3) - 1.0)
        cap = 1.0 + np.minimum(2.0 * self._cluster_row_stderr(len(row_sum)), headroom)
        if np.any(row_sum > cap):
            links = sp.diags(1.0 / np.maximum(row_sum / cap, 1.0)) @ links
        return LeafSystem(push.tocsr(), links, pull.tocsr(), rho, emission)


def uses_hierarchical_core(settings: Settings) -> bool:
    """Whether a solve runs on the hierarchical core (core.py): asked for, and no feature
    that only the legacy core has (shadow textures, the bf/bound oracles). Dask workers run
    either core's waves."""
    if settings.core != "hierarchical":
        return False
    what = settings.legacy_feature()
    if what is not None:
        warn(f"{what} runs on the legacy core only: this solve uses core='legacy' (leave it out to "
             "solve on the hierarchical core)")
        return False
    return True


def check_link_budget(scene: Scene, minimum: int, max_links: int, what: str) -> None:
    """Say before solving when the link budget cannot hold a request.

    ``minimum`` is the fewest links the solve holds before any refinement (``what`` says why).
    Above ``max_links`` nothing fits: SettingsError naming the memory it would take and the fix.
    Above half of it a warning: refining every initial link once replaces it by at least two
    (a cluster opens into two children, an element splits into four), so refinement stops at
    the cap before the tolerance.
    """
    from .errors import SettingsError

    where = scene.source or "<scene>"

    def size(links: int) -> str:
        nbytes = links * LINK_PEAK_BYTES
        return f"{nbytes / (1 << 30):.1f} GiB" if nbytes >= 1 << 30 else f"{nbytes / (1 << 20):.1f} MiB"

    if minimum > max_links:
        raise SettingsError(f"{where}: {what}: {minimum:,} links (about {size(minimum)} at "
                            f"{LINK_PEAK_BYTES} B per link) before any refinement, more than "
                            f"max_links={max_links:,}; raise max_links on a machine that holds it"
                            + ("" if "facing" not in what else ", or solve with clustering='on' (links "
                               "grow with the patches, not their pairs)"))
    if 2 * minimum > max_links:
        warn(f"{where}: {what}: {minimum:,} links before any refinement, and refining each once "
             f"needs at least {2 * minimum:,}, more than max_links={max_links:,}: refinement will "
             "stop at the cap well before the tolerance; raise max_links (about "
             f"{size(2 * minimum)} for one refinement) or solve a coarser mesh")


def _facing_pair_count(prob) -> int:
    """Ordered pairs of patches that face each other (the links a solve without clusters
    starts with), counted in chunks of bounded memory."""
    p = len(prob.patch_normal)
    rows_per_chunk = max(1, _LINK_CHUNK // max(p, 1))
    cols = np.arange(p)
    count = 0
    for start in range(0, p, rows_per_chunk):
        rows = np.arange(start, min(p, start + rows_per_chunk))
        r, s = np.repeat(rows, p), np.tile(cols, len(rows))
        keep = r != s
        count += int(prob.facing_pairs(r[keep], s[keep]).sum())
    return count


def solve_problem(scene: Scene, settings: Settings):
    """Run hierarchical radiosity on a loaded scene; returns a Solution. Its kernels are
    compiled without fast math (``_runtime.exact_arithmetic``)."""
    with exact_arithmetic():
        return _solve(scene, settings)


def _solve(scene: Scene, settings: Settings):
    """``solve_problem``'s work: the hierarchical core, or the legacy one."""
    from .solution import Solution

    max_links = settings.max_links or _memory_max_links()
    patches = len(scene.patch_tri)
    # every patch receives its light through at least one link
    check_link_budget(scene, patches, max_links, f"{patches:,} patches need one link each")
    if uses_hierarchical_core(settings):
        from .core import solve_hierarchical

        evaluator = None
        if settings.workers or settings.scheduler:
            from .distributed import DaskEvaluator

            evaluator = DaskEvaluator(scene, workers=settings.workers, scheduler=settings.scheduler)
        try:
            return solve_hierarchical(scene, settings, max_links, evaluator=evaluator)
        finally:
            if evaluator is not None:
                evaluator.close()
    t_start = time.perf_counter()
    prob = Problem(scene, settings)
    if prob.clusters is None and 2 * patches * (patches - 1) > prob.max_links:   # else no pair count can pass
        check_link_budget(scene, _facing_pair_count(prob), prob.max_links,
                          f"without clusters every pair of the {patches:,} patches facing each other is linked")
    bar = tqdm(total=settings.max_refine_passes + 1, desc="mirad", disable=settings.quiet)

    # --- initial linking and first solve ------------------------------------------------------
    t = time.perf_counter()
    recv, src = prob.initial_pairs()
    prob.timing["link"] += time.perf_counter() - t
    geo = prob.geometry()
    prob.links = prob.evaluate(recv, src, geo)
    _open_lit_clusters(prob)
    prob.update_direct(np.arange(len(prob.elements)))
    leaves = prob.elements.leaves
    system = prob.system(leaves)
    b_leaf, iterations, residual = prob.solve(system, system.emission.copy())
    total_iterations = most_iterations = iterations
    bar.update(1)

    # --- multigridding: refine against a shrinking power budget, re-solve ------------------
    # Each link's error is a power (W): the receiver's area times its radiosity error (see
    # link_power_errors). The solution's estimated relative error is their sum over the total
    # power scale A_total * B_mean. A pass refines every link above eps = budget / (2 M): the
    # links below it hold at most half the budget, so passes drive the estimate down until it
    # meets the tolerance (or elements reach their minimum size).
    passes = 0
    capped = False
    # Rounds: refinement passes until the running estimate meets the tolerance, then every
    # kept link re-estimated with fresh samples. The oracle kept exactly the links whose
    # samples looked smooth; estimating them from the same samples would bias F low (samples
    # that missed a kernel peak both look smooth and under-estimate), and the running
    # estimate with them. Re-evaluating with an independent random stream decouples selection
    # from estimation; if the fresh estimate is still over the tolerance, refinement goes on
    # from there (a new stream per round), while passes remain.
    try:
        for stream in range(1, _MAX_ROUNDS + 1):
            stalled = False
            while passes < settings.max_refine_passes:
                b_elem = system.pull @ b_leaf
                b_mean = _reflected_mean(prob, leaves, b_leaf)
                spread = _radiosity_spread(prob, system, b_elem)
                per_elem = _element_errors(prob, b_elem, spread)
                if _estimate(prob, b_elem, spread, b_mean, per_elem) <= settings.tolerance:
                    break
                budget = settings.tolerance / _error_scale(prob, b_elem, spread, per_elem) * b_mean * prob.total_area
                eps = settings.link_error_scale * budget / (2.0 * max(len(prob.links) + len(leaves), 1))
                t = time.perf_counter()
                for _ in range(4):
                    resampled = _resample_direct(prob, leaves, eps)
                    refined, capped = _refine(prob, b_elem, spread, eps)
                    if refined or resampled or capped:
                        break
                    # nothing is above its share, yet the estimate is over the tolerance: lower the bar
                    eps /= 4.0
                prob.timing["refine"] += time.perf_counter() - t
                passes += 1
                if refined or resampled:
                    x0 = prob.b_elem_cache[prob.elements.leaves] if refined else b_leaf
                    leaves = prob.elements.leaves
                    system = prob.system(leaves)
                    b_leaf, iterations, residual = prob.solve(system, x0)
                    total_iterations += iterations
                    most_iterations = max(most_iterations, iterations)
                bar.update(1)
                bar.set_postfix(elements=len(prob.elements), links=len(prob.links))
                if not (refined or resampled) or capped:
                    stalled = True
                    break
            # --- re-estimate every kept link with fresh samples -------------------------------
            if _open_lit_clusters(prob):
                leaves = prob.elements.leaves
            selected = prob.links
            prob.links = prob.evaluate(selected.recv, selected.src, prob.geometry(), stream=stream,
                                       vclass=selected.vclass)
            # whether a cluster link was seen at all is judged on both sample sets, so the error
            # estimate does not swing with which links happen to miss their cluster this time
            prob.links.ff_max = np.maximum(prob.links.ff_max, selected.ff_max)
            restore_textures(prob)
            system = prob.system(leaves)
            b_leaf, iterations, residual = prob.solve(system, b_leaf)
            total_iterations += iterations
            most_iterations = max(most_iterations, iterations)
            b_elem = system.pull @ b_leaf
            fresh = _estimate(prob, b_elem, _radiosity_spread(prob, system, b_elem),
                              _reflected_mean(prob, leaves, b_leaf))
            if fresh <= settings.tolerance or stalled or capped or passes >= settings.max_refine_passes:
                break
    finally:
        # the passes it took are the whole bar, which stays with the final estimate
        bar.total = bar.n
        bar.refresh()
        bar.close()
        if prob._executor is not None:
            prob._executor.close()
    if capped:
        warn(f"refinement stopped at max_elements={settings.max_elements} or "
             f"max_links={prob.max_links:,} ({len(prob.elements):,} elements, {len(prob.links):,} links; "
             "max_links defaults to what half the memory holds); the estimate says how far from the "
             "tolerance it got: raise the tolerance, or the caps on a larger machine")

    # --- results --------------------------------------------------------------------------------
    h_leaf = system.gather(b_leaf) + prob.direct[leaves]
    # Error estimate (relative, the tolerance's norm): the elements' power errors
    # (_element_errors) and the direct light's sampling error over A_total * mean(B - E).
    b_elem = system.pull @ b_leaf
    spread = _radiosity_spread(prob, system, b_elem)
    area_leaf = prob.elements.area[leaves]
    reflected_mean = _reflected_mean(prob, leaves, b_leaf)
    per_elem = _element_errors(prob, b_elem, spread)
    estimated = _estimate(prob, b_elem, spread, reflected_mean, per_elem)
    # the same error over the mean of B itself (emission included): the validation metric's norm
    estimated_of_mean = estimated * reflected_mean / _mean_radiosity(b_leaf, area_leaf)
    # per-leaf error map, W/m^2: its area integral over A_total * mean(B - E) is
    # stats["estimated_error"]
    err_leaf = system.push @ (per_elem / prob.elements.area)
    if scene.light_emitters:
        err_leaf += np.sqrt(2.0 / np.pi) * prob.direct_power_errors(leaves) / prob.elements.area[leaves]
    prob.timing["total"] = time.perf_counter() - t_start
    stats = {
        "elements": int(len(prob.elements)),
        "leaves": int(len(leaves)),
        "links": int(len(prob.links)),
        "rays": int(prob.rays),
        "seconds": {k: round(v, 4) for k, v in prob.timing.items()},
        "estimated_error": estimated,
        "estimated_error_of_mean": estimated_of_mean,
        "error_bound": _error_bound(prob, b_elem, spread, reflected_mean),
        "core": "legacy",
        "oracle": settings.oracle,
        "texture_links": int(np.count_nonzero(prob.links.vclass == TEXTURED)),
        "visibility_classes": dict(prob.classified, culling=prob.culler is not None),
        "solver": settings.solver,
        "solver_iterations": int(total_iterations),
        "solver_iterations_max": int(most_iterations),      # the most one solve took
        "solver_residual": float(residual),
        "refine_passes": passes,
        "clusters": 0 if prob.clusters is None else int(prob.clusters.count),
        "min_element_area": prob.min_area,
        "capped": bool(capped),
        # the estimate at or under the tolerance (a solve that stops above it also warns)
        "within_tolerance": bool(estimated <= settings.tolerance),
        "features": scene.features,
        "variant": scene.variant,
        "memory_bytes": {"elements": prob.elements.nbytes, "links": prob.links.nbytes},
        "settings": {k: getattr(settings, k) for k in ("tolerance", "samples_per_link", "seed", "solver")},
        "warnings": list(scene.warnings),
    }
    err_leaf = np.repeat(err_leaf[:, None], b_leaf.shape[1], axis=1)
    detail = _leaf_detail(prob, leaves, b_elem)
    stats["detail_leaves"] = int(len(detail[0]))
    return Solution.from_solve(scene, prob, leaves, b_leaf, h_leaf, err_leaf, stats, detail=detail)


#: Peak memory of a solve per link, bytes (measured 215 on the Cornell box at tolerance 0.02,
#: 11 M links; doubled for the temporaries of a large wave).
LINK_PEAK_BYTES = 400


#: Memory a default solve may use for its links (bytes): well under a laptop's memory, so a
#: default solve's peak is predictable; ``Settings.max_links`` raises it.
DEFAULT_LINK_MEMORY = 2 << 30


def _memory_max_links() -> int:
    """Links that DEFAULT_LINK_MEMORY (or half the machine's physical memory, if less) holds
    at LINK_PEAK_BYTES each."""
    try:
        memory = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):      # no sysconf (Windows): 16 GiB
        memory = 16 << 30
    return max(1, int(min(0.5 * memory, DEFAULT_LINK_MEMORY) / LINK_PEAK_BYTES))


#: Most rounds of (refinement passes, fresh re-estimate) in one solve.
_MAX_ROUNDS = 3
#: Measured error / summed error of the smooth links and source terms on the validation
#: scenes (see _element_errors and settings.py).
ESTIMATE_CALIBRATION = 0.13


def link_power_errors(prob: Problem, links: Links, b_elem: np.ndarray, spread: np.ndarray,
                      oracle: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-link error as power (W): (receiver term, source term), each (M,).

    receiver term  A_p * the oracle's error (W/m^2): for ``kernel`` rho_p * B_q * the spread of
                   the sampled kernel over the receiver, i.e. how far the link's one value is
                   from the irradiance it really brings to each point of p; for ``bf``
                   rho_p * B_q * F_hat; for ``bound`` rho_p * B_q * (F_max - F_min) (oracle.py);
    source term    A_p * rho_p * F_pq * spread_q: the link carries the source's mean radiosity,
                   off by the source's own variation.
    Weighting by area makes the sum match the area-weighted error norm, so tiny elements
    next to a contact edge stop splitting once their share is small. ``oracle`` defaults to
    the settings' one.
    """
    oracle = oracle or prob.settings.oracle
    area = prob.elements.area[links.recv]
    rho_b = _max_rho_b(prob, links, b_elem)
    cluster = prob.elements.is_cluster(links.src)
    if oracle == "bf":
        receiver = area * links.ff_max * rho_b
    elif oracle == "bound":
        f_lo, f_hi = transfer_bounds(links, cluster)
        receiver = area * (f_hi - f_lo) * rho_b
    else:
        receiver = area * links.ff_std * rho_b / np.sqrt(prob.settings.samples_per_link)
    source = area * prob.rho_max[links.recv] * links.ff * spread[links.src]
    # A cluster source is estimated by Monte Carlo and its sampled spread (above) is that
    # estimate's error; but where no sample saw any of it (or for the bound oracle, always),
    # a bound stands in: the form factor of the cluster's bounding sphere (zero when its box
    # lies behind the receiver's plane) times the brightest radiosity below it
    # (Smits-Arvo-Greenberg style).
    blind = np.flatnonzero(cluster & ((links.ff_max <= 0) | (oracle == "bound")))
    if len(blind):
        recv, src = links.recv[blind], links.src[blind]
        bound = cluster_form_factor_bound(prob, recv, src)
        receiver[blind] = area[blind] * prob.rho_max[recv] * bound * prob.b_max_below[src]
    if cluster.any():
        # a cluster holding an emitter is always opened (RenderPark does the same), seen or
        # not: its few area-drawn points would rarely land on the light that dominates
        lit = np.flatnonzero(cluster)[prob.cluster_emits[links.src[cluster] - prob.elements.first_cluster]]
        receiver[lit] = np.inf
    return receiver, source


def cluster_form_factor_bound(prob: Problem, recv: np.ndarray, src: np.ndarray) -> np.ndarray:
    """(M,) upper bound of the form factor from receiver elements to source clusters.

    The bounding sphere's form factor, and zero when the cluster's box lies behind (or in)
    the receiver's plane.
    """
    from .cluster import box_corners, sphere_form_factor_bound

    rc, rr = prob.bounding_spheres(recv)
    sc, sr = prob.bounding_spheres(src)
    bound = sphere_form_factor_bound(rc, rr, sc, sr)
    k = src - prob.elements.first_cluster
    corners = box_corners(prob.cluster_lo[k], prob.cluster_hi[k])                  # (M, 8, 3)
    origin = prob.elements.verts[recv, 0]
    height = np.einsum("mkc,mc->mk", corners - origin[:, None], prob.normals(recv)).max(axis=1)
    return np.where(height > PLANE_EPS * prob.diagonal, bound, 0.0)


def _max_rho_b(prob: Problem, links: Links, b_elem: np.ndarray) -> np.ndarray:
    """(M,) max over channels of rho_recv * B_src, one channel at a time (no (M, C) temporaries)."""
    patch_recv = prob.elements.patch[links.recv]
    out = np.zeros(len(links))
    for c in range(b_elem.shape[1]):
        np.maximum(out, prob.patch_rho[patch_recv, c] * b_elem[links.src, c], out=out)
    return out


def _reflected_mean(prob: Problem, leaves: np.ndarray, b_leaf: np.ndarray) -> float:
    """Area-weighted mean reflected radiosity B - E over the leaves, W/m^2 (mean over channels).

    Emission is known exactly, so errors are measured against the light the solver computes:
    a scene whose mean is dominated by a bright emitter still gets its reflected light right.
    """
    reflected = np.maximum(b_leaf - prob.patch_emission[prob.elements.patch[leaves]], 0.0)
    return _mean_radiosity(reflected, prob.elements.area[leaves])


def _error_scale(prob: Problem, b_elem: np.ndarray, spread: np.ndarray, per_elem: np.ndarray) -> float:
    """How much of the summed link power errors (the oracle's linear measure, which refinement
    shares out among the links) the estimate counts: the estimate's link part ``per_elem``
    (``_element_errors``) over that sum, so the budget matches the tolerance.
    ``bound``: 1 / (1 - rho_max).
    """
    if prob.settings.oracle == "bound":
        return _amplification(prob)
    receiver, source = link_power_errors(prob, prob.links, b_elem, spread)
    linear = float(np.sum(receiver + source))
    if not np.isfinite(linear) or linear <= 0:
        return ESTIMATE_CALIBRATION
    return float(per_elem.sum()) / linear


def _amplification(prob: Problem) -> float:
    """1 / (1 - rho_max): how much local transfer errors can grow through the solve."""
    return 1.0 / max(1.0 - float(prob.patch_rho.max()), 1e-3)


def _element_errors(prob: Problem, b_elem: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(N,) estimated power error (W) of the light each element gathers through its links.

    ``bound``: 1 / (1 - rho_max) times the summed link bounds. Otherwise (the ``bf`` oracle
    refines by its own measure, but its F_hat says how large a transfer is, not how wrong,
    so it is estimated like ``kernel``) the kernel errors of link_power_errors, in two parts:

    * links whose visibility is partial (0 < V < 1, not from a cluster: a shadow edge crosses
      their sample domain, where stratified samples gain little over independent ones) carry
      their standard error A rho B std(G v) / sqrt(n); a receiver's links draw independent
      samples, so their errors add in quadrature, and sqrt(2/pi) turns the standard error
      into an expected |error|;
    * every other link (smooth integrands, where the stratified and low-discrepancy samples
      do far better than std / sqrt(n)) and every source term are summed and scaled by
      ESTIMATE_CALIBRATION, measured against Mitsuba's path tracer.
    """
    n = len(prob.elements)
    links = prob.links
    if prob.settings.oracle == "bound":
        receiver, source = link_power_errors(prob, links, b_elem, spread, "bound")
        return _amplification(prob) * np.bincount(links.recv, weights=receiver + source, minlength=n)
    receiver, source = link_power_errors(prob, links, b_elem, spread, "kernel")
    partial = (links.vis > 0) & (links.vis < 1) & ~prob.elements.is_cluster(links.src)
    random = np.sqrt(np.bincount(links.recv[partial], weights=receiver[partial] ** 2, minlength=n))
    smooth = np.bincount(links.recv, weights=np.where(partial, 0.0, receiver) + source, minlength=n)
    return np.sqrt(2.0 / np.pi) * random + ESTIMATE_CALIBRATION * smooth


def _estimate(prob: Problem, b_elem: np.ndarray, spread: np.ndarray, b_mean: float,
              per_elem: np.ndarray | None = None) -> float:
    """Estimated relative error: the elements' power errors (``_element_errors``, passed as
    ``per_elem`` when already computed) plus the sampling error of the direct light from
    point/sky emitters, over A_total * mean reflected radiosity."""
    if per_elem is None:
        per_elem = _element_errors(prob, b_elem, spread)
    total = float(per_elem.sum()) + prob.direct_error_total(prob.elements.leaves)
    return total / max(prob.total_area * b_mean, 1e-300)


#: Links.vclass of links whose visibility is a shadow texture (shadows.py).
TEXTURED = 3
#: Links.vclass marker, within one refinement wave, of ray-traced children of a textured link:
#: they are texture candidates whatever their error, so a split receiver's shadow stays a
#: texture on its children (where their texture fits the budget) instead of turning into
#: a patchwork of textured and flat leaves.
RETEXTURE = 4


def texture_links_wave(prob: Problem, fresh: np.ndarray, error: np.ndarray, eps: float, b_elem: np.ndarray) -> None:
    """Replace ray visibility by a convolution shadow texture (shadows.py) on links that would
    otherwise split (and on the children of textured links, RETEXTURE): partly visible links
    from emitters whose texture's predicted error, as power, is within their share of the
    budget. Their receiver error becomes that prediction; ``error`` (over ``fresh``) is
    updated in place.
    """
    from .shadows import apply_texture_links, narrowest_penumbra

    links, e = prob.links, prob.elements
    src = links.src[fresh]
    inherited = links.vclass[fresh] == RETEXTURE
    links.vclass[fresh[inherited]] = 0                 # rays were traced; the class was a marker
    cand = (((error > eps) & (links.vclass[fresh] == 0)) | inherited) & ~e.is_cluster(src)
    cand &= (links.vis[fresh] > 0) & (links.vis[fresh] < 1)
    cand[cand] &= prob.patch_emission[e.patch[src[cand]]].max(axis=1) > 0
    if not cand.any():
        return
    t = time.perf_counter()
    # a texture pays where the receiver spans several penumbrae; below that, a split or two
    # resolves the shadow for less than a texture costs
    # (children of a textured link keep the texture's chance: their shadow is on screen already)
    ids = fresh[cand & ~inherited]
    pen = narrowest_penumbra(prob.scene.mi_scene, e.verts[links.src[ids]], e.verts[links.recv[ids]])
    cand[cand & ~inherited] = e.area[links.recv[ids]] >= TEXTURE_MIN_PENUMBRAE * pen ** 2
    if not cand.any():
        prob.timing["textures"] += time.perf_counter() - t
        return
    mask = np.zeros(len(links), bool)
    mask[fresh[cand]] = True
    tl, accepted = apply_texture_links(prob, mask, resolution=TEXTURE_RESOLUTION)
    idx = np.flatnonzero(accepted)                      # link indices, in tl's order
    rho_b = _max_rho_b(prob, links.select(idx), b_elem)
    tex_error = e.area[links.recv[idx]] * rho_b * tl.ff_unoccluded * tl.predicted_error
    # A texture stands in for the subtree that subdivision would grow to resolve its shadow:
    # elements about a penumbra wide, each link of which would be allowed eps. It gets their
    # summed share (at most one element per texel); the estimate still sums its real error,
    # so when the textures take too much, the estimate stays over the tolerance, eps falls and
    # the texture's own error sends its receiver to split (children re-decide).
    share = np.clip(e.area[links.recv[idx]] / np.maximum(tl.penumbra, 1e-30) ** 2, 1.0,
                    TEXTURE_RESOLUTION ** 2 / 4)
    ok = tex_error <= eps * share
    idx, ff, ff_unocc = idx[ok], tl.ff[ok], tl.ff_unoccluded[ok]
    links.ff[idx] = ff
    links.vis[idx] = ff / np.maximum(ff_unocc, 1e-30)
    # the kernel oracle reads the texture's predicted error through ff_std (see link_power_errors)
    links.ff_std[idx] = ff_unocc * tl.predicted_error[ok] * np.sqrt(prob.settings.samples_per_link)
    links.vclass[idx] = TEXTURED
    prob.textures.append((tl.select(ok), links.ff_std[idx].copy(), share[ok]))
    local = np.searchsorted(fresh, idx)
    error[local] = tex_error[ok]
    prob.timing["textures"] += time.perf_counter() - t


def _stored_textures(prob: Problem, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the TEXTURED links among ``ids`` keep their texture: (their positions in ``ids``,
    the index of each one's latest texture in the concatenation of ``prob.textures``)."""
    links = prob.links
    textured = np.flatnonzero(links.vclass[ids] == TEXTURED)
    if not len(textured) or not prob.textures:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    n = len(prob.elements)
    key = np.concatenate([t.recv.astype(np.int64) * n + t.src for t, _, _ in prob.textures])
    order = np.argsort(key, kind="stable")
    want = links.recv[ids[textured]].astype(np.int64) * n + links.src[ids[textured]]
    pos = np.clip(np.searchsorted(key[order], want, side="right") - 1, 0, len(key) - 1)  # latest texture
    found = key[order][pos] == want
    return textured[found], order[pos[found]]


def _texture_error_share(prob: Problem, ids: np.ndarray) -> np.ndarray:
    """(M,) error share of links ``ids``: a TEXTURED link's share from texture_links_wave, else 1."""
    share = np.ones(len(ids))
    at, j = _stored_textures(prob, ids)
    if len(at):
        share[at] = np.concatenate([sh for _, _, sh in prob.textures])[j]
    return share


def _textures_of_links(prob: Problem):
    """The stored textures of the links that are TEXTURED now: (link indices (K,), TextureLinks
    (K), ff_std (K,)), in the same order."""
    from .shadows import TextureLinks

    at, j = _stored_textures(prob, np.arange(len(prob.links)))
    if not len(at):
        return at, TextureLinks.empty(TEXTURE_RESOLUTION), np.zeros(0)
    tl = TextureLinks.concatenate([t for t, _, _ in prob.textures], TEXTURE_RESOLUTION)
    std = np.concatenate([s for _, s, _ in prob.textures])
    return at, tl.select(j), std[j]


def restore_textures(prob: Problem) -> None:
    """Put the stored texture transfers back on TEXTURED links after a re-evaluation."""
    t, tl, std = _textures_of_links(prob)
    links = prob.links
    links.ff[t], links.ff_std[t] = tl.ff, std
    links.vis[t] = tl.ff / np.maximum(tl.ff_unoccluded, 1e-30)


def _leaf_detail(prob: Problem, leaves: np.ndarray, b_elem: np.ndarray):
    """Shadow detail of the final texture links, summed per receiver leaf: (rows (T,) into
    ``leaves``, detail (T, R, R, C) float32 W/m^2, zero mean over each leaf; see
    TextureLinks.detail)."""
    _, tl, _ = _textures_of_links(prob)
    r = TEXTURE_RESOLUTION
    if not len(tl):
        return np.zeros(0, np.int32), np.zeros((0, r, r, prob.channels), np.float32)
    row_of = np.full(len(prob.elements), -1, np.int64)
    row_of[leaves] = np.arange(len(leaves))
    rows = row_of[tl.recv]
    keep = rows >= 0                       # textures live on leaves (links are pushed to leaves)
    tl, rows = tl.select(keep), rows[keep]
    detail = tl.detail(b_elem[tl.src], prob.rho(tl.recv))
    unique, slot = np.unique(rows, return_inverse=True)
    out = np.zeros((len(unique),) + detail.shape[1:], np.float32)
    np.add.at(out, slot, detail)
    return unique.astype(np.int32), out


#: Texels a side of the shadow textures made by the solver.
TEXTURE_RESOLUTION = 32
#: A link is a texture candidate only if its receiver's area is at least this many squared
#: widths of its sharpest penumbra (shadows.narrowest_penumbra).
TEXTURE_MIN_PENUMBRAE = 1.0


def _resample_direct(prob: Problem, leaves: np.ndarray, eps: float) -> bool:
    """Re-estimate the direct light of leaves whose sampling error exceeds eps (W) with 4x the
    points (up to MAX_DIRECT_SAMPLES); returns whether any was re-estimated.

    Rays go where the variance is: a leaf in full sun or open sky is exact with few points,
    one under a leaf layer's dappled shade needs many.
    """
    if not prob.scene.light_emitters:
        return False
    noisy = leaves[(prob.direct_power_errors(leaves) > eps) & (prob.direct_samples[leaves] < MAX_DIRECT_SAMPLES)]
    for samples in np.unique(prob.direct_samples[noisy]):          # a few sample counts at most
        ids = noisy[prob.direct_samples[noisy] == samples]
        prob.update_direct(ids, samples=int(min(4 * samples, MAX_DIRECT_SAMPLES)))
    return len(noisy) > 0


#: Most points per element for the direct light of point/sky emitters.
MAX_DIRECT_SAMPLES = 1024


def _error_bound(prob: Problem, b_elem: np.ndarray, spread: np.ndarray, b_mean: float) -> float:
    """The bound oracle's estimate (see _error_scale), whatever the oracle: loose where links
    are not classified (their lower bound is 0)."""
    receiver, source = link_power_errors(prob, prob.links, b_elem, spread, "bound")
    return _amplification(prob) * float(receiver.sum() + source.sum()) / max(prob.total_area * b_mean, 1e-300)


def _open_lit_clusters(prob: Problem) -> bool:
    """Open every cluster link whose cluster holds an emitter (their error is inf).

    Done before the first solve, so that solve (and the error budget taken from it) sees
    the lights, and again before the final estimate. Returns whether anything was opened.
    """
    if prob.clusters is None:
        return False
    n = len(prob.elements)
    before = len(prob.links)
    refined, _ = _refine(prob, np.zeros((n, prob.channels)), np.zeros(n), np.finfo(float).max)
    return refined or len(prob.links) != before


def _mean_radiosity(b_leaf: np.ndarray, area: np.ndarray) -> float:
    mean = float((area[:, None] * b_leaf).sum() / max(area.sum() * b_leaf.shape[1], 1e-300))
    return mean if mean > 0 else 1e-300


def _radiosity_spread(prob: Problem, system: LeafSystem, b_elem: np.ndarray) -> np.ndarray:
    """(N,) variation of radiosity inside each element, W/m^2 (max over channels).

    A link carries its source's mean radiosity; what that hides is how the radiosity
    varies over the source. Where the source already has leaves below it, that is
    measured: the area-weighted mean |B_leaf - B_element| over its leaves. A leaf's own
    variation is estimated from its incoming links' kernel spread (rho * B_src * std(G v)).
    """
    links = prob.links
    u = links.ff_std * _max_rho_b(prob, links, b_elem)
    per_elem = np.bincount(links.recv, weights=u, minlength=len(prob.elements))
    estimated = system.pull @ (system.push @ per_elem)
    pull = system.pull.tocoo()
    b_leaf = b_elem[prob.elements.leaves]
    deviation = np.abs(b_leaf[pull.col] - b_elem[pull.row]).max(axis=1)
    measured = np.bincount(pull.row, weights=pull.data * deviation, minlength=len(prob.elements))
    # brightest leaf below each element (cluster links' bounds)
    prob.b_max_below = np.zeros(len(prob.elements))
    np.maximum.at(prob.b_max_below, pull.row, b_leaf[pull.col].max(axis=1))
    return np.maximum(measured, estimated)


def _refine(prob: Problem, b_elem: np.ndarray, spread: np.ndarray, eps: float) -> tuple[bool, bool]:
    """Refinement waves at threshold eps until every link passes; returns (refined, capped)."""
    e = prob.elements
    refined = False
    capped = False
    checked = 0  # links [0, checked) passed the oracle at this eps; later ones are new
    while True:
        links = prob.links
        fresh = np.arange(checked, len(links))
        recv, src = links.recv[fresh], links.src[fresh]
        error, source_error = link_power_errors(prob, links.select(fresh), b_elem, spread)
        if prob.settings.shadow_textures:
            texture_links_wave(prob, fresh, error, eps, b_elem)
            error = error / _texture_error_share(prob, fresh)   # a texture may hold its subtree's share
        can_split = (e.area > prob.min_area) | e.is_cluster(np.arange(len(e)))  # clusters always open
        split_src, split_recv = choose_splits(error + source_error, eps, e.area[recv], e.area[src],
                                              can_split[recv], can_split[src],
                                              prefer_source=(source_error > error) | e.is_cluster(src))
        if not (split_src.any() or split_recv.any()):
            break
        # links the wave would add: four per split source, four per link into a split receiver
        growth = 4 * (int(np.count_nonzero(split_src))
                      + int(np.count_nonzero(np.isin(links.recv, recv[split_recv]))))
        if len(e) >= prob.settings.max_elements or len(links) + growth > prob.max_links:
            capped = True
            break
        refined = True
        n_before = len(e)
        e.split(np.concatenate([src[split_src], recv[split_recv]]))
        # children inherit their parent's radiosity until the next solve
        b_elem = np.concatenate([b_elem, b_elem[e.parent[n_before:]]])
        spread = np.concatenate([spread, 0.5 * spread[e.parent[n_before:]]])
        prob.update_direct(np.arange(n_before, len(e)))

        # links whose source was split go to the source's children ...
        # (children inherit their parent link's visibility class: their shaft lies inside it)
        owner, child = e.children_pairs(src[split_src])
        new_recv, new_src = recv[split_src][owner], child
        new_cls = links.vclass[fresh][split_src][owner]
        # ... and every link into a receiver that is no longer a leaf moves to its children:
        # links stay on receiver leaves, so each leaf gathers its whole (hierarchical) source
        # cut at its own sample points and its row sum cannot exceed 1
        keep = np.ones(len(links), bool)
        keep[fresh[split_src]] = False
        stale = keep & ~e.is_leaf[links.recv]
        keep &= ~stale
        pushed_recv = np.concatenate([links.recv[stale], new_recv])
        pushed_src = np.concatenate([links.src[stale], new_src])
        pushed_cls = np.concatenate([links.vclass[stale], new_cls])
        inner = ~e.is_leaf[pushed_recv]
        owner, child = e.children_pairs(pushed_recv[inner])
        new_recv = np.concatenate([pushed_recv[~inner], child])
        new_src = np.concatenate([pushed_src[~inner], pushed_src[inner][owner]])
        new_cls = np.concatenate([pushed_cls[~inner], pushed_cls[inner][owner]])
        # a texture belongs to its receiver: children trace rays, then re-decide (RETEXTURE)
        retexture = new_cls == TEXTURED
        new_cls[retexture] = 0
        # children of facing pairs: evaluate them all and drop the ones no sample point sees
        # (cheaper than a geometric facing test on every new pair)
        new_links = prob.evaluate(new_recv, new_src, prob.geometry(), vclass=new_cls)
        new_links.vclass[retexture & (new_links.vis > 0) & (new_links.vis < 1)] = RETEXTURE
        # (a cluster no sample saw is kept unless it lies wholly behind the receiver's plane)
        blind = np.flatnonzero((new_links.ff_max <= 0) & e.is_cluster(new_links.src))
        keep_new = new_links.ff_max > 0
        if len(blind):
            keep_new[blind] = cluster_form_factor_bound(prob, new_links.recv[blind], new_links.src[blind]) > 0
        new_links = new_links.select(keep_new)
        kept = links.select(keep)
        checked = len(kept)
        prob.links = kept.extend(new_links)
    prob.b_elem_cache = b_elem
    return refined, capped
