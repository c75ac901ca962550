"""Report half of ``mirad validate``: plots, markdown and JSON of a ``ValidationResult``.

``write_outputs(result, folder)`` writes ``NAME-speed-error.png`` (error against seconds,
log-log, both curves), ``NAME-images.png`` (mirad, path tracer, relative difference; when the
result holds images) and ``NAME.md`` (tables), each atomically. ``to_json`` / ``from_json``
keep a result's numbers (not its images) between processes (``validation/run_all.py``).
Nothing here measures: the numbers come from ``mirad.measure``.
"""

from __future__ import annotations

import datetime as _dt
import io
import math
import os
import platform
from pathlib import Path

import numpy as np

from . import _runtime  # noqa: F401
from .files import atomic_write, srgb_encode
from .measure import DEFAULT_TARGETS, ValidationResult, finish

import mitsuba as mi  # noqa: E402

__all__ = ["write_outputs", "markdown", "ratio_lines", "plot_speed_error", "plot_images", "to_json", "from_json",
           "machine", "percent"]


def percent(x) -> str:
    """``x`` as "1.23 %", or "n/a" for None or a non-finite number."""
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{100 * x:.3g} %"


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


# ------------------------------------------------------------------------------------------
# Figures
# ------------------------------------------------------------------------------------------

def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig, dpi: int) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    _pyplot().close(fig)
    return buf.getvalue()


def _tonemap(image: np.ndarray, scale: float) -> np.ndarray:
    return srgb_encode(np.clip(np.asarray(image) / (scale if scale > 0 else 1.0), 0, 1))


def plot_images(images: dict, metrics: dict) -> bytes:
    """PNG bytes: mirad's image, the path-traced one (both tonemapped at the reference's 99th
    luminance percentile) and their relative difference over fully covered pixels.

    ``images`` and ``metrics`` are the two dicts ``measure.compare_images`` returns."""
    plt = _pyplot()
    image, ref, mask = images["image"], images["reference"], images["mask"]
    lum = ref.mean(axis=2)
    scale = float(np.percentile(lum[mask], 99)) if mask.any() else 1.0
    eps = 1e-2 * max(float(lum[mask].mean()) if mask.any() else 1.0, 1e-300)
    diff = np.where(mask, (image.mean(axis=2) - lum) / (lum + eps), np.nan)
    fig, axes = plt.subplots(1, 3, figsize=(12, 4.2))
    axes[0].imshow(_tonemap(image, scale))
    axes[0].set_title("mirad (render)")
    axes[1].imshow(_tonemap(ref, scale))
    axes[1].set_title(f"Mitsuba path tracer, {images['spp']} spp")
    im = axes[2].imshow(diff, cmap="coolwarm", vmin=-0.5, vmax=0.5)
    axes[2].set_title(f"(mirad - path) / path; rel. L1 {metrics['rel_l1']:.2%}, rel. MSE {metrics['relmse']:.3g}")
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.04)
    for ax in axes:
        ax.set_axis_off()
    fig.tight_layout()
    return _png(fig, 90)


def plot_speed_error(result: ValidationResult) -> bytes:
    """PNG bytes: area-weighted relative L1 against seconds, log-log, mirad and the path tracer."""
    plt = _pyplot()
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
    ax.set_ylabel("area-weighted relative L1 error per triangle side")
    ax.set_title(f"{result.name}: {result.triangles} triangles")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig, 100)


# ------------------------------------------------------------------------------------------
# Files
# ------------------------------------------------------------------------------------------

def write_outputs(result: ValidationResult, out, *, write_table: bool = True) -> None:
    """Write NAME-speed-error.png, NAME-images.png (when the result holds images) and, unless
    ``write_table`` is false, NAME.md into the folder ``out``, atomically; ``result.files``
    and ``result.markdown`` record them."""
    out = Path(out)
    finish(result)
    if result.images:
        data = plot_images(result.images, result.image)
        path = out / f"{result.name}-images.png"
        atomic_write(path, lambda handle: handle.write(data))
        result.files["images"] = path
    plot = out / f"{result.name}-speed-error.png"
    png = plot_speed_error(result)
    atomic_write(plot, lambda handle: handle.write(png))
    result.files["plot"] = plot
    result.markdown = markdown(result)
    if write_table:
        table = out / f"{result.name}.md"
        atomic_write(table, lambda handle: handle.write(result.markdown.encode()))
        result.files["table"] = table


def to_json(result: ValidationResult) -> dict:
    """The measured numbers of a result as plain JSON types (``from_json`` reads them back)."""
    return {"name": result.name, "scene_source": result.scene_source, "triangles": result.triangles,
            "fingerprint": result.fingerprint, "reference": result.reference, "mirad": result.mirad,
            "path_tracer": result.path_tracer, "shapes": result.shapes, "image": result.image,
            "notes": result.notes, "running": result.running, "targets": list(result.targets),
            "files": {k: str(v) for k, v in result.files.items()}}


