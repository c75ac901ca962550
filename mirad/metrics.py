"""Error metrics of a radiosity solution against a reference, each with the reference's own noise.

All per-triangle metrics are area weighted and relative to the area-weighted mean reference
radiosity over triangles and channels, m = sum(A_i Bref_ic) / (C sum(A_i)):

- relative L1   = sum_ic A_i |B_ic - Bref_ic| / sum_ic A_i Bref_ic
- relative RMS  = sqrt(sum_ic A_i (B_ic - Bref_ic)^2 / (C sum A_i)) / m
- relative Linf = max_ic |B_ic - Bref_ic| / m

Next to each, the *noise floor*: the value the metric would take for a perfect solution compared
with this noisy reference (per-triangle reference errors taken as independent normal variables
with the reference's standard errors): sqrt(2/pi) sum A sigma / sum A Bref for L1, the area-weighted
RMS of sigma / m for RMS, and max sigma / m for Linf (a noise *scale*; the expected maximum over
many triangles is a few times larger). A measured error close to its floor is reference noise, not
solver error. ``rms_corrected`` removes the floor in quadrature (errors and noise are independent).

Reductions are in float64. Data first, options keyword-only.

>>> import numpy as np
>>> round(relative_l1(np.array([[1.1], [0.9]]), np.array([[1.0], [1.0]]), area=np.array([1.0, 1.0])), 12)
0.1
"""

from __future__ import annotations

import numpy as np

from .arrays import group_mean, group_sum

__all__ = ["relative_l1", "relative_rms", "relative_linf", "noise_floor", "shape_errors",
           "image_relative_mse", "image_noise_floor", "compare", "SQRT_2_OVER_PI"]

#: E|X| = sqrt(2/pi) sigma for X ~ N(0, sigma^2).
SQRT_2_OVER_PI = float(np.sqrt(2.0 / np.pi))
#: Regulariser of the per-pixel relative MSE, relative to the squared mean reference pixel.
IMAGE_EPSILON = 1e-2


