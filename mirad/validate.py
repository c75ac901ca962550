"""Speed against error: mirad's tolerance sweep next to Mitsuba path tracing, on one scene.

``validate(scene)`` measures, on the same machine and against the same high-sample path-traced
reference (``mirad.reference``):

- mirad at each tolerance: wall-clock seconds of ``mirad.solve`` and the per-triangle errors;
- the path tracer used as a per-triangle estimator in its own right at several sample counts
  (``triangle_reference`` with an independent seed): seconds and the same errors;
- the ratio of times at equal area-weighted relative L1 error (1 % and 2 % by default), each
  curve interpolated in log-log; the path tracer's curve may be extrapolated along err ~ t^-1/2
  (its known rate) when its sweep stops short, and the report says so;
- images: mirad's render, the path-traced image and a false-colour relative difference.

It writes ``NAME.md`` (tables), ``NAME-speed-error.png`` (error against seconds, log-log, both
curves) and ``NAME-images.png`` into the output folder, each atomically. Every error is reported
with the reference's own noise floor (``mirad.metrics``).

>>> result = validate("scenes/cornell-box/scene.xml", output_dir="out")    # doctest: +SKIP
>>> result.ratios[0.01]                                                    # doctest: +SKIP
"""

from __future__ import annotations

import datetime as _dt
import io
import math
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401
from .errors import OutputError, SettingsError
from .files import atomic_write, srgb_encode
from .metrics import compare, image_noise_floor, image_relative_l1, image_relative_mse, shape_errors
from .reference import (DEFAULT_CACHE, cached_image, cached_reference, camera_rays, triangle_reference)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

__all__ = ["validate", "ValidationResult", "time_at_error", "DEFAULT_TOLERANCES", "DEFAULT_PT_SAMPLES",
           "DEFAULT_REFERENCE_SAMPLES"]

#: The default sweep stays cheap (seconds to a minute on the shipped scenes); finer tolerances
#: and more samples are for ``validation/run_all.py`` or explicit options.
DEFAULT_TOLERANCES = (0.2, 0.1, 0.05)
DEFAULT_PT_SAMPLES = (16, 64, 256, 1024)
#: Reference paths per triangle on average (allocated by area).
DEFAULT_REFERENCE_SAMPLES = 4096
DEFAULT_TARGETS = (0.01, 0.02)
#: Scenes larger than this are JIT-warmed on the Cornell box rather than by a solve of their own.
WARM_UP_TRIANGLES = 3000


@dataclass
class ValidationResult:
    """Everything ``validate`` measured; ``markdown`` is the report text written to NAME.md."""

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


# ------------------------------------------------------------------------------------------
# Images
# ------------------------------------------------------------------------------------------

def _check_sensor(scene) -> None:
    """Raise SceneError when the scene has no sensor or its sensor sees no shape (1 ray per pixel)."""
    from .errors import SceneError

    for _, ray, _ in camera_rays(scene, spp=1, seed=0):
        if dr.any(scene.mi_scene.ray_test(mi.Ray3f(ray))):
            return
    raise SceneError(f"{scene.source or '<scene>'}: the sensor sees no shape (every camera ray misses the "
                     "geometry); point the sensor at the scene (check its to_world / lookat) or run without "
                     "images (--no-images)")


def _tonemap(image: np.ndarray, scale: float) -> np.ndarray:
    return srgb_encode(np.clip(np.asarray(image) / (scale if scale > 0 else 1.0), 0, 1))


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------

def _check_list(name: str, values, kind) -> tuple:
    try:
        out = tuple(kind(v) for v in values)
    except (TypeError, ValueError):
        raise SettingsError(f"{name}={values!r}: give a list of numbers") from None
    if not out or any(v <= 0 or not math.isfinite(v) for v in out):
        raise SettingsError(f"{name}={values!r}: give one or more positive numbers")
    return out


