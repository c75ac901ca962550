"""``mirad validate``: measure mirad against Mitsuba's path tracer on one scene, then report.

``validate(scene)`` checks the output folder, runs ``mirad.measure.measure`` (the tolerance
sweep, the path tracer as an estimator, the reference, the images; plain numbers and arrays)
and hands the result to ``mirad.report.write_outputs``, which writes ``NAME.md`` (tables),
``NAME-speed-error.png`` (error against seconds, log-log, both curves) and ``NAME-images.png``
into the output folder, each atomically. Every error is reported with the reference's own noise
floor (``mirad.metrics``); where a BSDF is two-sided the back sides are measured too.

>>> result = validate("scenes/cornell-box/scene.xml", output_dir="out")    # doctest: +SKIP
>>> result.ratios[0.01]                                                    # doctest: +SKIP
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import OutputError
from .measure import (DEFAULT_PT_SAMPLES, DEFAULT_REFERENCE_SAMPLES, DEFAULT_TARGETS, DEFAULT_TOLERANCES,
                      ValidationResult, finish, measure, time_at_error)
from .reference import DEFAULT_CACHE
from .report import from_json, machine, markdown, ratio_lines, to_json, write_outputs

__all__ = ["validate", "ValidationResult", "time_at_error", "finish", "write_outputs", "markdown", "ratio_lines",
           "to_json", "from_json", "machine", "DEFAULT_TOLERANCES", "DEFAULT_PT_SAMPLES", "DEFAULT_REFERENCE_SAMPLES",
           "DEFAULT_TARGETS"]


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
    pt_samples : samples per triangle (side) of the path tracer used as an estimator
    reference_samples : mean paths per triangle side of the reference, allocated by area (independent seed)
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
    out = Path(output_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder '{out}' ({exc.strerror}); choose another --output") from None
    if not os.access(out, os.W_OK):
        raise OutputError(f"output folder '{out}' is not writable; choose another --output")
    result = measure(scene, tolerances=tolerances, pt_samples=pt_samples, reference_samples=reference_samples,
                     reference_seed=reference_seed, targets=targets, images=images, image_spp=image_spp,
                     render_spp=render_spp, name=name, cache_dir=cache_dir, seed=seed, max_seconds=max_seconds,
                     quiet=quiet, progress=progress, **solve_options)
    if not quiet:
        for line in ratio_lines(result):
            print(line.replace("**", ""), flush=True)
    write_outputs(result, out, write_table=write_table)
    if not quiet:
        print("wrote " + ", ".join(str(p) for p in result.files.values()), flush=True)
    return result
