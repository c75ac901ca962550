"""Measurement half of ``mirad validate``: mirad's tolerance sweep next to Mitsuba path tracing.

``measure(scene)`` measures, on the same machine and against the same high-sample path-traced
reference (``mirad.reference``), and returns plain numbers (``ValidationResult``: dicts, lists
and, for the images, arrays); ``mirad.report`` turns them into a plot, markdown and JSON, and
``mirad.validate`` runs both. Measured:

- mirad at each tolerance: wall-clock seconds of ``mirad.solve`` and the per-patch errors;
- the path tracer used as a per-patch estimator in its own right at several sample counts
  (``triangle_reference`` with an independent seed): seconds and the same errors;
- the ratio of times at equal area-weighted relative L1 error (``finish``), each curve
  interpolated in log-log; the path tracer's curve may be extrapolated along err ~ t^-1/2 (its
  known rate) when its sweep stops short;
- images (optional): mirad's render, the path-traced image, their relative L1 and MSE.

Patches are the front side of every input triangle and, where the BSDF is two-sided, its back
side: the reference then runs a back-side pass (``side="back"``) and every error covers both
sides, so walls lit on their back are measured instead of reading "n/a".

>>> result = measure("scenes/cornell-box/scene.xml", images=False)      # doctest: +SKIP
>>> result.mirad[-1]["l1"]                                              # doctest: +SKIP
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401
from .errors import SceneError, SettingsError
from .metrics import compare, image_noise_floor, image_relative_l1, image_relative_mse, shape_errors
from .reference import DEFAULT_CACHE, cached_image, cached_reference, camera_rays, triangle_reference
from .solution import estimate_norm

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["measure", "ValidationResult", "Patches", "time_at_error", "finish", "check_sensor", "compare_images",
           "DEFAULT_TOLERANCES", "DEFAULT_PT_SAMPLES", "DEFAULT_REFERENCE_SAMPLES", "DEFAULT_TARGETS"]

#: The default sweep stays cheap (seconds to a minute on the shipped scenes); finer tolerances
#: and more samples are for ``validation/run_all.py`` or explicit options.
DEFAULT_TOLERANCES = (0.2, 0.1, 0.05)
DEFAULT_PT_SAMPLES = (16, 64, 256, 1024)
#: Reference paths per triangle side on average (allocated by area).
DEFAULT_REFERENCE_SAMPLES = 4096
DEFAULT_TARGETS = (0.01, 0.02)
#: Scenes larger than this are JIT-warmed on the Cornell box rather than by a solve of their own.
WARM_UP_TRIANGLES = 3000


@dataclass
class ValidationResult:
    """Everything ``measure`` measured. ``images`` holds the compared images as arrays (not
    saved to JSON); ``files`` and ``markdown`` are filled by ``mirad.report.write_outputs``."""

    name: str
    scene_source: str | None
    triangles: int
    fingerprint: str
    reference: dict
    mirad: list
    path_tracer: list
    ratios: dict
    crossings: dict
    shapes: list
    image: dict
    files: dict = field(default_factory=dict)
    markdown: str = ""
    notes: list = field(default_factory=list)
    running: str = ""
    targets: tuple = DEFAULT_TARGETS
    images: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------
# Patches: the sides compared
# ------------------------------------------------------------------------------------------

@dataclass
class Patches:
    """The triangle sides compared: every front side, then the back side of each triangle with
    a two-sided BSDF. ``back`` (B,) int are those triangles; ``area`` (T + B,) m^2, ``shape``
    (T + B,) int (back sides numbered after the S shapes) and ``names`` (S or 2 S,) the shape
    ids, back sides as "<id> (back)"."""

    back: np.ndarray
    area: np.ndarray
    shape: np.ndarray
    names: list

    @classmethod
    def of(cls, scene) -> "Patches":
        back = np.asarray(scene.back_triangles, dtype=np.int64)
        area = np.asarray(scene.tri_area, dtype=np.float64)
        names = list(scene.shape_ids)
        shape = np.asarray(scene.tri_shape, dtype=np.int64)
        if len(back):
            shape = np.concatenate([shape, shape[back] + len(names)])
            names = names + [f"{n} (back)" for n in names]
            area = np.concatenate([area, area[back]])
        return cls(back, area, shape, names)

    def values(self, front: np.ndarray, back: np.ndarray | None) -> np.ndarray:
        """(T + B, C): ``front`` (T, C), then ``back`` (B, C), the rows of ``self.back``."""
        return front if not len(self.back) else np.concatenate([front, back])

    def of_solution(self, sol) -> np.ndarray:
        """(T + B, C) W/m^2: a solution's radiosity on the patches compared."""
        back = sol.back_radiosity[self.back] if len(self.back) else None
        return self.values(sol.triangle_radiosity, back)


