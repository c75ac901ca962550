"""Run the validation suite at a fixed budget; write validation/REPORT.md and append to RESULTS.md.

For every scene of the suite, ``mirad.validate.validate`` sweeps mirad's tolerance and the path
tracer's samples per triangle against one path-traced reference (cached in .mirad-cache/), and
compares images. The report collects the per-scene tables, the speed-error plots and the images
(PNG files beside REPORT.md), a summary table, and the check of the targets of DESIGN §5:

- finely tessellated Cornell box and furnished room: mirad reaches 1 % area-weighted relative L1
  per-triangle error at least 10x faster than Mitsuba path tracing reaches the same error.

Usage (from the repository root)::

    python validation/run_all.py [--budget quick|default|full] [--scenes a,b] [--no-record]

The default budget takes a few minutes per scene on 2 cores (most of it the references, which
are cached for the next run); ``quick`` is a smoke run; ``full`` uses 4x the reference samples.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import mirad  # noqa: E402  (sets up LLVM before mitsuba)
from mirad.solution import atomic_write  # noqa: E402
from mirad.report import from_json, machine, percent, ratio_lines, to_json, write_outputs  # noqa: E402
from mirad.validate import validate  # noqa: E402

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

HERE = REPO / "validation"
REPORT = HERE / "REPORT.md"
RESULTS = HERE / "RESULTS.md"
#: Scenes whose target is ">= 10x faster than path tracing at 1 % L1".
TARGET_SCENES = ("cornell-box-fine", "furnished-room")
TARGET_RATIO = 10.0

#: Per scene: tolerances, path-tracer samples per triangle, reference samples per triangle,
#: seconds allowed per sweep (a sweep stops before a step likely to overrun it), and a hard
#: time limit for the whole scene (its validation runs in a child process; what finished is kept).
SUITE = {
    "cornell-box": dict(tolerances=(0.1, 0.05, 0.03, 0.02, 0.01), pt_samples=(64, 256, 1024, 4096, 16384),
                        reference_samples=65536, max_seconds=60, timeout=300),
    "cornell-box-fine": dict(tolerances=(0.2, 0.1, 0.05, 0.03, 0.02, 0.01),
                             pt_samples=(16, 64, 256, 1024, 4096, 8192), reference_samples=32768, max_seconds=240,
                             timeout=900),
    "furnished-room": dict(tolerances=(0.2, 0.1, 0.05, 0.03, 0.02, 0.01), pt_samples=(16, 64, 256, 1024, 4096, 8192),
                           reference_samples=32768, max_seconds=150, timeout=420),
    "plant-canopy": dict(tolerances=(0.2, 0.1, 0.05), pt_samples=(16, 64, 256, 1024), reference_samples=8192,
                         max_seconds=90, timeout=300),
    "tiny-bright-room": dict(tolerances=(0.2, 0.1, 0.05), pt_samples=(16, 64, 256, 1024),
                             reference_samples=8192, max_seconds=60, timeout=240),
    "wall-pierce": dict(tolerances=(0.2, 0.1, 0.05), pt_samples=(16, 64, 256, 1024), reference_samples=8192,
                        max_seconds=60, timeout=240),
}
BUDGETS = {  # multipliers of (reference samples, max_seconds); quick also trims the sweeps
    "quick": (1 / 16, 1 / 6),
    "default": (1.0, 1.0),
    "full": (4.0, 3.0),
}


def settings_for(name: str, budget: str) -> dict:
    cfg = dict(SUITE[name])
    ref_scale, time_scale = BUDGETS[budget]
    cfg["reference_samples"] = max(1024, int(cfg["reference_samples"] * ref_scale))
    cfg["max_seconds"] = cfg["max_seconds"] * time_scale
    cfg["timeout"] = cfg["timeout"] * max(time_scale, 0.5)
    if budget == "quick":
        cfg["tolerances"] = cfg["tolerances"][:2]
        cfg["pt_samples"] = cfg["pt_samples"][:3]
    return cfg


def where_time_goes(result) -> str:
    """One paragraph: phase timings of mirad's most accurate solve, and links per element."""
    if not result.mirad:
        return "mirad produced no solution within the budget."
    best = min(result.mirad, key=lambda r: r["l1"])
    ph = best["phases"]
    # (the hierarchical core names its Dr.Jit waves "transfer" and repeats them as "visibility",
    # the legacy core's name for its own)
    waves = "transfer" if "transfer" in ph else "visibility"
    parts = [f"{k} {v:.2f} s" for k, v in ph.items()
             if k not in ("total", "visibility" if waves == "transfer" else "") and isinstance(v, (int, float)) and v > 0]
    total = ph.get("total")
    links_per_leaf = (best["links"] or 0) / max(best["leaves"] or 1, 1)
    return (f"mirad's most accurate point (tolerance {best['tolerance']:g}: {percent(best['l1'])} L1 in "
            f"{best['seconds']:.1f} s wall clock, solver total {total:.1f} s) has phase timings "
            f"(`sol.stats['seconds']`) {', '.join(parts) or 'none'}; '{waves}' counts every Dr.Jit wave that "
            f"evaluates links or gathered pairs (the rays and their form factors); {best['leaves'] or 0:,} leaves, "
            f"{best['links'] or 0:,} links ({links_per_leaf:.0f} per leaf), {best['rays'] or 0:,} rays."
            if isinstance(total, (int, float)) else f"phase timings: {', '.join(parts)}")


