"""Visibility and transfer waves (and path-traced references) on a Dask cluster.

``Settings.workers = N`` starts a ``distributed.LocalCluster`` of N single-threaded worker
processes on this machine; ``Settings.scheduler = "tcp://host:8786"`` connects to a running
scheduler instead. Either core sends its waves there. Each worker

- loads the scene from its file once (``mirad.load_scene``, cached per worker process and
  keyed by the file's absolute path and the scene fingerprint, checked after loading), so a
  file that differs on the worker is an error, not a silently different answer (with a remote
  scheduler the same absolute path must exist on every worker, e.g. a shared file system);
- receives the arrays a wave reads as numpy arrays, scattered once to every worker and
  cached per worker by a token unique to their content: the legacy core's element geometry
  (sent when it changed since the last wave), the hierarchical core's node arrays
  (``node_arrays``: sent when the node count changed, as the in-process core uploads its
  ``NodeBuffers`` again only then). Both only grow by appended rows, so usually just the
  rows added since the last send travel, and a worker appends them to what it holds;
- receives a batch of links: receiver ids, source ids (and the legacy core's visibility
  classes);
- runs the same fused Dr.Jit kernels as the single-process solver: the legacy core's
  ``visibility.evaluate_links`` on a ``Geometry`` uploaded on the worker, the hierarchical
  core's ``transfer.evaluate`` (with the wave's rays per point, seed and ray offset) on
  ``NodeBuffers`` uploaded on the worker, returning its per-point arrays g, gv, gv_point.

The kernels draw every random number from a hash of the seed and the element (node) ids of
a link, so splitting a wave's link list into batches gives bitwise the same per-link results
as one launch: the solution (links, rays, radiosity, estimate) is identical to the in-process
one of the same core for a fixed seed (tests/test_distributed.py checks both cores).

A scene handed over as a Mitsuba dict or an ``mi.Scene`` has no file a worker could load:
those raise ``SettingsError``. Local worker processes are started with ``spawn``, so a script
that asks for workers must guard its entry point with ``if __name__ == "__main__":``.

Only the link waves go to the workers: the legacy core's ``Problem.evaluate`` (refinement
and the final fresh-sample pass), the hierarchical core's ``core._transfers`` (linking,
refinement and the final gather). The legacy core's cluster-link matrix entries
(``visibility.cluster_link_entries``), the hierarchical core's buried-surface rays
(``transfer.buried_fraction``) and either core's direct-light pass still run in the client
process, as do the linear solves.

>>> sol = mirad.solve("scenes/cornell-box/scene.xml", workers=2)            # doctest: +SKIP
>>> sol = mirad.solve("scenes/cornell-box/scene.xml", core="hierarchical", workers=2)  # doctest: +SKIP
>>> sol = mirad.solve("scene.xml", scheduler="tcp://10.0.0.5:8786")         # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)
from .errors import EnvironmentProblem, SettingsError

__all__ = ["DaskEvaluator", "check_main_guard", "unguarded_main_line", "chunk_seed"]

#: Fewest links per batch (smaller waves go out as fewer batches).
MIN_BATCH = 4096
#: Batches per worker and wave (a little slack for uneven batches).
BATCHES_PER_WORKER = 2
#: Geometries (and cluster trees) kept per worker process.
_CACHE_DEPTH = 2

# --- per-worker-process caches (module globals live once per worker process) --------------
_SCENES: dict = {}
_ARRAYS: dict = {}
_THREADS_SET = [False]


def _require_distributed():
    try:
        import distributed  # noqa: F401
    except ImportError:  # pragma: no cover - dependency missing
        raise EnvironmentProblem("workers/scheduler need the 'distributed' package; "
                                 "pip install 'distributed>=2024.1'") from None
    return distributed


def scene_file(scene) -> str:
    """Absolute path of the file a scene was loaded from; SettingsError when there is none."""
    if not getattr(scene, "source", None):
        raise SettingsError("workers/scheduler need a scene file: workers load the scene from its XML file, "
                            "and a scene given as a Mitsuba dict or an mi.Scene cannot be shipped; "
                            "save it as XML and pass the path, or drop workers/scheduler")
    return os.path.abspath(scene.source)


@dataclass(frozen=True)
class _SceneKey:
    path: str
    fingerprint: str
    variant: str
    threads: int          # Dr.Jit threads per worker process (0: leave Dr.Jit's default)


def _worker_scene(key: _SceneKey):
    """The scene of ``key`` on this worker process, loaded once."""
    from .errors import SceneError
    from .scene import load_scene

    if key.threads and not _THREADS_SET[0]:
        import drjit as dr

        dr.set_thread_count(key.threads)
        _THREADS_SET[0] = True
    cache_key = (key.path, key.fingerprint)
    if cache_key not in _SCENES:
        scene = load_scene(key.path, variant=key.variant)
        if scene.fingerprint != key.fingerprint:
            raise SceneError(f"scene file '{key.path}' on a worker has fingerprint {scene.fingerprint}, "
                             f"the client's has {key.fingerprint}; give every worker the same file")
        _SCENES[cache_key] = scene
    return _SCENES[cache_key]


def _cached(token: str, build):
    """Per-worker cache of uploaded Dr.Jit arrays, keyed by a content hash (last few kept)."""
    if token not in _ARRAYS:
        while len(_ARRAYS) >= 2 * _CACHE_DEPTH:
            _ARRAYS.pop(next(iter(_ARRAYS)))
        _ARRAYS[token] = build()
    return _ARRAYS[token]


# ------------------------------------------------------------------------------------------
# Geometry <-> numpy
# ------------------------------------------------------------------------------------------

def _digest(arrays) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.data)
    return h.hexdigest()


def geometry_arrays(geo) -> dict:
    """A ``visibility.Geometry`` as numpy float32 arrays (bitwise what the kernels read)."""
    vec = lambda v: np.ascontiguousarray(np.asarray(v.numpy(), np.float32).T)  # noqa: E731
    out = {name: vec(getattr(geo, name)) for name in ("v0", "v1", "v2", "normal", "curve_center", "curve_axis")}
    out["curve_radius"] = np.asarray(geo.curve_radius.numpy(), np.float32)
    out["offset"] = np.float64(geo.offset)
    out["size"] = int(geo.size)
    return out


def _upload_geometry(arrays: dict):
    from .arrays import to_float, to_vector3
    from .visibility import Geometry

    return Geometry(*(to_vector3(arrays[n]) for n in ("v0", "v1", "v2", "normal", "curve_center", "curve_axis")),
                    to_float(arrays["curve_radius"]), float(arrays["offset"]), int(arrays["size"]))


def cluster_arrays(clusters) -> dict | None:
    """A ``cluster.ClusterGeometry`` as numpy arrays, or None."""
    if clusters is None:
        return None
    return {"first": int(clusters.first), "patches": int(clusters.patches), "count": int(clusters.count),
            "order": np.asarray(clusters.order.numpy(), np.uint32), "cum": np.asarray(clusters.cum.numpy(), np.float32),
            "lo": np.asarray(clusters.lo.numpy(), np.uint32), "hi": np.asarray(clusters.hi.numpy(), np.uint32),
            "area": np.asarray(clusters.area.numpy(), np.float32)}


def _upload_clusters(arrays: dict | None):
    if arrays is None:
        return None
    from .arrays import to_float, to_uint
    from .cluster import ClusterGeometry

    return ClusterGeometry(arrays["first"], to_uint(arrays["order"]), to_float(arrays["cum"]),
                           to_uint(arrays["lo"]), to_uint(arrays["hi"]), to_float(arrays["area"]),
                           arrays["patches"], arrays["count"])


#: The ``nodes.Nodes`` fields that ``transfer.NodeBuffers.upload`` reads.
NODE_FIELDS = ("kind", "poly", "normal", "fill", "area", "recv_pts", "recv_nrm", "children", "curve", "center",
               "radius", "parent")


def node_arrays(nodes) -> dict:
    """The arrays of a ``nodes.Nodes`` (N nodes) that the hierarchical core's transfer waves
    read, as ``NodeBuffers.upload`` converts them: float32 (bitwise what it uploads), ``kind``
    uint32, ``size`` N. Shapes as in ``Nodes``: poly (N, 4, 3), recv_pts (N, K, 3), ..."""
    out = {name: np.ascontiguousarray(getattr(nodes, name), np.float32) for name in NODE_FIELDS
           if name not in ("kind", "children", "parent")}
    out["kind"] = np.ascontiguousarray(nodes.kind, np.uint32)
    out["parent"] = np.ascontiguousarray(nodes.parent, np.int64)
    # (a triangle's own id in place of its children: rows sent once stay valid after splits)
    from .nodes import cluster_children

    out["children"] = cluster_children(nodes.kind, nodes.children)
    out["size"] = len(nodes)
    return out


class _NodeArrays:
    """What ``NodeBuffers.upload`` reads of a ``Nodes``, rebuilt from ``node_arrays`` on a worker."""

    def __init__(self, arrays: dict):
        for name in NODE_FIELDS:
            setattr(self, name, arrays[name])

    def __len__(self) -> int:
        return len(self.kind)


def _token(arrays: dict | None) -> str:
    if arrays is None:
        return "none"
    return _digest([v for v in arrays.values() if isinstance(v, np.ndarray)]) + str(
        [v for v in arrays.values() if not isinstance(v, np.ndarray)])


# ------------------------------------------------------------------------------------------
# Tasks (run on workers)
# ------------------------------------------------------------------------------------------

def _assemble(parts) -> dict:
    """Element geometry from a chain of parts [(token, arrays), ...]: the first holds the rows
    of some earlier wave, each later one the rows appended since (elements only ever grow).
    Concatenations are cached per worker by token, so a worker only appends what is new."""
    start = 0
    for i in range(len(parts) - 1, -1, -1):
        if "n" + parts[i][0] in _ARRAYS:
            start = i
            break
    arrays = _ARRAYS.get("n" + parts[start][0], parts[start][1])
    for token, delta in parts[start + 1:]:
        arrays = {k: (np.concatenate([v, delta[k]]) if isinstance(v, np.ndarray) else delta[k])
                  for k, v in arrays.items()}
    _ARRAYS.pop("n" + parts[start][0], None)
    _ARRAYS["n" + parts[-1][0]] = arrays
    return arrays


def _links_task(key: _SceneKey, geo_payload, cl_payload, recv, src, vclass, samples: int, seed: int):
    """One batch of links on a worker: the per-link LinkWave fields and the ray count."""
    from .visibility import LinkWave, evaluate_links

    scene = _worker_scene(key)
    geo_token = geo_payload[-1][0]
    cl_token, cl_arrays = cl_payload
    geo = _cached("g" + geo_token, lambda: _upload_geometry(_assemble(geo_payload)))
    clusters = _cached("c" + cl_token, lambda: _upload_clusters(cl_arrays))
    wave = evaluate_links(scene.mi_scene, geo, recv, src, samples=samples, seed=seed, clusters=clusters,
                          vclass=vclass)
    return tuple(getattr(wave, f) for f in LinkWave.FIELDS), wave.rays


def _transfers_task(key: _SceneKey, nodes_payload, recv, src, rays_per_point: int, seed: int, offset: float,
                    samples: bool, spread: bool):
    """One batch of hierarchical-core links on a worker: ``transfer.evaluate``'s per-point
    arrays g, gv, gv_point, gv_square (M, K) float32, the ray count and, with ``samples``, the
    volume clusters' arriving samples (links indexed within the batch)."""
    from .transfer import evaluate

    pt = evaluate(_worker_scene(key).mi_scene, _node_buffers(nodes_payload), recv, src, rays_per_point=rays_per_point,
                  seed=seed, offset=offset, samples=samples, spread=spread)
    return pt.g, pt.gv, pt.gv_point, pt.gv_square, pt.rays, pt.samples


