"""Dask scale-out (mirad/distributed.py): bitwise the same results as the in-process solver,
on either core (the legacy core's link waves, the hierarchical core's transfer waves).

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


@pytest.mark.parametrize("core, clustering", [("legacy", "off"), ("legacy", "on"), ("hierarchical", "auto")])
def test_solve_on_two_workers_is_bitwise_the_in_process_solve(core, clustering, monkeypatch):
    a = mirad.solve(CORNELL, tolerance=0.2, clustering=clustering, core=core, quiet=True)
    if core == "hierarchical":
        # its waves at this tolerance are a few hundred links: split them over both workers
        monkeypatch.setattr(distributed, "MIN_BATCH", 32)
    b = mirad.solve(CORNELL, tolerance=0.2, clustering=clustering, core=core, quiet=True, workers=2)
    assert a.stats["core"] == b.stats["core"] == core
    assert a.stats["links"] == b.stats["links"] and a.stats["rays"] == b.stats["rays"]
    assert a.stats["elements"] == b.stats["elements"]
    np.testing.assert_array_equal(a.triangle_radiosity, b.triangle_radiosity)
    np.testing.assert_array_equal(a.vertex_radiosity, b.vertex_radiosity)
    assert a.stats["estimated_error"] == b.stats["estimated_error"]


def test_volume_samples_from_workers_are_bitwise_those_in_process(monkeypatch):
    """The final gather splits volume clusters' transfers by the triangle each of their
    samples came from (``core.SampleLog``); the workers return the samples of their waves
    (``evaluate_transfers(samples=True)``), each batch's links counted from its first. The
    furnished room at tolerance 0.9 takes much of its light so, split over many batches."""
    a = mirad.solve(SCENES / "furnished-room" / "scene.xml", tolerance=0.9, quiet=True)
    monkeypatch.setattr(distributed, "MIN_BATCH", 256)
    b = mirad.solve(SCENES / "furnished-room" / "scene.xml", tolerance=0.9, quiet=True, workers=2)
    assert a.stats["links"] == b.stats["links"] and a.stats["rays"] == b.stats["rays"]
    np.testing.assert_array_equal(a.triangle_radiosity, b.triangle_radiosity)


def test_hierarchical_solve_closes_its_workers_on_error(monkeypatch):
    from mirad import core

    closed = []
    monkeypatch.setattr(distributed.DaskEvaluator, "close", lambda self, close=distributed.DaskEvaluator.close:
                        (closed.append(True), close(self)))

    def fail(state):
        raise RuntimeError("stage failed")

    monkeypatch.setattr(core, "link", fail)
    with pytest.raises(RuntimeError, match="stage failed"):
        mirad.solve(CORNELL, tolerance=0.2, core="hierarchical", quiet=True, workers=2)
    assert closed == [True]


def test_any_split_of_a_wave_gives_bitwise_the_same_links(evaluator, monkeypatch):
    """Element and cluster links, split into many small batches over the workers."""
    scene, ev = evaluator
    prob = Problem(scene, mirad.make_settings(clustering="on", core="legacy"))
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


@pytest.mark.parametrize("rays_per_point", [1, 3])
def test_any_split_of_a_transfer_wave_gives_bitwise_the_same_points(evaluator, monkeypatch, rays_per_point):
    """Hierarchical-core transfers over random node pairs, split into many small batches,
    before and after splits grew the nodes (the workers then get only the new rows)."""
    from mirad import core
    from mirad.nodes import split_triangles
    from mirad.transfer import NodeBuffers, evaluate

    scene, ev = evaluator
    state = core.build(scene, mirad.make_settings(core="hierarchical", tolerance=0.1, quiet=True))
    monkeypatch.setattr(distributed, "MIN_BATCH", 97)         # odd batch boundaries
    monkeypatch.setattr(distributed, "BATCHES_PER_WORKER", 7)
    rng = np.random.default_rng(rays_per_point)
    for grow in (False, True):
        if grow:
            n = len(state.nodes)
            split_triangles(state.nodes, np.flatnonzero(state.nodes.kind == core.TRIANGLE)[::3], state.surface)
            assert len(state.nodes) > n
        nodes = state.nodes
        recv = rng.choice(np.flatnonzero(nodes.kind != core.VOLUME), 2000).astype(np.int32)
        src = rng.integers(0, len(nodes), 2000).astype(np.int32)
        kw = dict(rays_per_point=rays_per_point, seed=11, offset=state.offset)
        one = evaluate(scene.mi_scene, NodeBuffers.upload(nodes), recv, src, **kw)
        before = ev.batches
        many = ev.evaluate_transfers(nodes, recv, src, **kw)
        assert ev.batches - before == 14
        assert len(ev._chains["nodes"][0]) == 1 + grow            # grown: only the new rows were sent
        for name in ("g", "gv", "gv_point"):
            np.testing.assert_array_equal(getattr(one, name), getattr(many, name), err_msg=name)
        assert one.rays == many.rays > 0 and np.count_nonzero(one.gv) > 0


def test_empty_transfer_wave(evaluator):
    from mirad import core

    scene, ev = evaluator
    state = core.build(scene, mirad.make_settings(core="hierarchical", quiet=True))
    pt = ev.evaluate_transfers(state.nodes, np.zeros(0, np.int32), np.zeros(0, np.int32), rays_per_point=1, seed=0,
                               offset=state.offset)
    assert pt.rays == 0 and all(getattr(pt, f).shape == (0, core.RECEIVER_POINTS) for f in ("g", "gv", "gv_point"))


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


@pytest.mark.parametrize("core", ["legacy", "hierarchical"])
def test_workers_need_a_scene_file(core):
    with pytest.raises(SettingsError, match="need a scene file"):
        mirad.solve(closed_box(0.5, 1.0), tolerance=0.2, workers=2, core=core)


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
