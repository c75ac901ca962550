"""Array helpers shared by every module: numpy -> Dr.Jit converters, group means, constants.

A leaf module (only ``_runtime`` before Mitsuba), the one home of each of these.
"""

from __future__ import annotations

import numpy as np

from . import _runtime  # noqa: F401  (LLVM set-up before mitsuba)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["MAX_LANES", "RAY_OFFSET", "LEAF_CORNER_UV", "DR_PAD", "shadow_ray_length", "row_norm", "dr_buffer",
           "to_float", "to_uint", "to_bool", "to_vector3", "to_point3", "scene_diagonal", "group_sum", "group_mean",
           "channel_max"]

#: Largest number of lanes in one Dr.Jit launch (bounds the memory of a wave).
MAX_LANES = 1 << 22
#: Shadow and gather rays start and stop this fraction of the scene diagonal off a surface.
RAY_OFFSET = 1e-5
#: (u, v) of a leaf's corners v0, v1, v2 in its parametrisation y = v0 + u (v1 - v0) + v (v2 - v0).
LEAF_CORNER_UV = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])


#: Elements kept readable past the end of every numpy buffer handed to Dr.Jit (``dr_buffer``).
DR_PAD = 64


#: Bytes a buffer handed to Dr.Jit starts on (``dr_buffer``): always the same alignment, so that
#: a frozen wave (``transfer.FREEZE_WAVES``) finds its inputs as it recorded them (an input
#: mapped at another alignment is recorded anew).
DR_ALIGN = 64


def dr_buffer(a, dtype) -> np.ndarray:
    """(N,) ``a`` flattened and cast to ``dtype``, in a fresh buffer that stays readable DR_PAD
    elements past its end (zeros), for a Dr.Jit array to be made of.

    On the CPU (LLVM) Dr.Jit maps a contiguous numpy array's memory instead of copying it, and
    its kernels load whole SIMD packets: 16 lanes with AVX-512, so the last packet of an
    elementwise kernel reads up to 15 elements past the array's end. Where that end is the end
    of a mapped page and the next page is not mapped, the read faults: a SIGSEGV inside
    JIT-compiled code, at a page boundary, for about one array size in a thousand (a large
    array is a page-aligned mapping of its own; ``tests/test_arrays.py`` builds one that ends
    at a guard page). A buffer with room after its end is never read past it; gathers are
    masked and were never the problem. Every numpy -> Dr.Jit conversion in mirad goes
    through here (``to_float``, ``to_uint``, ``to_bool`` and the vectors made of them)."""
    flat = np.ravel(np.asarray(a))
    itemsize = np.dtype(dtype).itemsize
    room = np.zeros((len(flat) + DR_PAD) * itemsize + DR_ALIGN, np.uint8)
    start = -room.ctypes.data % DR_ALIGN
    out = room[start:start + (len(flat) + DR_PAD) * itemsize].view(dtype)
    out[:len(flat)] = flat
    return out[:len(flat)]


def to_float(a) -> "mi.Float":
    """mi.Float of an array (flattened, float32)."""
    return mi.Float(dr_buffer(a, np.float32))


def to_uint(a) -> "mi.UInt32":
    """mi.UInt32 of an array of non-negative integers (flattened)."""
    return mi.UInt32(dr_buffer(a, np.uint32))


def to_bool(a) -> "mi.Bool":
    """mi.Bool of an array of truth values (flattened)."""
    return mi.Bool(dr_buffer(a, bool))


def to_vector3(a) -> "mi.Vector3f":
    """mi.Vector3f of an (N, 3) array."""
    a = np.asarray(a)
    return mi.Vector3f(to_float(a[:, 0]), to_float(a[:, 1]), to_float(a[:, 2]))


def to_point3(a) -> "mi.Point3f":
    """mi.Point3f of an (N, 3) array."""
    a = np.asarray(a)
    return mi.Point3f(to_float(a[:, 0]), to_float(a[:, 1]), to_float(a[:, 2]))


def shadow_ray_length(dist, offset: float):
    """Length (m, a Dr.Jit float like ``dist``) of a shadow ray to a point ``dist`` away that lies
    ``offset`` (m) off its surface (the ray ends are lifted by RAY_OFFSET of the diagonal): half
    the offset short of that point, so the ray cannot reach the surface the point lies on, while
    an occluder farther than that from the point still blocks it. The relative margin it
    replaces, dist (1 - 1e-4), skipped 0.2 mm at the end of a 2 m ray, six times the offset in a
    3.5 m room: rays from under a sheet closing the room reached wall points 0.04 mm above the
    sheet, and light crossed it (tests/test_hard_cases.py, seeds 0-5)."""
    return dr.maximum(dist - 0.5 * offset, 0.0)


