"""Shadow textures by convolution against shadow rays and against subdivision.

For each shadow case (scenes/shadow-cases/) the link floor <- light is computed three ways
on the same R x R texel grid over the receiver:

* reference: ``ray_visibility`` with many stratified kernel-weighted rays per texel;
* texture: ``shadow_texture`` (mask rays, depth layers, FFT), timed;
* subdivision: the receiver split into k x k elements, each with one link of ``--rays``
  shadow rays from jittered element points to the source (what HR refinement does),
  piecewise-constant visibility per element, timed, for k = 2, 4, ..., R.

Errors, texel-wise over the receiver against the reference: mean |V - V_ref| and the
relative L1 of the irradiance texture sum |F (V - V_ref)| / sum F V_ref (F: the unoccluded
point form factor, so this is the per-texel irradiance error of the link). At equal error
(the smallest k whose irradiance error is at most the texture's) the table sets elements,
links, rays and seconds side by side. Appends the table to validation/RESULTS.md with
``--record``.

Usage (from the repository root)::

    python validation/bench_shadows.py [--resolution 128] [--ref-rays 1024] [--record]
"""

from __future__ import annotations

import argparse
import datetime as _dt
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import mirad  # noqa: E402
from mirad import shadows as S  # noqa: E402
import mitsuba as mi  # noqa: E402
from mirad.validate import machine  # noqa: E402

CASES = {"parallel": "floor", "tilted": "floor", "table": "floor", "leaves": "ground"}
RESULTS = REPO / "validation" / "RESULTS.md"


def quad(scene, sid: str) -> np.ndarray:
    """(4, 3) corners of a rectangle shape, counter-clockwise about its normal."""
    tris = scene.tri_vertices[scene.tri_shape == scene.shape_index(sid)]
    normal = np.cross(tris[0, 1] - tris[0, 0], tris[0, 2] - tris[0, 0])
    normal /= np.linalg.norm(normal)
    pts = np.unique(np.round(tris.reshape(-1, 3), 9), axis=0)
    c = pts.mean(axis=0)
    t1 = pts[0] - c
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(normal, t1)
    order = np.argsort(np.arctan2((pts - c) @ t2, (pts - c) @ t1))
    return pts[order]


