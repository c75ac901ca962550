"""numpy -> Dr.Jit conversions (mirad.arrays): arrays that end at an unmapped page.

On the CPU, Dr.Jit maps a contiguous numpy array instead of copying it, and its elementwise
kernels load whole SIMD packets, reading past the array's last element. An array whose end is
followed by an unmapped page then faults inside JIT-compiled code (SIGSEGV). The scripts below
place an array's last element right before a page made unreadable with ``mprotect`` and run an
elementwise kernel on it: through mirad's converters, which copy into a padded buffer, they
finish with the right sums; the control hands the same memory to Dr.Jit directly.

And the row copies of the gather's (M, K) and (M, 3) arrays (``take_rows``, ``put_rows``): fancy
indexing's results, bit for bit; the sums and maxima over a row's few columns (``row_sum``,
``channel_max``): numpy's reductions, bit for bit.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from hypothesis import given, settings as hyp_settings, strategies as st

from mirad.arrays import channel_max, put_rows, row_sum, take_rows

# (count of elements: not a multiple of any SIMD width, so that the last packet is partial)
GUARDED = textwrap.dedent("""
    import ctypes, mmap, sys
    import numpy as np
    import mirad  # noqa: F401  (sets the variant up)
    import drjit as dr
    import mitsuba as mi
    from mirad.arrays import to_bool, to_float, to_uint, to_vector3

    pages = 64
    page = mmap.PAGESIZE
    buf = mmap.mmap(-1, (pages + 1) * page, prot=mmap.PROT_READ | mmap.PROT_WRITE)
    libc = ctypes.CDLL(None)
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    address = ctypes.addressof(ctypes.c_char.from_buffer(buf))

    def guarded(dtype, count):
        whole = np.frombuffer(buf, dtype=dtype, count=pages * page // np.dtype(dtype).itemsize)
        return whole[len(whole) - count:]          # its last element ends where the guard page starts

    count = 65533
    f, u, b = guarded(np.float32, count), None, None
    f[:] = 1.5
    if libc.mprotect(ctypes.c_void_p(address + pages * page), page, 0) != 0:
        sys.exit(3)
    how = sys.argv[1]
    if how == "mapped":
        x = mi.Float(f)
    else:
        x = to_float(f)
    y = x * 2.0 + 1.0
    dr.eval(y)
    total = float(np.asarray(y.numpy(), np.float64).sum())
    assert abs(total - 4.0 * count) < 1e-3 * count, total
    if how == "mirad":
        u = np.frombuffer(buf, dtype=np.uint32, count=pages * page // 4)[-count:]
        n = to_uint(u) + 1
        dr.eval(n)
        assert int(np.asarray(n.numpy(), np.int64).sum()) == count * (1 + int(u[0]))
        k = to_bool(np.frombuffer(buf, dtype=np.uint8, count=pages * page)[-count:] > 0)
        dr.eval(~k)
        v = to_vector3(f[: count - count % 3].reshape(-1, 3))
        w = dr.norm(v)
        dr.eval(w)
    print("done")
""")


def _run(how: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", GUARDED, how], capture_output=True, text=True, timeout=300)


def test_converted_arrays_are_never_read_past_their_end():
    """mirad's converters: the kernel reads no byte past the array (the guard page is untouched)."""
    out = _run("mirad")
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert out.stdout.strip().endswith("done")


def test_the_guard_page_catches_a_read_past_the_end():
    """The control: the same memory mapped into Dr.Jit as it is faults (so the test above can fail).
    Only where Dr.Jit maps host memory (the CPU backend); a GPU variant copies it."""
    import mitsuba as mi

    import mirad  # noqa: F401

    if not mi.variant().startswith("llvm"):
        pytest.skip("the GPU backend copies numpy arrays to the device")
    out = _run("mapped")
    if out.returncode == 0:
        pytest.skip("this CPU's packets did not reach the guard page (narrow SIMD): nothing to show")
    assert out.returncode < 0 or out.returncode == 139, (out.returncode, out.stderr[-2000:])


def test_mirad_hands_numpy_to_drjit_only_through_its_converters():
    """The class of the fault above: no module of mirad builds a Dr.Jit array straight from a numpy
    expression (``mi.Float(np....)``, ``mi.UInt32(a.astype(...))``), which would map memory that
    kernels read past; ``arrays.dr_buffer`` is the one way in (``to_float``, ``to_uint``,
    ``to_bool`` and the vectors made of them)."""
    import ast
    from pathlib import Path

    import mirad

    types = {"Float", "Float64", "UInt32", "Int32", "UInt64", "Int64", "Bool", "Vector3f", "Point3f", "Point2f",
             "Normal3f", "Color3f", "TensorXf"}
    found = []
    for path in sorted(Path(mirad.__file__).parent.glob("*.py")):
        if path.name == "arrays.py":
            continue
        source = path.read_text()
        for node in ast.walk(ast.parse(source)):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and isinstance(node.func.value, ast.Name) and node.func.value.id in ("mi", "dr")
                    and node.func.attr in types):
                continue
            converted = ("to_float", "to_uint", "to_bool", "to_vector3", "to_point3")

            def raw(arg) -> bool:        # (an argument made by a converter is safe)
                if isinstance(arg, ast.Starred):
                    arg = arg.value
                if isinstance(arg, ast.GeneratorExp):
                    arg = arg.elt
                if isinstance(arg, ast.Call) and isinstance(arg.func, ast.Name) and arg.func.id in converted:
                    return False
                text = ast.get_source_segment(source, arg) or ""
                return "np." in text or ".astype(" in text or "ascontiguousarray" in text

            if any(raw(a) for a in node.args):
                found.append(f"{path.name}:{node.lineno}: {ast.get_source_segment(source, node)}")
    assert not found, "\n".join(found)


# --- the row copies (take_rows, put_rows): fancy indexing's result, faster ------------------

_ROWS = hyp_settings(max_examples=60, deadline=None, derandomize=True)


@_ROWS
@given(st.integers(1, 40), st.sampled_from([(), (3,), (7,), (4, 3), (2, 7, 3)]), st.integers(0, 2**16),
       st.sampled_from(["int", "negative", "mask", "run"]))
def test_take_rows_and_put_rows_are_fancy_indexing(n, trailing, seed, kind):
    """``take_rows(a, i)`` is ``a[i]`` and ``put_rows(a, i, v)`` is ``a[i] = v``, bit for bit,
    for any shape, index array (ints, negative ints, a bool mask, a run of rows) and dtype."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((n,) + trailing).astype(rng.choice([np.float32, np.float64]))
    if kind == "mask":
        index = rng.random(n) < 0.5
    elif kind == "run":
        start = int(rng.integers(0, n))
        index = np.arange(start, int(rng.integers(start, n + 1)))
    else:
        index = rng.integers(-n if kind == "negative" else 0, n, size=int(rng.integers(0, 2 * n)))
    got = take_rows(a, index)
    assert got.dtype == a.dtype and np.array_equal(got, a[index])
    if kind != "mask":
        index = np.unique(index) if len(index) else index    # (rows written once each)
        values = rng.standard_normal((len(index),) + trailing).astype(a.dtype)
        expected, out = a.copy(), a.copy()
        expected[index] = values
        put_rows(out, index, values)
        assert np.array_equal(out, expected)


@_ROWS
@given(st.integers(0, 40), st.integers(1, 7), st.integers(0, 2**16), st.booleans())
def test_row_sum_and_channel_max_are_numpys_reductions(n, k, seed, zeros):
    """``row_sum(a)`` is ``a.sum(axis=1)`` and ``channel_max(a)`` is ``a.max(axis=1)``, bit for bit
    (signed zeros too), for float32 and float64 rows of up to 7 values: the receivers' points."""
    rng = np.random.default_rng(seed)
    a = (rng.standard_normal((n, k)) * 10.0 ** rng.integers(-15, 15, (n, k))).astype(rng.choice([np.float32,
                                                                                                   np.float64]))
    if zeros:
        a[rng.random((n, k)) < 0.3] = -0.0
    got, expected = row_sum(a), a.sum(axis=1)
    assert got.dtype == expected.dtype and np.array_equal(got, expected)
    assert np.array_equal(np.signbit(got), np.signbit(expected))
    if n:
        assert np.array_equal(channel_max(a), a.max(axis=1))
        # (and along the last axis of any array: a node's children's channels)
        stacked = np.stack([a, -a], axis=1)
        assert np.array_equal(channel_max(stacked), stacked.max(axis=2))