def validate(scene, *, tolerances=DEFAULT_TOLERANCES, pt_samples=DEFAULT_PT_SAMPLES,
             reference_samples: int = DEFAULT_REFERENCE_SAMPLES, reference_seed: int = 1, targets=DEFAULT_TARGETS,
             images: bool = True, image_spp: int = 64, render_spp: int = 4, output_dir="validation-out",
             name: str | None = None, cache_dir=DEFAULT_CACHE, seed: int = 0, max_seconds: float | None = None,
             quiet: bool = False, write_table: bool = True, progress=None, **solve_options) -> ValidationResult:
    """Sweep mirad's tolerance and the path tracer's samples per triangle; write table, plot, images.

    Parameters
    ----------
    scene : XML path, Mitsuba dict, mi.Scene or mirad.Scene
    tolerances : mirad tolerances to solve at (coarse to fine)
    pt_samples : samples per triangle of the path tracer used as an estimator
    reference_samples : mean paths per triangle of the reference, allocated by area (independent seed)
    reference_seed : seed of the reference (the path-tracer sweep uses other seeds)
    targets : errors (area-weighted relative L1) at which to report the time ratio
    images : also compare images (needs a sensor that sees the scene)
    image_spp : samples per pixel of the path-traced image; render_spp those of mirad's image
    output_dir : folder for NAME.md, NAME-speed-error.png, NAME-images.png (created if missing)
    name : file stem (default: the scene file's folder name, or its stem when not scene.xml)
    cache_dir : reference cache folder (None: no cache)
    seed : mirad's seed
    max_seconds : stop a sweep once its next step would likely exceed this many seconds in all
    quiet : print nothing
    write_table : write NAME.md (``run_all`` collects the markdown into one report instead)
    progress : callable(ValidationResult), called after every step with the results so far
    **solve_options : passed to ``mirad.solve``

    Returns
    -------
    ValidationResult
    """
    import mirad

    tolerances = _check_list("tolerances", tolerances, float)
    pt_samples = _check_list("pt_samples", pt_samples, int)
    targets = _check_list("targets", targets, float)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    loaded = mirad.load_scene(scene)
    if name is None:
        source = Path(loaded.source) if loaded.source else None
        name = "scene" if source is None else (source.parent.name if source.stem == "scene" else source.stem)
    out = Path(output_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder '{out}' ({exc.strerror}); choose another --output") from None
    if not os.access(out, os.W_OK):
        raise OutputError(f"output folder '{out}' is not writable; choose another --output")
    if images:
        _check_sensor(loaded)  # no sensor, or one that sees nothing: fail before the long work
    area = np.asarray(loaded.tri_area, dtype=np.float64)
    say(f"validate {name}: {loaded.triangle_count} triangles, fingerprint {loaded.fingerprint}")
    result = ValidationResult(name=name, scene_source=loaded.source, triangles=loaded.triangle_count,
                              fingerprint=loaded.fingerprint, reference={}, mirad=[], path_tracer=[], ratios={},
                              crossings={}, shapes=[], image={})
    result.targets = targets
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
    ref = cached_reference(loaded, cache_dir=cache_dir, samples_per_triangle=reference_samples,
                           seed=reference_seed, allocation="area", quiet=quiet)
    floor = compare(ref.radiosity, ref.radiosity, ref.stderr, area=area)["noise"]
    result.reference = {"samples_per_triangle": reference_samples, "seed": reference_seed, "seconds": ref.seconds,
                        "paths": ref.paths, "noise": floor, "from_cache": ref.from_cache, "method": ref.method}
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
        est = triangle_reference(loaded, samples_per_triangle=n, seed=reference_seed + 1000 + k)
        spent += est.seconds
        err = compare(est.radiosity, ref.radiosity, ref.stderr, area=area)
        rows.append({"samples": n, "seconds": est.seconds, **err})
        say(f"path tracer {n} samples/triangle: {est.seconds:.2f} s, L1 {err['l1']:.4%}")
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
        err = compare(sol.triangle_radiosity, ref.radiosity, ref.stderr, area=area)
        st = sol.stats
        rows.append({"tolerance": tol, "seconds": dt, "phases": dict(st.get("seconds", {})), **err,
                     "elements": st.get("elements"), "leaves": st.get("leaves"), "links": st.get("links"),
                     "rays": st.get("rays"),
                     # in the norm of the measured columns (over the mean of B, emission included)
                     "estimated_error": st.get("estimated_error_of_mean", st.get("estimated_error"))})
        last_sol = sol
        result.running = ""
        result.shapes = shape_errors(sol.triangle_radiosity, ref.radiosity, area=area, shape=loaded.tri_shape,
                                     stderr=ref.stderr, names=loaded.shape_ids)
        say(f"mirad tolerance {tol:g}: {dt:.2f} s, relative L1 {err['l1']:.4%} of mean(B), RMS {err['rms']:.4%}; "
            f"solver's estimate {st.get('estimated_error', float('nan')):.4%} of mean(B - E)")
        finish(result)
        report(result)

    for line in ratio_lines(result):
        say(line.replace("**", ""))

    # --- images --------------------------------------------------------------------------------------
    if images and last_sol is not None:
        result.image = _compare_images(loaded, last_sol, result, out, name, image_spp=image_spp,
                                       render_spp=render_spp, seed=reference_seed, cache_dir=cache_dir)
        say(f"image: relative L1 {result.image['rel_l1']:.4%}, relative MSE {result.image['relmse']:.4g} "
            f"(reference noise {result.image['noise']:.2g})")
        report(result)

    # --- plot and table ------------------------------------------------------------------------------
    write_outputs(result, out, write_table=write_table)
    say("wrote " + ", ".join(str(p) for p in result.files.values()))
    return result


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


def write_outputs(result: ValidationResult, out, *, write_table: bool = True) -> None:
    """Write NAME-speed-error.png and (optionally) NAME.md for a result, atomically."""
    out = Path(out)
    finish(result)
    plot = out / f"{result.name}-speed-error.png"
    png = _plot(result)
    atomic_write(plot, lambda handle: handle.write(png))
    result.files["plot"] = plot
    result.markdown = markdown(result)
    if write_table:
        table = out / f"{result.name}.md"
        atomic_write(table, lambda handle: handle.write(result.markdown.encode()))
        result.files["table"] = table


def to_json(result: ValidationResult) -> dict:
    """The measured data of a result as plain JSON types (``from_json`` reads it back)."""
    return {"name": result.name, "scene_source": result.scene_source, "triangles": result.triangles,
            "fingerprint": result.fingerprint, "reference": result.reference, "mirad": result.mirad,
            "path_tracer": result.path_tracer, "shapes": result.shapes, "image": result.image,
            "notes": result.notes, "running": getattr(result, "running", ""),
            "targets": list(getattr(result, "targets", DEFAULT_TARGETS)),
            "files": {k: str(v) for k, v in result.files.items()}}


def from_json(data: dict) -> ValidationResult:
    result = ValidationResult(name=data["name"], scene_source=data["scene_source"], triangles=data["triangles"],
                              fingerprint=data["fingerprint"], reference=data["reference"], mirad=data["mirad"],
                              path_tracer=data["path_tracer"], ratios={}, crossings={}, shapes=data["shapes"],
                              image=data["image"], files={k: Path(v) for k, v in data["files"].items()},
                              notes=list(data["notes"]))
    result.running = data.get("running", "")
    result.targets = tuple(data.get("targets", DEFAULT_TARGETS))
    return finish(result)


def _compare_images(scene, sol, result, out: Path, name: str, *, image_spp, render_spp, seed, cache_dir) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import mirad
    ref = cached_image(scene, cache_dir=cache_dir, spp=image_spp, seed=seed)
    t0 = time.perf_counter()
    how = "mirad.render"
    image = np.asarray(mirad.render(scene, sol, spp=render_spp), dtype=np.float64)[..., :3]
    seconds = time.perf_counter() - t0
    mask = ref.coverage >= 1.0
    relmse = image_relative_mse(image, ref.image, mask=mask)
    rel_l1 = image_relative_l1(image, ref.image, mask=mask)
    noise = image_noise_floor(ref.stderr, ref.image, mask=mask)
    lum = ref.image.mean(axis=2)
    scale = float(np.percentile(lum[mask], 99)) if mask.any() else 1.0
    eps = 1e-2 * max(float(lum[mask].mean()) if mask.any() else 1.0, 1e-300)
    diff = (image.mean(axis=2) - lum) / (lum + eps)
    diff = np.where(mask, diff, np.nan)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    axes[0].imshow(_tonemap(image, scale))
    axes[0].set_title("mirad (render)")
    axes[1].imshow(_tonemap(ref.image, scale))
    axes[1].set_title(f"Mitsuba path tracer, {ref.spp} spp")
    im = axes[2].imshow(diff, cmap="coolwarm", vmin=-0.5, vmax=0.5)
    axes[2].set_title(f"(mirad - path) / path; rel. L1 {rel_l1:.2%}, rel. MSE {relmse:.3g}")
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.04)
    for ax in axes:
        ax.set_axis_off()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    path = out / f"{name}-images.png"
    atomic_write(path, lambda handle: handle.write(buf.getvalue()))
    result.files["images"] = path
    return {"relmse": relmse, "rel_l1": rel_l1, "noise": noise, "spp": ref.spp, "render_spp": render_spp, "how": how,
            "reference_seconds": ref.seconds, "render_seconds": seconds,
            "covered_pixels": float(mask.mean())}