def _reference(scene, patches: Patches, *, cache_dir, samples: int, seed: int, quiet: bool):
    """Reference radiosity and stderr (T + B, C) of both sides, the paths, seconds and method."""
    front = cached_reference(scene, cache_dir=cache_dir, samples_per_triangle=samples, seed=seed,
                             allocation="area", quiet=quiet)
    if not len(patches.back):
        return front.radiosity, front.stderr, front
    back = cached_reference(scene, cache_dir=cache_dir, samples_per_triangle=samples, seed=seed,
                            allocation="area", quiet=quiet, triangles=patches.back, side="back")
    front.paths += back.paths
    front.seconds += back.seconds
    front.from_cache = front.from_cache and back.from_cache
    return (patches.values(front.radiosity, back.radiosity), patches.values(front.stderr, back.stderr), front)


def _estimate(scene, patches: Patches, samples: int, seed: int):
    """The path tracer as an estimator of both sides: ((T + B, C) radiosity, seconds)."""
    est = triangle_reference(scene, samples_per_triangle=samples, seed=seed)
    if not len(patches.back):
        return est.radiosity, est.seconds
    back = triangle_reference(scene, samples_per_triangle=samples, seed=seed, triangles=patches.back, side="back")
    return patches.values(est.radiosity, back.radiosity), est.seconds + back.seconds


# ------------------------------------------------------------------------------------------
# Interpolation of the speed-error curves
# ------------------------------------------------------------------------------------------

