"""The path-traced reference against closed forms, its standard errors, its cache and bad input."""

from pathlib import Path

import numpy as np
import pytest

import mirad
import mitsuba as mi
from conftest import F_PARALLEL, F_PERPENDICULAR, SCENES, closed_box
from mirad.reference import (Reference, cache_path, cached_reference, reference_image,
                             triangle_reference)

#: The reference must reproduce a closed form within this many of its own standard errors.
Z_MAX = 3.0


@pytest.mark.parametrize("method", ["outgoing", "irradiance"])
@pytest.mark.parametrize("name, exact", [("parallel-squares", F_PARALLEL),
                                         ("perpendicular-squares", F_PERPENDICULAR)])
def test_form_factor_closed_forms_within_three_standard_errors(name, exact, method):
    scene = mirad.load_scene(SCENES / "closed-form" / f"{name}.xml")
    ref = triangle_reference(scene, samples_per_triangle=40000, seed=1, method=method)
    # black emitter of exitance 1: receiver radiosity = rho * F = 0.5 F, no inter-reflection
    b = ref.shape_radiosity(scene, "receiver")
    se = ref.shape_stderr(scene, "receiver")
    assert np.all(se > 0) and np.all(se < 0.01 * 0.5 * exact)  # informative: under 1 %
    assert np.all(np.abs(b - 0.5 * exact) <= Z_MAX * se)
    np.testing.assert_allclose(ref.shape_radiosity(scene, "emitter"), 1.0, rtol=1e-5)


@pytest.mark.parametrize("method", ["outgoing", "irradiance"])
def test_white_furnace_within_three_standard_errors(method):
    rho = 0.5
    scene = mirad.load_scene(closed_box(rho, 1 / np.pi))
    ref = triangle_reference(scene, samples_per_triangle=20000, seed=2, method=method)
    exact = 1.0 / (1.0 - rho)
    area = scene.tri_area
    mean = (ref.radiosity * area[:, None]).sum(0) / area.sum()
    se = np.sqrt(((ref.stderr * area[:, None]) ** 2).sum(0)) / area.sum()
    assert np.all(np.abs(mean - exact) <= Z_MAX * se)
    # the standard errors are honest: z-scores over the triangles spread like N(0, 1)
    z = (ref.radiosity - exact) / ref.stderr
    assert 0.5 < z.std() < 1.6
    assert np.abs(z).max() < 4.5


def test_seeds_are_independent_and_runs_reproducible():
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    a = triangle_reference(scene, samples_per_triangle=500, seed=3)
    b = triangle_reference(scene, samples_per_triangle=500, seed=3)
    c = triangle_reference(scene, samples_per_triangle=500, seed=4)
    assert np.array_equal(a.radiosity, b.radiosity)
    assert not np.array_equal(a.radiosity, c.radiosity)


def test_batches_do_not_change_the_estimate_statistics():
    # two launches (4 x 20000 paths; the third triangle is split across them) give an estimate
    # consistent with one launch (batch=7001, twelve launches, took 9 s for the same check)
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    ref = triangle_reference(scene, samples_per_triangle=20000, seed=5, batch=40001)
    b, se = ref.shape_radiosity(scene, "receiver"), ref.shape_stderr(scene, "receiver")
    assert np.all(np.abs(b - 0.5 * F_PARALLEL) <= Z_MAX * se)
    sub = triangle_reference(scene, samples_per_triangle=100, seed=5, triangles=[2, 3])
    assert sub.radiosity.shape == (2, 3)


def test_cache_reused_for_same_scene_and_settings(tmp_path):
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    first = cached_reference(scene, cache_dir=tmp_path, samples_per_triangle=256, seed=1)
    assert not first.from_cache
    again = cached_reference(scene, cache_dir=tmp_path, samples_per_triangle=256, seed=1)
    assert again.from_cache and np.array_equal(again.radiosity, first.radiosity)
    other = cached_reference(scene, cache_dir=tmp_path, samples_per_triangle=256, seed=2)
    assert not other.from_cache
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_cache_from_a_different_scene_is_never_reused(tmp_path):
    a = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    b = mirad.load_scene(SCENES / "closed-form" / "perpendicular-squares.xml")
    assert a.fingerprint != b.fingerprint
    ref_a = cached_reference(a, cache_dir=tmp_path, samples_per_triangle=256, seed=1)
    # plant scene a's reference under the name scene b would use
    target = cache_path(b, cache_dir=tmp_path, samples_per_triangle=256, seed=1, max_depth=-1,
                        method="outgoing", triangles=None)
    Path(cache_path(a, cache_dir=tmp_path, samples_per_triangle=256, seed=1, max_depth=-1,
                    method="outgoing", triangles=None)).rename(target)
    assert Reference.load(target).fingerprint == a.fingerprint
    ref_b = cached_reference(b, cache_dir=tmp_path, samples_per_triangle=256, seed=1)
    assert not ref_b.from_cache and ref_b.fingerprint == b.fingerprint
    assert not np.array_equal(ref_b.radiosity, ref_a.radiosity)
    assert Reference.load(target).fingerprint == b.fingerprint   # overwritten with the right one