def subdivision(mi_scene, source, receiver, k: int, rays: int, res: int, seed: int = 1):
    """Visibility of k x k receiver elements (one link of ``rays`` rays each), broadcast to the
    res x res texels; returns (texels (res, res), rays, seconds)."""
    t = time.perf_counter()
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    uv = (np.stack([i, j], -1)[:, :, None, :] + rng.random((k, k, rays, 2))) / k
    e_u, e_v = receiver[1] - receiver[0], receiver[3] - receiver[0]
    pts = receiver[0] + uv[..., :1] * e_u + uv[..., 1:] * e_v
    normal = np.cross(e_u, e_v)
    normal /= np.linalg.norm(normal)
    flat = pts.reshape(-1, 3)
    vis, _ = S.ray_visibility(mi_scene, source, flat, np.tile(normal, (len(flat), 1)), rays=1, seed=seed)
    per_elem = vis.reshape(k, k, rays).mean(axis=2)
    seconds = time.perf_counter() - t
    texels = np.repeat(np.repeat(per_elem, res // k, axis=0), res // k, axis=1)
    return texels, k * k * rays, seconds


def errors(v, v_ref, f):
    return float(np.abs(v - v_ref).mean()), float(np.abs(f * (v - v_ref)).sum() / max((f * v_ref).sum(), 1e-300))


def run(name: str, res: int, ref_rays: int, rays: int):
    scene = mirad.load_scene(REPO / "scenes" / "shadow-cases" / f"{name}.xml")
    mi_scene = scene.mi_scene
    source, receiver = quad(scene, "light"), quad(scene, CASES[name])
    S.shadow_texture(mi_scene, source, receiver, 16)          # compile the kernels once
    t = time.perf_counter()
    tex = S.shadow_texture(mi_scene, source, receiver, res)
    t_tex = time.perf_counter() - t
    pts = S.receiver_points(receiver[None], res)[0].reshape(-1, 3)
    normal = np.cross(receiver[1] - receiver[0], receiver[3] - receiver[0])
    normal /= np.linalg.norm(normal)
    t = time.perf_counter()
    v_ref, se = S.ray_visibility(mi_scene, source, pts, np.tile(normal, (len(pts), 1)), rays=ref_rays, seed=7)
    t_ref = time.perf_counter() - t
    v_ref, se = v_ref.reshape(res, res), se.reshape(res, res)
    f = tex.point_ff[0]
    v = tex.texture[0]
    tex_err = errors(v, v_ref, f)
    within = float(np.mean(np.abs(v - v_ref) <= 3 * se + 1e-3))
    subs = []
    for per in rays:
        k = 2
        while k <= res:
            vk, n_rays, secs = subdivision(mi_scene, source, receiver, k, per, res)
            subs.append((k, n_rays, secs, *errors(vk, v_ref, f), per))
            k *= 2
    return {"name": name, "tex": tex, "t_tex": t_tex, "tex_err": tex_err, "within": within, "t_ref": t_ref,
            "noise": float(se.mean()), "subs": subs}


def batched(name: str = "leaves", tiles: int = 8, res: int = 32):
    """Seconds of one ``shadow_textures`` call on tiles x tiles links (receiver tiles <- light)."""
    scene = mirad.load_scene(REPO / "scenes" / "shadow-cases" / f"{name}.xml")
    source, receiver = quad(scene, "light"), quad(scene, CASES[name])
    e_u, e_v = (receiver[1] - receiver[0]) / tiles, (receiver[3] - receiver[0]) / tiles
    i, j = (a.ravel() for a in np.meshgrid(np.arange(tiles), np.arange(tiles), indexing="ij"))
    o = receiver[0] + i[:, None] * e_u + j[:, None] * e_v
    rcv = np.stack([o, o + e_u, o + e_u + e_v, o + e_v], 1)
    src = np.repeat(source[None], len(rcv), 0)
    S.shadow_textures(scene.mi_scene, src[:2], rcv[:2], res)
    t = time.perf_counter()
    tex = S.shadow_textures(scene.mi_scene, src, rcv, res)
    return len(rcv), res, time.perf_counter() - t, tex.rays


def table(results, res, ref_rays, rays, batch=None) -> str:
    lines = [f"## Shadow textures by convolution (issue 10), {_dt.date.today().isoformat()}", "",
             f"`python validation/bench_shadows.py --record`; {machine()}, variant {mi.variant()}; "
             "the CPU was shared with 3 other agents' jobs, so seconds are indicative. Link floor <- light of each "
             f"scenes/shadow-cases scene on a {res} x {res} texel grid over the receiver. Reference: {ref_rays} "
             "kernel-weighted stratified shadow rays per texel. Texture: `shadow_texture` (mask rays + depth "
             f"layers + FFT). Subdivision: k x k receiver elements, one link of {'/'.join(map(str, rays))} rays each (piecewise-"
             "constant visibility). Errors texel-wise against the reference: mean |dV|, and irradiance L1 = "
             "sum |F dV| / sum F V_ref. 'within noise': share of texels with |dV| <= 3 reference standard errors + 0.001. "
             "Equal error: the subdivision with the fewest rays whose irradiance L1 is at most the texture's. "
             "Seconds: one link's texture (one Dr.Jit launch per hit pass) against one launch for all k x k "
             "subdivision links; neither includes the solver's cost per element and link.", "",
             "| scene | method | elements | links | rays | seconds | mean abs dV | irradiance L1 | layers | predicted | within noise |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        tex = r["tex"]
        lines.append(f"| {r['name']} | texture {res}² | 1 | 1 | {tex.rays:,} | {r['t_tex']:.3f} | {r['tex_err'][0]:.4f} | "
                     f"{100 * r['tex_err'][1]:.2f} % | {int(tex.layers[0])} | {float(tex.predicted_error[0]):.4f} | "
                     f"{100 * r['within']:.1f} % |")
        equal = sorted((s for s in r["subs"] if s[4] <= r["tex_err"][1]), key=lambda s: s[1])
        best = equal[0] if equal else min(r["subs"], key=lambda s: s[4])
        tag = "subdivision (equal error)" if equal else "subdivision (best tried, error still above)"
        k, n_rays, secs, e_v, e_h, per = best
        lines.append(f"| {r['name']} | {tag} {k}x{k}, {per} rays/link | {k * k} | {k * k} | {n_rays:,} | {secs:.3f} | {e_v:.4f} | "
                     f"{100 * e_h:.2f} % | – | – | – |")
    lines.append("")
    lines.append("Subdivision sweep (k x k elements / rays per link: irradiance L1): " + "; ".join(
        f"{r['name']}: " + ", ".join(f"{s[0]}/{s[5]}: {100 * s[4]:.1f} %" for s in r["subs"]) for r in results))
    lines.append("")
    if batch:
        k, r, secs, n_rays = batch
        lines.append(f"Batched: {k} links (leaves scene, the ground in {int(np.sqrt(k))} x {int(np.sqrt(k))} tiles <- light), "
                     f"{r} x {r} texels each, in one `shadow_textures` call: {secs:.2f} s ({1e3 * secs / k:.1f} ms per link, "
                     f"{n_rays:,} mask rays).")
        lines.append("")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--ref-rays", type=int, default=1024)
    ap.add_argument("--rays", default="16,64,256", help="shadow rays per subdivision link (a list)")
    ap.add_argument("--scenes", default=",".join(CASES))
    ap.add_argument("--record", action="store_true")
    args = ap.parse_args(argv)
    rays = [int(x) for x in args.rays.split(",")]
    results = [run(n, args.resolution, args.ref_rays, rays) for n in args.scenes.split(",")]
    text = table(results, args.resolution, args.ref_rays, rays, batched())
    print(text)
    if args.record:
        with open(RESULTS, "a") as fh:
            fh.write("\n" + text)


if __name__ == "__main__":
    main()