def _prepare(value, reference, area):
    value = np.asarray(value, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if value.ndim == 1:
        value = value[:, None]
    if reference.ndim == 1:
        reference = reference[:, None]
    if value.shape != reference.shape:
        raise ValueError(f"value {value.shape} and reference {reference.shape} must have the same (T, C) shape")
    area = np.ones(len(value)) if area is None else np.asarray(area, dtype=np.float64).ravel()
    if area.shape != (len(value),):
        raise ValueError(f"area must be (T,) = ({len(value)},); got {area.shape}")
    if np.any(area < 0) or not np.all(np.isfinite(area)):
        raise ValueError("area must be finite and non-negative")
    return value, reference, area


def _mean(reference: np.ndarray, area: np.ndarray) -> float:
    """Area-weighted mean of the reference over triangles and channels."""
    total = float((area[:, None] * reference).sum())
    weight = float(area.sum()) * reference.shape[1]
    if weight <= 0 or total <= 0:
        raise ValueError("the reference is zero everywhere (or the area is zero); relative errors are undefined")
    return total / weight


def relative_l1(value, reference, *, area=None) -> float:
    """Area-weighted relative L1 error of (T, C) values against a (T, C) reference."""
    value, reference, area = _prepare(value, reference, area)
    m = _mean(reference, area)
    return float((area[:, None] * np.abs(value - reference)).sum() / (m * area.sum() * reference.shape[1]))


def relative_rms(value, reference, *, area=None) -> float:
    """Area-weighted RMS error over triangles and channels, divided by the area-weighted mean."""
    value, reference, area = _prepare(value, reference, area)
    m = _mean(reference, area)
    ms = (area[:, None] * (value - reference) ** 2).sum() / (area.sum() * reference.shape[1])
    return float(np.sqrt(ms) / m)


def relative_linf(value, reference, *, area=None) -> float:
    """Largest absolute error over triangles and channels, divided by the area-weighted mean."""
    value, reference, area = _prepare(value, reference, area)
    m = _mean(reference, area)
    return float(np.abs(value - reference).max() / m)


def noise_floor(stderr, reference, *, area=None) -> dict:
    """The L1, RMS and Linf a perfect solution would show against a reference with this stderr.

    Returns {"l1", "rms", "linf"}, each relative to the area-weighted mean reference.
    """
    stderr, reference, area = _prepare(stderr, reference, area)
    m = _mean(reference, area)
    norm = m * area.sum() * reference.shape[1]
    return {"l1": float(SQRT_2_OVER_PI * (area[:, None] * stderr).sum() / norm),
            "rms": float(np.sqrt((area[:, None] * stderr ** 2).sum() / (area.sum() * reference.shape[1])) / m),
            "linf": float(stderr.max() / m)}


def shape_errors(value, reference, *, area, shape, stderr=None, names=None) -> list[dict]:
    """Per shape: relative error of the area-weighted mean radiosity (mean over channels).

    Parameters
    ----------
    value, reference : (T, C) float
    area : (T,) float
    shape : (T,) int   shape index of each triangle
    stderr : (T, C) float, optional reference standard errors (gives each shape's noise)
    names : list[str], optional shape ids

    Returns
    -------
    list of {"shape", "triangles", "reference", "value", "error", "noise"}; "error" is
    sum_c |mean B - mean Bref| / sum_c mean Bref over the shape, "noise" the same ratio for
    the reference's standard error of the shape mean (NaN without stderr).
    """
    value, reference, area = _prepare(value, reference, area)
    shape = np.asarray(shape, dtype=np.int64).ravel()
    count = int(shape.max()) + 1 if len(shape) else 0
    weight = np.bincount(shape, weights=area, minlength=count)
    rows = []
    mean_v = group_mean(shape, value, count, weights=area)
    mean_r = group_mean(shape, reference, count, weights=area)
    if stderr is not None:
        s = np.asarray(stderr, dtype=np.float64).reshape(reference.shape)
        var = group_sum(shape, (area[:, None] * s) ** 2, count)
        se = np.sqrt(var) / np.maximum(weight, 1e-300)[:, None]
    tri_count = np.bincount(shape, minlength=count)
    for k in range(count):
        if tri_count[k] == 0:
            continue
        denom = mean_r[k].sum()
        err = np.abs(mean_v[k] - mean_r[k]).sum() / denom if denom > 0 else np.nan
        noise = se[k].sum() / denom if (stderr is not None and denom > 0) else np.nan
        rows.append({"shape": names[k] if names is not None else k, "triangles": int(tri_count[k]),
                     "reference": float(mean_r[k].mean()), "value": float(mean_v[k].mean()),
                     "error": float(err), "noise": float(noise)})
    return rows


def _masked_pixels(image, reference, mask) -> tuple:
    """(image, reference) pixels (N, C) float64 selected by mask (H, W) bool (all if None)."""
    image = np.asarray(image, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    if image.shape != reference.shape:
        raise ValueError(f"image {image.shape} and reference {reference.shape} must have the same shape")
    sel = np.ones(image.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if not sel.any():
        raise ValueError("the mask selects no pixel")
    return image[sel], reference[sel]


def image_relative_mse(image, reference, *, mask=None) -> float:
    """Mean per-pixel relative squared error (I - R)^2 / (R^2 + eps), eps = 1e-2 mean(R)^2.

    Scale free: multiplying both images by a constant leaves it unchanged. ``mask`` (H, W) bool
    restricts the mean to some pixels (e.g. fully covered ones).
    """
    i, r = _masked_pixels(image, reference, mask)
    eps = IMAGE_EPSILON * max(float(r.mean()), 1e-300) ** 2
    return float(np.mean((i - r) ** 2 / (r * r + eps)))


def image_relative_l1(image, reference, *, mask=None) -> float:
    """Relative L1 of an image: sum |I - R| over sum R (pixels and channels in ``mask``).

    A robust companion of ``image_relative_mse``: each pixel counts in proportion to its
    brightness, not to its squared relative error, so a few pixels at shadow edges or on a
    light do not decide it. Scale free.
    """
    i, r = _masked_pixels(image, reference, mask)
    return float(np.abs(i - r).sum() / max(float(r.sum()), 1e-300))


def image_noise_floor(stderr, reference, *, mask=None) -> float:
    """The relative MSE a perfect image would show against this noisy reference: mean sigma^2/(R^2+eps)."""
    stderr = np.asarray(stderr, dtype=np.float64)
    reference = np.asarray(reference, dtype=np.float64)
    sel = np.ones(reference.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    r = reference[sel]
    eps = IMAGE_EPSILON * max(float(r.mean()), 1e-300) ** 2
    return float(np.mean(stderr[sel] ** 2 / (r * r + eps)))


def compare(value, reference, stderr, *, area) -> dict:
    """Every per-triangle metric with its noise floor.

    Returns {"l1", "rms", "linf", "rms_corrected", "noise": {"l1", "rms", "linf"}}.
    """
    floor = noise_floor(stderr, reference, area=area)
    rms = relative_rms(value, reference, area=area)
    return {"l1": relative_l1(value, reference, area=area), "rms": rms,
            "linf": relative_linf(value, reference, area=area),
            "rms_corrected": float(np.sqrt(max(rms * rms - floor["rms"] ** 2, 0.0))), "noise": floor}