def _plot(result: ValidationResult) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    if result.mirad:
        ax.loglog([r["seconds"] for r in result.mirad], [r["l1"] for r in result.mirad], "o-", color="tab:blue",
                  label="mirad (tolerance sweep)")
        for r in result.mirad:
            ax.annotate(f"{r['tolerance']:g}", (r["seconds"], r["l1"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
    if result.path_tracer:
        ax.loglog([r["seconds"] for r in result.path_tracer], [r["l1"] for r in result.path_tracer], "s-",
                  color="tab:orange", label="Mitsuba path tracer (samples/triangle)")
        for r in result.path_tracer:
            ax.annotate(f"{r['samples']}", (r["seconds"], r["l1"]), fontsize=7, xytext=(3, -9),
                        textcoords="offset points")
    ax.axhline(result.reference["noise"]["l1"], color="grey", ls=":", label="reference noise floor (L1)")
    for target in result.ratios:
        ax.axhline(target, color="lightgrey", lw=0.8, zorder=0)
    ax.set_xlabel("seconds (wall clock)")
    ax.set_ylabel("area-weighted relative L1 error per triangle")
    ax.set_title(f"{result.name}: {result.triangles} triangles")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


def machine() -> str:
    """CPU model, core count, OS (for the report)."""
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu or platform.machine()}, {os.cpu_count()} cores ({platform.system()})"


def _pct(x) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{100 * x:.3g} %"


def ratio_lines(result: ValidationResult) -> list[str]:
    """One line per target: the time ratio at equal error, or why there is none."""
    lines = []
    for target, ratio in result.ratios.items():
        (tm, hm), (tp, hp) = result.crossings[target]["mirad"], result.crossings[target]["path_tracer"]
        if ratio is not None:
            bound = {(True, False): "≥ ", (False, True): "≤ "}.get((hm == "at most", hp == "at most"), "")
            if hm == hp == "at most":
                bound = "~ (both bounds) "
            lines.append(f"at {_pct(target)} L1: mirad {tm:.3g} s ({hm}), path tracer {tp:.3g} s ({hp}): "
                         f"**{bound}{ratio:.2f}x**")
        elif tm is None:
            best = min(result.mirad, key=lambda r: r["l1"]) if result.mirad else None
            tail = f"; its best is {_pct(best['l1'])} at {best['seconds']:.2f} s" if best else ""
            lines.append(f"at {_pct(target)} L1: no ratio, mirad did not reach it{tail}"
                         + (f" (path tracer {tp:.3g} s, {hp})" if tp else ""))
        else:
            lines.append(f"at {_pct(target)} L1: no ratio, path tracer {hp} (mirad {tm:.3g} s, {hm})")
    return lines


def markdown(result: ValidationResult) -> str:
    """The report of one scene as markdown (tables, ratios, images)."""
    ref = result.reference
    noise = ref["noise"]
    lines = [f"## {result.name}", "",
             f"- scene: `{result.scene_source or '<scene>'}`, {result.triangles} triangles, fingerprint "
             f"{result.fingerprint}",
             f"- measured {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} on {machine()}, variant {mi.variant()}",
             f"- reference: Mitsuba `path`, method `{ref['method']}`, {ref['samples_per_triangle']} samples/triangle "
             f"({ref['paths']:,} paths, {ref['seconds']:.1f} s{', cached' if ref['from_cache'] else ''}); its noise "
             f"floor: L1 {_pct(noise['l1'])}, RMS {_pct(noise['rms'])}, L∞ scale {_pct(noise['linf'])}",
             "- errors: per input triangle and colour channel, area weighted, relative to the area-weighted mean "
             "reference radiosity; 'RMS corr.' removes the reference noise in quadrature", "",
             "### mirad", "",
             "Errors per triangle are relative to mean(B), emission included; the solver's own estimate "
             "(and its tolerance) is relative to mean(B - E), the reflected light; 'estimated' shows it "
             "converted to mean(B).", "",
             "| tolerance | seconds | refine | visibility | solve | leaves | links | rays | rel. L1 | rel. RMS | "
             "RMS corr. | rel. L∞ | estimated |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result.mirad:
        ph = r["phases"]
        f = lambda k: f"{ph[k]:.2f}" if isinstance(ph.get(k), (int, float)) else "–"  # noqa: E731
        est = r["estimated_error"]
        lines.append(f"| {r['tolerance']:g} | {r['seconds']:.2f} | {f('refine')} | {f('visibility')} | {f('solve')} | "
                     f"{r['leaves'] or 0:,} | {r['links'] or 0:,} | {r['rays'] or 0:,} | {_pct(r['l1'])} | "
                     f"{_pct(r['rms'])} | {_pct(r['rms_corrected'])} | {_pct(r['linf'])} | "
                     f"{_pct(est) if isinstance(est, (int, float)) else '–'} |")
    lines += ["", "### Mitsuba path tracer as a per-triangle estimator", "",
              "| samples/triangle | seconds | rel. L1 | rel. RMS | RMS corr. | rel. L∞ |", "|---:|---:|---:|---:|---:|---:|"]
    for r in result.path_tracer:
        lines.append(f"| {r['samples']} | {r['seconds']:.2f} | {_pct(r['l1'])} | {_pct(r['rms'])} | "
                     f"{_pct(r['rms_corrected'])} | {_pct(r['linf'])} |")
    if result.running:
        lines += ["", f"**{result.running} did not finish within the time limit**; the rows above are what "
                  "finished."]
    lines += ["", "### Time ratio at equal error (path tracer seconds / mirad seconds)", ""]
    lines += [f"- {x}" for x in ratio_lines(result)]
    lines += ["", f"![speed against error]({result.files.get('plot', Path(result.name + '-speed-error.png')).name})", ""]
    if result.shapes:
        finest = result.mirad[-1]["tolerance"]
        lines += [f"### Per shape (mirad at tolerance {finest:g})", "",
                  "| shape | triangles | reference B | mirad B | rel. error | reference noise |",
                  "|---|---:|---:|---:|---:|---:|"]
        for s in result.shapes:
            lines.append(f"| {s['shape']} | {s['triangles']} | {s['reference']:.4g} | {s['value']:.4g} | "
                         f"{_pct(s['error'])} | {_pct(s['noise'])} |")
        lines.append("")
    if result.image:
        im = result.image
        lines += ["### Images", "",
                  f"mirad image: {im['how']} ({im['render_spp']} spp); path-traced image {im['spp']} spp "
                  f"({im['reference_seconds']:.1f} s). Over fully covered pixels "
                  f"({100 * im['covered_pixels']:.0f} % of the image): relative L1 {_pct(im.get('rel_l1'))} "
                  f"(sum |I - R| / sum R, robust), relative MSE {im['relmse']:.4g} (decided by the few pixels "
                  f"with the largest relative error); the reference image's own noise contributes "
                  f"{im['noise']:.2g} to the MSE.", "",
                  f"![mirad, path tracer, relative difference]({result.files['images'].name})", ""]
    for note in result.notes:
        lines.append(f"- note: {note}")
    return "\n".join(lines).rstrip() + "\n"
