"""Metrics on synthetic arrays with known answers, and against a naive loop."""

import numpy as np
import pytest

from mirad.metrics import (SQRT_2_OVER_PI, compare, image_noise_floor, image_relative_mse, noise_floor,
                           relative_l1, relative_linf, relative_rms, shape_errors)


def test_known_answers_on_two_triangles():
    ref = np.array([[1.0], [3.0]])
    val = np.array([[1.5], [2.0]])
    area = np.array([1.0, 3.0])
    # area-weighted mean of ref = (1 + 9) / 4 = 2.5
    assert relative_l1(val, ref, area=area) == pytest.approx((0.5 + 3.0) / 10.0)
    assert relative_rms(val, ref, area=area) == pytest.approx(np.sqrt((0.25 + 3.0) / 4) / 2.5)
    assert relative_linf(val, ref, area=area) == pytest.approx(1.0 / 2.5)


def test_exact_solution_has_zero_error_and_scale_invariance():
    rng = np.random.default_rng(0)
    ref = rng.random((50, 3)) + 0.1
    area = rng.random(50)
    assert relative_l1(ref, ref, area=area) == 0.0
    val = ref * (1 + 0.1 * rng.standard_normal(ref.shape))
    for f in (relative_l1, relative_rms, relative_linf):
        assert f(7.0 * val, 7.0 * ref, area=area) == pytest.approx(f(val, ref, area=area))


def test_uniform_relative_error_gives_that_l1():
    ref = np.random.default_rng(1).random((20, 3)) + 0.5
    assert relative_l1(1.03 * ref, ref, area=np.ones(20)) == pytest.approx(0.03)


def test_matches_naive_loop():
    rng = np.random.default_rng(2)
    ref, val, area = rng.random((15, 3)) + 0.2, rng.random((15, 3)) + 0.2, rng.random(15)
    num = den = sq = 0.0
    worst = 0.0
    for i in range(15):
        for c in range(3):
            num += area[i] * abs(val[i, c] - ref[i, c])
            den += area[i] * ref[i, c]
            sq += area[i] * (val[i, c] - ref[i, c]) ** 2
            worst = max(worst, abs(val[i, c] - ref[i, c]))
    mean = den / (3 * area.sum())
    assert relative_l1(val, ref, area=area) == pytest.approx(num / den)
    assert relative_rms(val, ref, area=area) == pytest.approx(np.sqrt(sq / (3 * area.sum())) / mean)
    assert relative_linf(val, ref, area=area) == pytest.approx(worst / mean)


def test_noise_floor_predicts_the_error_of_a_perfect_solution():
    # a perfect solution against a noisy reference: the measured L1 and RMS are the floor
    rng = np.random.default_rng(3)
    truth = np.full((20000, 3), 2.0)
    sigma = np.full_like(truth, 0.02)
    noisy = truth + sigma * rng.standard_normal(truth.shape)
    floor = noise_floor(sigma, noisy, area=np.ones(20000))
    assert floor["l1"] == pytest.approx(SQRT_2_OVER_PI * 0.01, rel=0.01)
    assert relative_l1(truth, noisy, area=np.ones(20000)) == pytest.approx(floor["l1"], rel=0.02)
    assert relative_rms(truth, noisy, area=np.ones(20000)) == pytest.approx(floor["rms"], rel=0.02)
    # and compare() removes it in quadrature from RMS
    biased = truth * 1.05
    res = compare(biased, noisy, sigma, area=np.ones(20000))
    assert res["rms_corrected"] == pytest.approx(0.05, rel=0.02)


def test_shape_errors_of_shape_means():
    ref = np.array([[1.0], [3.0], [2.0]])
    val = np.array([[2.0], [2.0], [2.2]])
    rows = shape_errors(val, ref, area=np.array([1.0, 1.0, 2.0]), shape=np.array([0, 0, 1]),
                        stderr=np.array([[0.1], [0.1], [0.2]]), names=["a", "b"])
    assert [r["shape"] for r in rows] == ["a", "b"]
    assert rows[0]["error"] == pytest.approx(0.0)          # means 2 and 2
    assert rows[1]["error"] == pytest.approx(0.1)
    assert rows[0]["noise"] == pytest.approx(np.sqrt(0.01 + 0.01) / 2 / 2)
    assert rows[1]["triangles"] == 1


def test_image_relative_mse():
    ref = np.ones((4, 5, 3))
    assert image_relative_mse(ref, ref) == 0.0
    # 10 % everywhere: (0.1^2) / (1 + 0.01) per pixel
    assert image_relative_mse(1.1 * ref, ref) == pytest.approx(0.01 / 1.01)
    mask = np.zeros((4, 5), bool)
    mask[0, 0] = True
    img = ref.copy()
    img[1:, :] = 5.0
    assert image_relative_mse(img, ref, mask=mask) == 0.0
    assert image_noise_floor(0.1 * ref, ref) == pytest.approx(0.01 / 1.01)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="same"):
        relative_l1(np.ones((3, 3)), np.ones((4, 3)))
    with pytest.raises(ValueError, match="zero everywhere"):
        relative_l1(np.ones((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="area"):
        relative_l1(np.ones((3, 3)), np.ones((3, 3)), area=np.ones(2))


def test_image_relative_l1_is_scale_free_and_robust_to_a_few_bright_pixels():
    from mirad.metrics import image_relative_l1, image_relative_mse

    rng = np.random.default_rng(0)
    ref = rng.uniform(0.5, 1.0, (32, 32, 3))
    assert image_relative_l1(1.1 * ref, ref) == pytest.approx(0.1)
    assert image_relative_l1(10 * 1.1 * ref, 10 * ref) == pytest.approx(0.1)
    spoiled = ref.copy()
    spoiled[:3, :3] = 0.0                                   # 9 of 1024 pixels black (a missed light)
    dark = ref * 1e-3
    dark[:3, :3] = ref[:3, :3]
    # relative MSE: the few near-black reference pixels decide it; relative L1 stays at their share
    assert image_relative_l1(spoiled, ref) == pytest.approx(ref[:3, :3].sum() / ref.sum())
    assert image_relative_mse(dark * 0 + ref, dark) > 100 * image_relative_l1(spoiled, ref)