def time_at_error(seconds, errors, target: float, *, extrapolate_slope: float | None = None):
    """Seconds at which a curve first reaches ``target`` error, interpolated in log-log.

    Points are taken in the order given, which is the sweep's order of increasing cost (coarse to
    fine tolerance, few to many samples): measured seconds of small runs are too noisy on a shared
    machine to order the points by. Returns (seconds or None, how) with how one of
    "at most" (the quickest point is already at or below the target: an upper bound),
    "interpolated", "extrapolated" (beyond the last point along err ~ t^slope; only when
    ``extrapolate_slope`` is given) or "not reached".
    """
    t = np.asarray(seconds, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    if len(t) == 0:
        return None, "not reached"
    if e[0] <= target:
        return float(t[0]), "at most"
    for k in range(1, len(t)):
        if e[k] <= target:
            if e[k] == e[k - 1] or t[k - 1] <= 0:
                return float(t[k]), "at most"
            lt = np.interp(np.log(target), [np.log(e[k]), np.log(e[k - 1])], [np.log(t[k]), np.log(t[k - 1])])
            return float(np.exp(lt)), "interpolated"
    if extrapolate_slope is not None and e[-1] > 0 and t[-1] > 0:
        return float(t[-1] * (target / e[-1]) ** (1.0 / extrapolate_slope)), "extrapolated"
    return None, "not reached"


def finish(result: ValidationResult) -> ValidationResult:
    """(Re)compute the crossings and time ratios of a result from its rows."""
    floor = result.reference.get("noise", {}).get("l1", 0.0)
    rows, pt_rows = result.mirad, result.path_tracer
    for target in getattr(result, "targets", DEFAULT_TARGETS):
        tm, how_m = time_at_error([r["seconds"] for r in rows], [r["l1"] for r in rows], target)
        if target < 2 * floor:
            tp, how_p = None, "below twice the reference noise floor"
            tp_i, how_i = time_at_error([r["seconds"] for r in pt_rows], [r["l1"] for r in pt_rows], target)
            if tp_i is not None:
                tp, how_p = tp_i, how_i
        else:
            tp, how_p = time_at_error([r["seconds"] for r in pt_rows], [r["l1"] for r in pt_rows], target,
                                      extrapolate_slope=-0.5)
        result.crossings[target] = {"mirad": (tm, how_m), "path_tracer": (tp, how_p)}
        result.ratios[target] = tp / tm if (tm and tp) else None
    return result


# ------------------------------------------------------------------------------------------
# Images
# ------------------------------------------------------------------------------------------

def check_sensor(scene) -> None:
    """Raise SceneError when the scene has no sensor or its sensor sees no shape (1 ray per pixel)."""
    for _, ray, _ in camera_rays(scene, spp=1, seed=0):
        if dr.any(scene.mi_scene.ray_test(mi.Ray3f(ray))):
            return
    raise SceneError(f"{scene.source or '<scene>'}: the sensor sees no shape (every camera ray misses the "
                     "geometry); point the sensor at the scene (check its to_world / lookat) or run without "
                     "images (--no-images)")


def compare_images(scene, sol, *, image_spp: int, render_spp: int, seed: int, cache_dir) -> tuple[dict, dict]:
    """mirad's render against the path-traced image over fully covered pixels.

    Returns (metrics, arrays): metrics {"relmse", "rel_l1", "noise", "spp", "render_spp", "how",
    "reference_seconds", "render_seconds", "covered_pixels"}; arrays {"image", "reference" (H, W, 3)
    radiance W/(m^2 sr), "mask" (H, W) bool, "spp"}.
    """
    import mirad

    ref = cached_image(scene, cache_dir=cache_dir, spp=image_spp, seed=seed)
    t0 = time.perf_counter()
    image = np.asarray(mirad.render(scene, sol, spp=render_spp), dtype=np.float64)[..., :3]
    seconds = time.perf_counter() - t0
    mask = ref.coverage >= 1.0
    metrics = {"relmse": image_relative_mse(image, ref.image, mask=mask),
               "rel_l1": image_relative_l1(image, ref.image, mask=mask),
               "noise": image_noise_floor(ref.stderr, ref.image, mask=mask), "spp": ref.spp,
               "render_spp": render_spp, "how": "mirad.render", "reference_seconds": ref.seconds,
               "render_seconds": seconds, "covered_pixels": float(mask.mean())}
    return metrics, {"image": image, "reference": ref.image, "mask": mask, "spp": ref.spp}


# ------------------------------------------------------------------------------------------
# The sweep
# ------------------------------------------------------------------------------------------

def check_list(name: str, values, kind) -> tuple:
    """``values`` as a tuple of positive finite ``kind``; SettingsError naming ``name`` otherwise."""
    try:
        out = tuple(kind(v) for v in values)
    except (TypeError, ValueError):
        raise SettingsError(f"{name}={values!r}: give a list of numbers") from None
    if not out or any(v <= 0 or not math.isfinite(v) for v in out):
        raise SettingsError(f"{name}={values!r}: give one or more positive numbers")
    return out


def scene_name(loaded) -> str:
    """The scene file's folder name when it is scene.xml, else its stem; "scene" without a file."""
    source = Path(loaded.source) if loaded.source else None
    return "scene" if source is None else (source.parent.name if source.stem == "scene" else source.stem)


def measure(scene, *, tolerances=DEFAULT_TOLERANCES, pt_samples=DEFAULT_PT_SAMPLES,
            reference_samples: int = DEFAULT_REFERENCE_SAMPLES, reference_seed: int = 1, targets=DEFAULT_TARGETS,
            images: bool = True, image_spp: int = 64, render_spp: int = 4, name: str | None = None,
            cache_dir=DEFAULT_CACHE, seed: int = 0, max_seconds: float | None = None, quiet: bool = False,
            progress=None, **solve_options) -> ValidationResult:
    """Sweep mirad's tolerance and the path tracer's samples per triangle; no file is written.

    Parameters are those of ``mirad.validate.validate`` without the output options; ``progress``
    (callable(ValidationResult)) is called after every step with the results so far.

    Returns
    -------
    ValidationResult (errors relative to the reference's area-weighted mean radiosity, over
    every front side and the back sides of two-sided BSDFs)
    """
    import mirad

    tolerances = check_list("tolerances", tolerances, float)
    pt_samples = check_list("pt_samples", pt_samples, int)
    targets = check_list("targets", targets, float)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    loaded = mirad.load_scene(scene)
    name = scene_name(loaded) if name is None else name
    if images:
        check_sensor(loaded)  # no sensor, or one that sees nothing: fail before the long work
    patches = Patches.of(loaded)
    area = patches.area
    sides = f", {len(patches.back)} of them two-sided (back sides compared too)" if len(patches.back) else ""
    say(f"validate {name}: {loaded.triangle_count} triangles{sides}, fingerprint {loaded.fingerprint}")
    result = ValidationResult(name=name, scene_source=loaded.source, triangles=loaded.triangle_count,
                              fingerprint=loaded.fingerprint, reference={}, mirad=[], path_tracer=[], ratios={},
                              crossings={}, shapes=[], image={}, targets=targets)
    report = progress or (lambda r: None)

    # --- warm-up (JIT compilation is not part of either timing) --------------------------------
    # A large scene is warmed up on the Cornell box instead: compiling is then negligible next to
    # its solve, and its own coarsest solve may take minutes.
    if loaded.triangle_count <= WARM_UP_TRIANGLES:
        mirad.solve(loaded, tolerance=max(tolerances), seed=seed, **solve_options)
    else:
        mirad.solve(mi.cornell_box(), tolerance=0.2, seed=seed)
        result.notes.append(f"JIT warm-up on the Cornell box (scene over {WARM_UP_TRIANGLES} triangles): "
                            "mirad's first timing may include a little kernel compilation")
    triangle_reference(loaded, samples_per_triangle=2, seed=999, triangles=np.arange(min(64, loaded.triangle_count)))

    # --- reference -----------------------------------------------------------------------------
    ref_b, ref_se, ref = _reference(loaded, patches, cache_dir=cache_dir, samples=reference_samples,
                                    seed=reference_seed, quiet=quiet)
    floor = compare(ref_b, ref_b, ref_se, area=area)["noise"]
    result.reference = {"samples_per_triangle": reference_samples, "seed": reference_seed, "seconds": ref.seconds,
                        "paths": ref.paths, "noise": floor, "from_cache": ref.from_cache, "method": ref.method,
                        "back_sides": int(len(patches.back))}
    say(f"reference: {reference_samples} samples/triangle on average (by area), {ref.seconds:.1f} s"
        f"{' (from cache)' if ref.from_cache else ''}; noise floor L1 {floor['l1']:.4%}, RMS {floor['rms']:.4%}")
    report(result)

    # --- path tracer as an estimator -------------------------------------------------------------
    triangle_reference(loaded, samples_per_triangle=min(pt_samples), seed=998)  # warm-up at full width
    spent = 0.0
    for k, n in enumerate(sorted(pt_samples)):
        rows = result.path_tracer
        if max_seconds is not None and rows and spent + 4 * rows[-1]["seconds"] > max_seconds:
            result.notes.append(f"path-tracer sweep stopped before {n} samples/triangle (budget {max_seconds:g} s)")
            say(result.notes[-1])
            break
        est, seconds = _estimate(loaded, patches, n, reference_seed + 1000 + k)
        spent += seconds
        err = compare(est, ref_b, ref_se, area=area)
        rows.append({"samples": n, "seconds": seconds, **err})
        say(f"path tracer {n} samples/triangle: {seconds:.2f} s, L1 {err['l1']:.4%}")
        finish(result)
        report(result)

    # --- mirad sweep ------------------------------------------------------------------------------
    spent, last_sol = 0.0, None
    for tol in sorted(tolerances, reverse=True):
        rows = result.mirad
        if max_seconds is not None and rows and spent + 4 * rows[-1]["seconds"] > max_seconds:
            result.notes.append(f"mirad sweep stopped before tolerance {tol:g} (budget {max_seconds:g} s)")
            say(result.notes[-1])
            break
        result.running = f"mirad at tolerance {tol:g}"
        report(result)
        t0 = time.perf_counter()
        sol = mirad.solve(loaded, tolerance=tol, seed=seed, **solve_options)
        dt = time.perf_counter() - t0
        spent += dt
        value = patches.of_solution(sol)
        err = compare(value, ref_b, ref_se, area=area)
        st = sol.stats
        rows.append({"tolerance": tol, "seconds": dt, "phases": dict(st.get("seconds", {})), **err,
                     "elements": st.get("elements"), "leaves": st.get("leaves"), "links": st.get("links"),
                     "rays": st.get("rays"),
                     # in the norm of the measured columns (over the mean of B, emission included)
                     "estimated_error": st.get("estimated_error_of_mean", st.get("estimated_error"))})
        last_sol = sol
        result.running = ""
        result.shapes = shape_errors(value, ref_b, area=area, shape=patches.shape, stderr=ref_se,
                                     names=patches.names)
        say(f"mirad tolerance {tol:g}: {dt:.2f} s, relative L1 {err['l1']:.4%} of mean(B), RMS {err['rms']:.4%}; "
            f"solver's estimate {st.get('estimated_error', float('nan')):.4%} of {estimate_norm(st)}")
        finish(result)
        report(result)

    # --- images --------------------------------------------------------------------------------------
    if images and last_sol is not None:
        result.image, result.images = compare_images(loaded, last_sol, image_spp=image_spp, render_spp=render_spp,
                                                     seed=reference_seed, cache_dir=cache_dir)
        say(f"image: relative L1 {result.image['rel_l1']:.4%}, relative MSE {result.image['relmse']:.4g} "
            f"(reference noise {result.image['noise']:.2g})")
        report(result)
    return finish(result)