def summary_table(results: list) -> str:
    lines = ["| scene | triangles | reference noise (L1) | mirad best L1 (s) | path tracer at 1 % (s) | "
             "ratio at 1 % | ratio at 2 % | image rel. MSE (noise) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        best = min(r.mirad, key=lambda x: x["l1"]) if r.mirad else None
        tp, hp = r.crossings.get(0.01, {}).get("path_tracer", (None, "n/a"))
        cells = [r.name, f"{r.triangles:,}", percent(r.reference["noise"]["l1"]),
                 f"{percent(best['l1'])} ({best['seconds']:.2f})" if best else "n/a",
                 f"{tp:.3g} ({hp})" if tp else hp]
        for target in (0.01, 0.02):
            value = r.ratios.get(target)
            cells.append(f"{value:.2f}x" if value else "n/a")
        cells.append(f"{r.image['relmse']:.3g} ({r.image['noise']:.2g})" if r.image else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def targets_section(results: list) -> str:
    out = ["## Targets", "",
           f"Target (DESIGN §5): on the finely tessellated Cornell box and the furnished room, mirad reaches 1 % "
           f"area-weighted relative L1 per-triangle error at least {TARGET_RATIO:g}x faster than Mitsuba path "
           "tracing reaches the same error.", ""]
    for r in results:
        if r.name not in TARGET_SCENES:
            continue
        ratio = r.ratios.get(0.01)
        met = ratio is not None and ratio >= TARGET_RATIO
        verdict = "**met**" if met else "**not met**"
        out.append(f"- {r.name}: {verdict}. " + "; ".join(ratio_lines(r)[:1]) + ".")
        if not met:
            out.append(f"  - where mirad's time goes: {where_time_goes(r)}")
    missing = [n for n in TARGET_SCENES if n not in {r.name for r in results}]
    for n in missing:
        out.append(f"- {n}: not run in this report.")
    return "\n".join(out)


def write_report(results: list, header: str, notes: list) -> None:
    body = [header, "", "## Summary", "", summary_table(results), "", targets_section(results), ""]
    if notes:
        body += ["## Notes", ""] + [f"- {n}" for n in notes] + [""]
    body += ["## Per scene", ""]
    for r in results:  # each scene's "## name / ### part" becomes "### name / #### part"
        body += ["#" + r.markdown.replace("\n### ", "\n#### "), ""]
    text = "\n".join(body).rstrip() + "\n"
    atomic_write(REPORT, lambda handle: handle.write(text.encode()))


def record(results: list, stamp: str, budget: str) -> None:
    lines = [f"## run_all ({budget} budget): validation suite, {stamp}", "",
             f"- machine: {machine()}; Mitsuba variant {mi.variant()}; mitsuba {mi.__version__}, drjit "
             f"{dr.__version__}, mirad {mirad.__version__}",
             "- CPU shared with other work while measuring: timings are indicative (see validation/REPORT.md)",
             "- error: area-weighted relative L1 per triangle against a path-traced reference; ratio = path-tracer "
             "seconds / mirad seconds at equal error (log-log interpolation)", "", summary_table(results), ""]
    text = RESULTS.read_text() if RESULTS.exists() else "# mirad benchmark results\n"
    text = text.rstrip("\n") + "\n\n" + "\n".join(lines).rstrip("\n") + "\n"
    atomic_write(RESULTS, lambda handle: handle.write(text.encode()))


#: A child whose resident memory passes this fraction of the machine's stops itself (exit status
#: MEMORY_EXIT) rather than let the kernel's OOM killer pick a process of someone else's.
MEMORY_FRACTION = 0.6
MEMORY_EXIT = 3


def _memory_guard(state: Path) -> None:
    """Watch this process's resident memory; above the limit, note it in the state file and exit."""
    import threading

    try:
        page = os.sysconf("SC_PAGE_SIZE")
        limit = MEMORY_FRACTION * page * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        return

    def watch():
        while True:
            try:
                with open("/proc/self/statm") as fh:
                    rss = int(fh.read().split()[1]) * page
            except OSError:
                return
            if rss > limit:
                try:
                    data = json.loads(state.read_text())
                    data["notes"].append(f"stopped: resident memory passed {limit / 2**30:.0f} GiB "
                                         f"while running {data.get('running') or 'a step'}")
                    text = json.dumps(data).encode()
                    atomic_write(state, lambda handle: handle.write(text))
                finally:
                    os._exit(MEMORY_EXIT)
            time.sleep(0.5)

    threading.Thread(target=watch, daemon=True).start()


def run_one(name: str, state: Path, cfg: dict, cache: str) -> int:
    """Child process: validate one scene, saving the results so far to ``state`` after every step."""
    def save(result):
        data = json.dumps(to_json(result)).encode()
        atomic_write(state, lambda handle: handle.write(data))

    cfg = {k: v for k, v in cfg.items() if k != "timeout"}
    _memory_guard(state)
    validate(REPO / "scenes" / name / "scene.xml", output_dir=HERE, name=name, cache_dir=cache, write_table=False,
             progress=save, **cfg)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget", choices=sorted(BUDGETS), default="default")
    ap.add_argument("--scenes", default=",".join(SUITE), help="comma-separated scene folders under scenes/")
    ap.add_argument("--no-record", action="store_true", help="do not append to validation/RESULTS.md")
    ap.add_argument("--cache", default=str(REPO / ".mirad-cache"), help="reference cache folder")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)      # child process: one scene
    ap.add_argument("--state", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    unknown = [n for n in names + ([args.one] if args.one else []) if n not in SUITE]
    if unknown:
        print(f"run_all: unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SUITE)}", file=sys.stderr)
        return 2
    if args.one:
        return run_one(args.one, Path(args.state), settings_for(args.one, args.budget), args.cache)
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    started = time.perf_counter()
    results, notes = [], []
    with tempfile.TemporaryDirectory(prefix="mirad-run-all-") as tmp:
        for name in names:
            cfg = settings_for(name, args.budget)
            state = Path(tmp) / f"{name}.json"
            print(f"\n=== {name}: {cfg}", flush=True)
            t0 = time.perf_counter()
            cmd = [sys.executable, __file__, "--one", name, "--state", str(state), "--budget", args.budget,
                   "--cache", args.cache]
            try:
                proc = subprocess.run(cmd, timeout=cfg["timeout"], stderr=subprocess.PIPE, text=True)
                failure = proc.stderr.strip().splitlines()[-1] if proc.returncode and proc.stderr.strip() else ""
                if proc.returncode == MEMORY_EXIT:
                    failure = "stopped by its memory guard"
                elif proc.returncode < 0:
                    failure = f"killed by signal {-proc.returncode} (9: out of memory, most likely)"
                elif proc.returncode and not failure:
                    failure = f"exit status {proc.returncode}"
            except subprocess.TimeoutExpired:
                failure = f"stopped at the scene's time limit ({cfg['timeout']:.0f} s)"
            if not state.exists():
                notes.append(f"{name}: no result ({failure or 'nothing finished'})")
                print(notes[-1], file=sys.stderr)
                continue
            result = from_json(json.loads(state.read_text()))
            if failure:
                result.notes.append(f"validation {failure}" + (f" while running {result.running}" if result.running
                                                                else ""))
            else:
                result.running = ""
            write_outputs(result, HERE, write_table=False)
            result.markdown = result.markdown.replace(f"- scene: `{result.scene_source}`",
                                                      f"- scene: `scenes/{name}/scene.xml`")
            results.append(result)
            print(f"{name}: {time.perf_counter() - t0:.0f} s", flush=True)
    minutes = (time.perf_counter() - started) / 60
    header = "\n".join([
        "# mirad validation report", "",
        f"Written by `python validation/run_all.py --budget {args.budget}` on {stamp} in {minutes:.1f} min.",
        f"Machine: {machine()}; Mitsuba variant {mi.variant()} (mitsuba {mi.__version__}, drjit {dr.__version__}, "
        f"mirad {mirad.__version__}). The CPU was shared with other developers' work while measuring, so "
        "timings carry that noise (small runs most: a launch can wait a scheduler slice).", "",
        "Method: every error is the area-weighted relative L1 (and RMS, L∞) of per-triangle front-side "
        "radiosity against a path-traced reference (Mitsuba `path`, a ray aimed at uniformly sampled points "
        "of each triangle, B = π·L_o), normalised by the area-weighted mean; each is shown with the "
        "reference's own noise floor (the error a perfect solution would show). The path tracer is also run "
        "as a per-triangle estimator in its own right (independent seeds, fewer samples) and timed the same "
        "way (wall clock, JIT warm-up excluded for both). Ratios are path-tracer seconds / mirad seconds at "
        "equal L1, each curve interpolated in log-log; the path tracer's curve is extrapolated along its "
        "t^-1/2 rate when its sweep stops short (marked)."])
    write_report(results, header, notes)
    print(f"\nwrote {REPORT}")
    if not args.no_record and results:
        record(results, stamp, args.budget)
        print(f"appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