def _node_buffers(nodes_payload):
    """The hierarchical core's node buffers on a worker, uploaded once per node set."""
    from .transfer import NodeBuffers

    token = nodes_payload[-1][0]
    return _cached("h" + token, lambda: NodeBuffers.upload(_NodeArrays(_assemble(nodes_payload))))


def _preload_task(key: _SceneKey) -> int:
    return _worker_scene(key).triangle_count


def _reference_task(key: _SceneKey, triangles, samples: int, seed: int, max_depth: int, method: str):
    from .reference import triangle_reference

    scene = _worker_scene(key)
    ref = triangle_reference(scene, samples_per_triangle=samples, seed=seed, max_depth=max_depth,
                             triangles=triangles, method=method)
    return ref.radiosity, ref.stderr, ref.paths


# ------------------------------------------------------------------------------------------
# Client side
def _is_main_guard(node) -> bool:
    """Whether an ``ast`` statement is ``if __name__ == "__main__":``."""
    import ast

    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare):
        return False
    sides = [node.test.left, *node.test.comparators]
    return (any(isinstance(x, ast.Name) and x.id == "__name__" for x in sides)
            and any(isinstance(x, ast.Constant) and x.value == "__main__" for x in sides))


def unguarded_main_line(frame=None) -> tuple[str, int] | None:
    """(script, line) when a script's own top-level code, outside ``if __name__ == "__main__":``,
    leads to this call; None otherwise (a guarded call, an interactive session, a notebook).

    Local workers are spawned processes that import the script again: unguarded, the import
    asks for workers once more, and each worker dies with a long multiprocessing traceback.
    """
    import ast
    import inspect
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if not path or not str(path).endswith(".py"):
        return None
    frame = frame or inspect.currentframe()
    line = None
    while frame is not None:        # the outermost frame of the script's own top-level code
        if frame.f_globals.get("__name__") == "__main__" and frame.f_code.co_name == "<module>":
            line = frame.f_lineno
        frame = frame.f_back
    if line is None:
        return None
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8", errors="replace"))
    except (OSError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if node.lineno <= line <= (node.end_lineno or node.lineno):
            return None if _is_main_guard(node) else (str(path), line)
    return None


def check_main_guard(workers: int) -> None:
    """SettingsError naming the script and the fix when local workers would re-run it (see
    ``unguarded_main_line``); nothing is started."""
    found = unguarded_main_line()
    if found is not None:
        script, line = found
        raise SettingsError(f"workers={workers}: {script}, line {line} asks for worker processes from the "
                            "script's top level; each worker imports the script again and would ask for "
                            "workers itself; put the script's code under 'if __name__ == \"__main__\":' "
                            "(or leave workers at 0)")


# ------------------------------------------------------------------------------------------

class DaskEvaluator:
    """Runs link waves on a Dask cluster: the legacy core's (``evaluate_links``, made lazily by
    ``Problem.evaluate``) or the hierarchical core's (``evaluate_transfers``, made by
    ``solver.solve_problem`` before the solve and closed after it, also on error).

    Parameters
    ----------
    scene : mirad.Scene loaded from a file (``scene.source``)
    workers : int, local worker processes (a LocalCluster; ignored when ``scheduler`` is given)
    scheduler : str or None, address of a running Dask scheduler
    """

    def __init__(self, scene, *, workers: int = 0, scheduler: str | None = None):
        distributed = _require_distributed()
        path = scene_file(scene)
        t0 = time.perf_counter()
        self._cluster = None
        if scheduler:
            try:
                self.client = distributed.Client(scheduler, timeout="30s")
            except Exception as exc:
                raise SettingsError(f"cannot connect to the Dask scheduler at {scheduler!r} ({exc}); "
                                    "check the address or start one with 'dask scheduler'") from None
            threads = 0
        else:
            check_main_guard(int(workers))
            cores = os.cpu_count() or 1
            threads = max(1, cores // max(int(workers), 1))
            self._cluster = distributed.LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                                     dashboard_address=None, silence_logs=40)
            self.client = distributed.Client(self._cluster)
        self.workers = max(1, len(self.client.scheduler_info(n_workers=-1)["workers"]))
        self.key = _SceneKey(path, scene.fingerprint, scene.variant, threads)
        self._chains = {}              # slot -> (futures of (token, rows) parts, numpy arrays sent so far)
        self._nodes = (-1, [])         # (node count, chain) of the hierarchical core's nodes sent last
        self._cl = (None, None)
        self.batches = 0
        # every worker starts loading the scene now, while the client links and uploads
        self._preload = [self.client.submit(_preload_task, self.key, workers=[w], allow_other_workers=False,
                                            pure=False)
                         for w in self.client.scheduler_info(n_workers=-1)["workers"]]
        #: seconds: starting/connecting, packing + scattering geometry, waiting for the batches
        self.timing = {"start": time.perf_counter() - t0, "scatter": 0.0, "run": 0.0}

    def _scatter(self, slot: str, arrays):
        token = _token(arrays)
        last_token, last_future = getattr(self, slot)
        if token == last_token:
            return last_future
        future = self.client.scatter((token, arrays), broadcast=True, hash=False)
        setattr(self, slot, (token, future))
        return future

    def _scatter_rows(self, slot: str, arrays: dict) -> list:
        """Send the rows the workers do not have yet; returns the chain of part futures.

        ``arrays`` is a struct of arrays (N, ...) with N in ``arrays["size"]``, and scalars.
        Elements (and nodes) only ever grow (refinement appends children), so each wave
        usually sends just the rows added since the last one of this ``slot``; anything else
        (other scalars, a changed row) starts a new chain.
        """
        chain, sent = self._chains.get(slot, ([], None))
        n_old = 0 if sent is None else sent["size"]
        extends = (sent is not None and arrays["size"] >= n_old
                   and all(arrays[k] == v for k, v in sent.items() if not isinstance(v, np.ndarray) and k != "size")
                   and all(np.array_equal(arrays[k][:n_old], v) for k, v in sent.items() if isinstance(v, np.ndarray)))
        if extends and arrays["size"] == n_old:
            return chain
        if extends:
            part = {k: (v[n_old:] if isinstance(v, np.ndarray) else v) for k, v in arrays.items()}
        else:
            part, chain = arrays, []
        token = uuid.uuid4().hex          # unique per part (hashing 30 MB per wave costs more than sending)
        chain = chain + [self.client.scatter((token, part), broadcast=True, hash=False)]
        self._chains[slot] = (chain, arrays)
        return chain

    def evaluate_links(self, mi_scene, geo, recv: np.ndarray, src: np.ndarray, *, samples: int, seed: int,
                       clusters=None, vclass: np.ndarray | None = None):
        """Same contract (and bitwise the same results) as ``visibility.evaluate_links``.

        ``mi_scene`` is unused (workers trace against their own copy of the scene file); it is
        there so both functions take the same arguments.
        """
        from .visibility import LinkWave

        m = len(recv)
        vclass = np.zeros(m, np.int8) if vclass is None else np.asarray(vclass, np.int8)
        if m == 0:
            return LinkWave(*(np.zeros(0, np.float32) for _ in LinkWave.FIELDS), 0)
        t0 = time.perf_counter()
        geo_f = self._scatter_rows("geometry", geometry_arrays(geo))
        cl_f = self._scatter("_cl", cluster_arrays(clusters))
        t1 = time.perf_counter()
        self.timing["scatter"] += t1 - t0
        batches = max(1, min(self.workers * BATCHES_PER_WORKER, -(-m // MIN_BATCH)))
        bounds = np.linspace(0, m, batches + 1).astype(np.int64)
        futures = [self.client.submit(_links_task, self.key, geo_f, cl_f, recv[a:b], src[a:b], vclass[a:b],
                                      int(samples), int(seed), pure=False)
                   for a, b in zip(bounds[:-1], bounds[1:])]
        results = self.client.gather(futures)
        self.timing["run"] += time.perf_counter() - t1
        self.batches += len(futures)
        fields = [np.concatenate([r[0][i] for r in results]) for i in range(len(LinkWave.FIELDS))]
        return LinkWave(*fields, int(sum(r[1] for r in results)))

    def evaluate_transfers(self, nodes, recv: np.ndarray, src: np.ndarray, *, rays_per_point: int, seed: int,
                           offset: float, samples: bool = False, spread: bool = False):
        """Same contract (and bitwise the same results) as ``transfer.evaluate`` on
        ``NodeBuffers.upload(nodes)``: the hierarchical core's links recv <- src (M,).

        Like the in-process core, which uploads its node buffers again only when the node
        count changes, the node arrays go to the workers once per change of ``len(nodes)``
        (just the rows added since the last send, when the others are unchanged)."""
        from .nodes import RECEIVER_POINTS
        from .transfer import PointTransfers, join_samples

        m = len(recv)
        if m == 0:
            return PointTransfers(*(np.zeros((0, RECEIVER_POINTS), np.float32) for _ in range(4)), 0,
                                  join_samples([]) if samples else None)
        t0 = time.perf_counter()
        if self._nodes[0] != len(nodes):
            self._nodes = (len(nodes), self._scatter_rows("nodes", node_arrays(nodes)))
        chain = self._nodes[1]
        t1 = time.perf_counter()
        self.timing["scatter"] += t1 - t0
        batches = max(1, min(self.workers * BATCHES_PER_WORKER, -(-m // MIN_BATCH)))
        bounds = np.linspace(0, m, batches + 1).astype(np.int64)
        futures = [self.client.submit(_transfers_task, self.key, chain, recv[a:b], src[a:b], int(rays_per_point),
                                      int(seed), float(offset), bool(samples), bool(spread), pure=False)
                   for a, b in zip(bounds[:-1], bounds[1:])]
        results = self.client.gather(futures)
        self.timing["run"] += time.perf_counter() - t1
        self.batches += len(futures)
        found = None
        if samples:     # (each batch's links counted from its first)
            found = join_samples([(r[5][0] + a,) + r[5][1:] for r, a in zip(results, bounds[:-1])])
        return PointTransfers(*(np.concatenate([r[i] for r in results]) for i in range(4)),
                              int(sum(r[4] for r in results)), found)

    def reference(self, scene, *, samples_per_triangle: int = 1024, seed: int = 0, max_depth: int = -1,
                  method: str = "outgoing", chunk: int = 4096):
        """Per-triangle path-traced reference computed in triangle chunks on the workers.

        Chunk k of ``chunk`` triangles runs ``reference.triangle_reference`` with its own seed
        (a hash of ``seed`` and k), so the result depends on ``seed`` and ``chunk`` only, not on
        the number of workers. It is an independent estimate of the same quantity as the
        in-process reference (not bitwise the same: that one seeds per launch).
        """
        from .reference import Reference

        t = scene.triangle_count
        starts = range(0, t, int(chunk))
        futures = [self.client.submit(_reference_task, self.key, np.arange(a, min(t, a + chunk)),
                                      int(samples_per_triangle), chunk_seed(seed, k), int(max_depth), method,
                                      pure=False)
                   for k, a in enumerate(starts)]
        t0 = time.perf_counter()
        parts = self.client.gather(futures)
        return Reference(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                         int(samples_per_triangle), time.perf_counter() - t0, int(sum(p[2] for p in parts)),
                         method=method, seed=int(seed), fingerprint=scene.fingerprint)

    def close(self) -> None:
        """Close the client (and the LocalCluster this evaluator started)."""
        try:
            self.client.close()
        finally:
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def chunk_seed(seed: int, chunk: int) -> int:
    """The seed of chunk ``chunk`` of a distributed reference with seed ``seed`` (31 bits), so a
    chunk can be recomputed in process with ``triangle_reference(seed=chunk_seed(seed, k))``."""
    digest = hashlib.blake2b(f"mirad-ref:{seed}:{chunk}".encode(), digest_size=4).digest()
    return int.from_bytes(digest, "little") >> 1
