"""Dask scale-out (mirad/distributed.py): bitwise the same results as the in-process solver.

The LocalCluster runs 2 worker *processes* (processes=True, spawn): they start in ~3 s here,
and process workers are what a real scale-out uses (a separate Dr.Jit per worker).
"""

from __future__ import annotations

import numpy as np
import pytest

import mirad
from conftest import SCENES, closed_box, run_cli
from mirad import distributed
from mirad.errors import SettingsError
from mirad.solver import Problem
from mirad.visibility import LinkWave, evaluate_links

CORNELL = SCENES / "cornell-box" / "scene.xml"


@pytest.fixture(scope="module")
def evaluator():
    scene = mirad.load_scene(CORNELL)
    with distributed.DaskEvaluator(scene, workers=2) as ev:
        yield scene, ev


@pytest.mark.parametrize("clustering", ["off", "on"])
def test_solve_on_two_workers_is_bitwise_the_in_process_solve(clustering):
    a = mirad.solve(CORNELL, tolerance=0.2, clustering=clustering)
    b = mirad.solve(CORNELL, tolerance=0.2, clustering=clustering, workers=2)
    assert a.stats["links"] == b.stats["links"] and a.stats["rays"] == b.stats["rays"]
    assert a.stats["elements"] == b.stats["elements"]
    np.testing.assert_array_equal(a.triangle_radiosity, b.triangle_radiosity)
    np.testing.assert_array_equal(a.vertex_radiosity, b.vertex_radiosity)
    assert a.stats["estimated_error"] == b.stats["estimated_error"]


def test_any_split_of_a_wave_gives_bitwise_the_same_links(evaluator, monkeypatch):
    """Element and cluster links, split into many small batches over the workers."""
    scene, ev = evaluator
    prob = Problem(scene, mirad.make_settings(clustering="on"))
    geo = prob.geometry()
    recv_c, src_c = prob.initial_pairs()                      # every patch <- the root cluster
    rng = np.random.default_rng(3)
    p = len(prob.patch_normal)
    recv_e, src_e = rng.integers(0, p, 3000), rng.integers(0, p, 3000)
    leaf_clusters = prob.elements.first_cluster + rng.integers(0, prob.clusters.count, 500)
    recv = np.concatenate([recv_c, recv_e, rng.integers(0, p, 500)]).astype(np.int32)
    src = np.concatenate([src_c, src_e, leaf_clusters]).astype(np.int32)
    vclass = np.zeros(len(recv), np.int8)
    vclass[rng.random(len(recv)) < 0.1] = 2                    # some links proven blocked
    one = evaluate_links(scene.mi_scene, geo, recv, src, samples=16, seed=5, clusters=prob.clusters,
                         vclass=vclass)
    monkeypatch.setattr(distributed, "MIN_BATCH", 97)         # odd batch boundaries
    monkeypatch.setattr(distributed, "BATCHES_PER_WORKER", 7)
    before = ev.batches
    many = ev.evaluate_links(None, geo, recv, src, samples=16, seed=5, clusters=prob.clusters, vclass=vclass)
    assert ev.batches - before == 14
    for name in LinkWave.FIELDS:
        np.testing.assert_array_equal(getattr(one, name), getattr(many, name), err_msg=name)
    assert one.rays == many.rays > 0


def test_empty_wave(evaluator):
    scene, ev = evaluator
    prob = Problem(scene, mirad.make_settings())
    wave = ev.evaluate_links(None, prob.geometry(), np.zeros(0, np.int32), np.zeros(0, np.int32),
                             samples=16, seed=0)
    assert wave.rays == 0 and all(len(getattr(wave, f)) == 0 for f in LinkWave.FIELDS)


def test_reference_chunks_match_in_process_chunks(evaluator):
    """The distributed reference is per chunk exactly ``triangle_reference`` with the chunk's seed."""
    from mirad.reference import triangle_reference

    scene, ev = evaluator
    ref = ev.reference(scene, samples_per_triangle=64, seed=2, chunk=10)
    assert ref.radiosity.shape == (scene.triangle_count, 3)
    assert ref.paths == 64 * scene.triangle_count
    for k, start in enumerate(range(0, scene.triangle_count, 10)):
        tris = np.arange(start, min(scene.triangle_count, start + 10))
        local = triangle_reference(scene, samples_per_triangle=64, seed=distributed.chunk_seed(2, k), triangles=tris)
        np.testing.assert_array_equal(ref.radiosity[tris], local.radiosity)
        np.testing.assert_array_equal(ref.stderr[tris], local.stderr)


def test_workers_need_a_scene_file():
    with pytest.raises(SettingsError, match="need a scene file"):
        mirad.solve(closed_box(0.5, 1.0), tolerance=0.2, workers=2)


@pytest.mark.parametrize("bad", [{"workers": -1}, {"workers": 1.5}, {"workers": True}, {"scheduler": " "},
                                 {"scheduler": 8786}])
def test_bad_distributed_settings(bad):
    with pytest.raises(SettingsError):
        mirad.make_settings(**bad)


def test_cli_rejects_negative_workers(tmp_path):
    out = run_cli("solve", CORNELL, "--workers", "-2", "-o", tmp_path / "s.npz", "--quiet")
    assert out.returncode == 2 and "workers=-2" in out.stderr


def test_a_script_without_the_main_guard_is_told_the_fix(tmp_path):
    """Local workers import the script again: unguarded top-level code is refused before any
    process starts (it printed ~500 lines of multiprocessing tracebacks), a guarded one is not."""
    import subprocess
    import sys

    call = f"mirad.solve({str(CORNELL)!r}, tolerance=0.5, workers=2, quiet=True)"
    bad = tmp_path / "bad.py"
    bad.write_text(f"import mirad\n{call}\n")
    res = subprocess.run([sys.executable, str(bad)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and len(res.stderr.splitlines()) < 30
    assert "bad.py, line 2" in res.stderr and "if __name__ == \"__main__\":" in res.stderr
    assert "bootstrapping" not in res.stderr
    guarded = tmp_path / "guarded.py"
    guarded.write_text(f"import mirad\nfrom mirad.distributed import unguarded_main_line\n\n\ndef main():\n"
                       f"    return unguarded_main_line()\n\n\nif __name__ == \"__main__\":\n    print(main())\n")
    res = subprocess.run([sys.executable, str(guarded)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "None", res.stderr