def from_json(data: dict) -> ValidationResult:
    """A ValidationResult from ``to_json``'s dict (without images), its ratios recomputed."""
    result = ValidationResult(name=data["name"], scene_source=data["scene_source"], triangles=data["triangles"],
                              fingerprint=data["fingerprint"], reference=data["reference"], mirad=data["mirad"],
                              path_tracer=data["path_tracer"], ratios={}, crossings={}, shapes=data["shapes"],
                              image=data["image"], files={k: Path(v) for k, v in data["files"].items()},
                              notes=list(data["notes"]), running=data.get("running", ""),
                              targets=tuple(data.get("targets", DEFAULT_TARGETS)))
    return finish(result)


# ------------------------------------------------------------------------------------------
# Markdown
# ------------------------------------------------------------------------------------------

def ratio_lines(result: ValidationResult) -> list[str]:
    """One line per target: the time ratio at equal error, or why there is none."""
    lines = []
    for target, ratio in result.ratios.items():
        (tm, hm), (tp, hp) = result.crossings[target]["mirad"], result.crossings[target]["path_tracer"]
        if ratio is not None:
            bound = {(True, False): "≥ ", (False, True): "≤ "}.get((hm == "at most", hp == "at most"), "")
            if hm == hp == "at most":
                bound = "~ (both bounds) "
            lines.append(f"at {percent(target)} L1: mirad {tm:.3g} s ({hm}), path tracer {tp:.3g} s ({hp}): "
                         f"**{bound}{ratio:.2f}x**")
        elif tm is None:
            best = min(result.mirad, key=lambda r: r["l1"]) if result.mirad else None
            tail = f"; its best is {percent(best['l1'])} at {best['seconds']:.2f} s" if best else ""
            lines.append(f"at {percent(target)} L1: no ratio, mirad did not reach it{tail}"
                         + (f" (path tracer {tp:.3g} s, {hp})" if tp else ""))
        else:
            lines.append(f"at {percent(target)} L1: no ratio, path tracer {hp} (mirad {tm:.3g} s, {hm})")
    return lines


def markdown(result: ValidationResult) -> str:
    """The report of one scene as markdown (tables, ratios, images)."""
    ref = result.reference
    noise = ref["noise"]
    back = ref.get("back_sides", 0)
    sides = (f"every front side and the back sides of the {back:,} triangles with a two-sided BSDF (their own "
             "reference pass)" if back else "every triangle's front side (no two-sided BSDF)")
    lines = [f"## {result.name}", "",
             f"- scene: `{result.scene_source or '<scene>'}`, {result.triangles} triangles, fingerprint "
             f"{result.fingerprint}",
             f"- measured {_dt.datetime.now().strftime('%Y-%m-%d %H:%M')} on {machine()}, variant {mi.variant()}",
             f"- reference: Mitsuba `path`, method `{ref['method']}`, {ref['samples_per_triangle']} samples/triangle "
             f"({ref['paths']:,} paths, {ref['seconds']:.1f} s{', cached' if ref['from_cache'] else ''}); its noise "
             f"floor: L1 {percent(noise['l1'])}, RMS {percent(noise['rms'])}, L∞ scale {percent(noise['linf'])}",
             f"- errors: per triangle side and colour channel over {sides}, area weighted, relative to the "
             "area-weighted mean reference radiosity; 'RMS corr.' removes the reference noise in quadrature", "",
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
                     f"{r['leaves'] or 0:,} | {r['links'] or 0:,} | {r['rays'] or 0:,} | {percent(r['l1'])} | "
                     f"{percent(r['rms'])} | {percent(r['rms_corrected'])} | {percent(r['linf'])} | "
                     f"{percent(est) if isinstance(est, (int, float)) else '–'} |")
    lines += ["", "### Mitsuba path tracer as a per-triangle estimator", "",
              "| samples/triangle | seconds | rel. L1 | rel. RMS | RMS corr. | rel. L∞ |", "|---:|---:|---:|---:|---:|---:|"]
    for r in result.path_tracer:
        lines.append(f"| {r['samples']} | {r['seconds']:.2f} | {percent(r['l1'])} | {percent(r['rms'])} | "
                     f"{percent(r['rms_corrected'])} | {percent(r['linf'])} |")
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
                         f"{percent(s['error'])} | {percent(s['noise'])} |")
        lines.append("")
    if result.image:
        im = result.image
        lines += ["### Images", "",
                  f"mirad image: {im['how']} ({im['render_spp']} spp); path-traced image {im['spp']} spp "
                  f"({im['reference_seconds']:.1f} s). Over fully covered pixels "
                  f"({100 * im['covered_pixels']:.0f} % of the image): relative L1 {percent(im.get('rel_l1'))} "
                  f"(sum |I - R| / sum R, robust), relative MSE {im['relmse']:.4g} (decided by the few pixels "
                  f"with the largest relative error); the reference image's own noise contributes "
                  f"{im['noise']:.2g} to the MSE.", ""]
        if "images" in result.files:
            lines += [f"![mirad, path tracer, relative difference]({Path(result.files['images']).name})", ""]
    for note in result.notes:
        lines.append(f"- note: {note}")
    return "\n".join(lines).rstrip() + "\n"