def row_slices(count: int, size: int):
    """Slices over ``count`` rows, ``size`` at a time (none for no rows): a large scene's
    millions of links or pairs in pieces whose temporaries stay small."""
    return (slice(a, a + size) for a in range(0, count, size))


def take_rows(a: np.ndarray, index) -> np.ndarray:
    """``a[index]`` for an index array along the first axis (ints, or a bool mask of a's
    length): the same rows, copied by ``np.take`` / ``np.compress``. (numpy copies the rows of an
    (M, 3) or (M, K) array picked by fancy indexing about four times slower than ``np.take``
    does; a 1-D array's items take the same time either way.)"""
    if a.ndim < 2:
        return a[index]
    index = np.asarray(index)
    if index.dtype == bool:
        return np.compress(index, a, axis=0)
    return np.take(a, index, axis=0)


def put_rows(out: np.ndarray, index: np.ndarray, values: np.ndarray) -> None:
    """``out[index] = values`` for row indices ``index`` (M,) along the first axis: as a
    slice where they are one run of rows (a wave's pairs, often all of them), whose copy is one
    block rather than fancy indexing's row by row."""
    run = len(index) and index[0] >= 0 and index[-1] - index[0] + 1 == len(index)
    if run and (len(index) == 1 or (np.diff(index) == 1).all()):
        out[index[0]:index[0] + len(index)] = values
    else:
        out[index] = values


def row_norm(v: np.ndarray) -> np.ndarray:
    """(...,) Euclidean length of the vectors v (..., 3) along the last axis (a third of the
    time of ``np.linalg.norm(v, axis=-1)`` on the gather's millions of pairs)."""
    return np.sqrt(np.einsum("...c,...c->...", v, v))


def scene_diagonal(vertices: np.ndarray) -> float:
    """Length of the bounding-box diagonal of vertices (V, 3), m; 1.0 for an empty or point set."""
    vertices = np.asarray(vertices, np.float64)
    if not len(vertices):
        return 1.0
    return float(np.linalg.norm(vertices.max(0) - vertices.min(0))) or 1.0


def group_sum(group: np.ndarray, values: np.ndarray, count: int, *, weights=None) -> np.ndarray:
    """Per-group sums of ``weights * values``: (count, C) for values (N, C), (count,) for (N,).

    ``group`` (N,) int in [0, count); ``weights`` (N,) or None (all ones).
    """
    values = np.asarray(values, np.float64)
    w = np.ones(len(group)) if weights is None else np.asarray(weights, np.float64)
    if values.ndim == 1:
        return np.bincount(group, weights=w * values, minlength=count)
    return np.stack([np.bincount(group, weights=w * values[:, c], minlength=count)
                     for c in range(values.shape[1])], 1).reshape(count, values.shape[1])


def group_mean(group: np.ndarray, values: np.ndarray, count: int, *, weights=None) -> np.ndarray:
    """Per-group weighted means (area-weighted when ``weights`` are areas); 0 for empty groups.

    Same shapes as :func:`group_sum`.
    """
    w = np.ones(len(group)) if weights is None else np.asarray(weights, np.float64)
    total = group_sum(group, values, count, weights=w)
    norm = np.maximum(np.bincount(group, weights=w, minlength=count), 1e-300)
    return total / (norm if total.ndim == 1 else norm[:, None])


def channel_max(a: np.ndarray) -> np.ndarray:
    """(N,) largest value of each row of a (N, C) array with few columns (channels); of any
    array (..., C), the largest along its last axis (...).

    Elementwise maxima over the columns: ``a.max(axis=1)`` walks each short row on its own
    and is about five times slower on (N, 3) arrays, once per refinement pass."""
    a = np.asarray(a)
    return np.maximum.reduce([a[..., c] for c in range(a.shape[-1])]) if a.shape[-1] > 1 else a[..., 0].copy()


def row_sum(a: np.ndarray) -> np.ndarray:
    """(M,) sum of each row of a float (M, K) array with few columns (a receiver's K points, a
    node's children), added column by column from the left.

    ``a.sum(axis=1)`` walks each short row on its own, two to six times slower; for K < 8 it adds
    a row's values in the same order from zero, so the sums are its bits."""
    a = np.asarray(a)
    out = a[:, 0] + 0.0 if a.shape[1] else np.zeros(len(a), a.dtype)
    for k in range(1, a.shape[1]):
        out += a[:, k]
    return out