def test_corrupt_cache_is_recomputed(tmp_path):
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    path = cache_path(scene, cache_dir=tmp_path, samples_per_triangle=64, seed=1, max_depth=-1,
                      method="outgoing", triangles=None)
    path.write_bytes(b"not an npz file")
    ref = cached_reference(scene, cache_dir=tmp_path, samples_per_triangle=64, seed=1)
    assert not ref.from_cache and ref.radiosity.shape == (scene.triangle_count, 3)


def test_interrupted_cache_write_leaves_nothing(tmp_path, monkeypatch):
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")

    def interrupted(handle, **arrays):
        handle.write(b"PK\x03\x04 half a file")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", interrupted)
    with pytest.raises(KeyboardInterrupt):
        cached_reference(scene, cache_dir=tmp_path, samples_per_triangle=64, seed=1)
    assert list(tmp_path.iterdir()) == []


def _looking_away():
    T = mi.ScalarTransform4f
    scene = closed_box(0.5, 0.0, size=0.5)
    scene["floor"]["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}
    scene["sensor"] = {"type": "perspective", "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 10],
                                                                       up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16}}
    return scene


def test_sensor_that_sees_no_shape_is_a_clear_error():
    scene = mirad.load_scene(_looking_away())
    with pytest.raises(mirad.SceneError, match="sees no shape"):
        reference_image(scene, spp=1)


def test_scene_without_sensor_is_a_clear_error():
    scene = mirad.load_scene(closed_box(0.5, 1 / np.pi))
    with pytest.raises(mirad.SceneError, match="no sensor"):
        reference_image(scene, spp=1)


def test_reference_image_of_the_furnace_is_flat():
    # inside a white furnace every pixel sees radiance E / (pi (1 - rho)) = 2 / pi
    scene = mirad.load_scene(SCENES / "closed-form" / "furnace.xml")
    img = reference_image(scene, spp=16, seed=1)
    assert img.image.shape[2] == 3 and np.all(img.coverage == 1)
    mean, se = img.image.mean(), np.sqrt((img.stderr ** 2).sum()) / img.stderr.size
    assert abs(mean - 2 / np.pi) <= Z_MAX * se + 1e-6


@pytest.mark.parametrize("options, hint", [({"samples_per_triangle": 0}, "samples_per_triangle"),
                                           ({"method": "hemicube"}, "method"),
                                           ({"max_depth": 0}, "max_depth")])
def test_bad_settings(options, hint):
    scene = mirad.load_scene(SCENES / "closed-form" / "parallel-squares.xml")
    with pytest.raises(mirad.SettingsError, match=hint):
        triangle_reference(scene, **options)


def test_back_side_reference_is_the_flipped_sheets_front(tmp_path):
    """side="back" estimates the other side of a two-sided sheet: the same as the front-side
    estimate of the sheet with its faces flipped (independent seeds, within Z_MAX standard errors)."""
    import sys

    sys.path.insert(0, str(SCENES / "hard-cases"))
    import cases

    scene = mirad.load_scene(cases.sheet_room(tmp_path / "up"))
    flipped = mirad.load_scene(cases.sheet_room(tmp_path / "down", flip=True))
    sheet = np.flatnonzero(scene.tri_shape == scene.shape_index("sheet"))
    back = triangle_reference(scene, samples_per_triangle=4096, seed=3, triangles=sheet, side="back")
    front = triangle_reference(flipped, samples_per_triangle=4096, seed=4, triangles=sheet)
    assert back.side == "back" and np.all(back.radiosity > 0)
    a = scene.tri_area[sheet]
    b, f = (r.radiosity[:, 0] @ a / a.sum() for r in (back, front))
    se = np.hypot(*(np.sqrt(((r.stderr[:, 0] * a) ** 2).sum()) / a.sum() for r in (back, front)))
    assert abs(b - f) <= Z_MAX * se
    with pytest.raises(mirad.errors.SettingsError, match="side"):
        triangle_reference(scene, samples_per_triangle=16, side="top")
