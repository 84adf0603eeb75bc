"""Mie against Henyey-Greenstein optics in the forward estimator, with and without the
detector directional importance sampling (:mod:`cloudct.mc.detector_sampling`).

Scenes: the single cloud (bundled rico32x37x26) and a field piece (the two cumuli of
rico122x106x39, ``benchmarks/scenes.py``), each with its LES microphysics turned into
(a) the bundled HG optics (g = 0.85, cloud albedo 0.99) and (b) Mie optics from the bundled
table at 0.672 micron (``cloudct les2nc``'s default), both seen by the nine-camera set.

Per scene, optics and aim fraction: ``--seeds`` renders of ``--photons`` photons in 32
batches each, pooled. Reported:

- the mean relative variance of the pixel means over the bright pixels (above 10% of the
  view's maximum in the HG image), and the efficiency 1 / (relative variance x wall time);
- the brightest pixel over the 99th percentile of its view (the firefly ratio), per view;
- each view's mean radiance with its standard error, and the z-score between the aimed
  and the plain estimates of every view mean and of every 4x4-binned pixel (they estimate
  the same images);
- the score-function gradient's noise and signal with the Mie and HG optics (and the cut
  Mie optics with ``--truncation``): two independent estimates of the gradient at 0.8 x
  the true extinction, residual from images rendered once, signal fraction cos(g1, g2)
  and precision per second;
- ``--truncation DEG``: also the Mie images with the phase functions' forward peak cut
  flat at DEG degrees (``phase_truncation``, :mod:`cloudct.optics`; aimed as the full
  ones), their efficiency and firefly ratio, and their bias: the relative difference of
  each view mean and of the lit 4x4-binned pixels from the full Mie images (aimed), in
  units of the pair's standard error;
- ``--combined SHARE [SHARE ...]``: also the combined estimator (forward photons and
  backward pixel samples weighted by multiple importance sampling, both aiming:
  :mod:`cloudct.mc.combined`) with SHARE backward paths per forward photon (samples per
  pixel = SHARE x photons / pixels), for both optics: its efficiency (the two estimators'
  wall time together), firefly ratio, the share of the light its backward paths carry, and
  its agreement with the aimed forward images (Mie) or the plain ones (HG);
- ``--piece-check``: on the test suite's piece of the single cloud (12 x 16 x 14 voxels,
  Mie optics of its own droplets, three 16 x 16 cameras), 4x4-binned pixels of an aimed
  render (3.2 million photons) against a plain one of 12.8 million and against the
  backward estimator at 65,536 samples per pixel, and the plain renders of 3.2 million
  photons each against the aimed one.

Usage::

    python -m benchmarks forward.mie_variance [--photons 1000000] [--seeds 4] [--aim 0.1]
        [--gradient-photons 1000000] [--piece-check] [--gradient-only] [--truncation DEG]
        [--combined SHARE ...] [--output benchmarks/results/mie_variance]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, markdown_table, run_header, write_result
from benchmarks.scenes import LES, cloud_optics, two_cumuli
from cloudct.les import bundled_single_cloud, read_les
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render_batches
from cloudct.mc.scene import single_cloud_scene
from cloudct.medium import cell_edges
from cloudct.optics import OPTICS, to_optical, with_phase_truncation
from cloudct.retrieval.optimizers import block_mean

BATCHES = 32


def scenes() -> dict:
    """The single cloud and the two cumuli, each with HG (the single cloud's) and Mie optics."""
    les = read_les(LES / "rico122x106x39.txt")
    single = bundled_single_cloud()
    return {"single_cloud": {o: cloud_optics(single, "bundled single cloud", o) for o in OPTICS},
            "two_cumuli": {o: two_cumuli(les, o) for o in OPTICS}}


def scene_of(medium):
    edges = cell_edges(medium)
    return single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))


def pooled_render(medium, scene, photons: int, seeds: int, aim: float | None, **kw) -> dict:
    batches, wall, shares = [], 0.0, []
    for seed in range(1, seeds + 1):
        b, info = render_batches(medium, scene, photons=photons, batches=BATCHES, seed=seed,
                                 aim_fraction=aim, progress=False, **kw)
        batches.append(b)
        wall += info["wall_time"]
        shares.append(info.get("backward_share", 0.0))
    b = np.concatenate(batches)
    return {"mean": b.mean(axis=0), "var": b.var(axis=0, ddof=1) / len(b), "wall": wall,
            "view_batches": b.mean(axis=(2, 3)), "binned": binned(b),
            "backward_share": float(np.mean(shares)), **{k: info[k] for k in kw}}


def combined_runs(medium, scene, args, aim: float | None, reference: dict, bright) -> dict:
    """The combined estimator at each ``--combined`` share: summary, the share of light
    its backward paths carry, and agreement with ``reference``."""
    cam = scene.cameras[0]
    pixels = len(scene.cameras) * cam.nrows * cam.ncols
    out = {}
    for share in args.combined:
        run = pooled_render(medium, scene, args.photons, args.seeds, aim, method="combined",
                            pixel_samples=max(1, round(share * args.photons / pixels)))
        out[f"combined {share:g}"] = {
            **summary(run, bright), "pixel_samples": run["pixel_samples"],
            "backward_share": run["backward_share"], "agreement": agreement(run, reference)}
    return out


def binned(b: np.ndarray, n: int = 4) -> np.ndarray:
    v, r, c = b.shape[1:]
    return b[:, :, : r // n * n, : c // n * n].reshape(len(b), v, r // n, n, c // n, n).mean(
        axis=(3, 5))


def summary(run: dict, bright: np.ndarray) -> dict:
    mean, var = run["mean"], run["var"]
    rv = float(np.mean(var[bright] / mean[bright] ** 2))
    firefly = [float(mean[v].max() / np.percentile(mean[v], 99)) for v in range(len(mean))]
    vb = run["view_batches"]
    return {"relative_variance": rv, "wall_s": run["wall"], "efficiency": 1.0 / (rv * run["wall"]),
            "firefly_max": max(firefly), "firefly_median": float(np.median(firefly)),
            "view_mean": vb.mean(axis=0).tolist(),
            "view_mean_se": (vb.std(axis=0, ddof=1) / np.sqrt(len(vb))).tolist()}


def agreement(a: dict, b: dict) -> dict:
    """z-scores between two runs' view means and 4x4-binned pixels."""
    def z(x, y):
        d = x.mean(axis=0) - y.mean(axis=0)
        se = np.sqrt(x.var(axis=0, ddof=1) / len(x) + y.var(axis=0, ddof=1) / len(y))
        ok = se > 0
        return d[ok] / se[ok]
    zv = z(a["view_batches"], b["view_batches"])
    zb = z(a["binned"], b["binned"])
    lit = a["binned"].mean(axis=0) > 0.1 * a["binned"].mean(axis=0).max()
    zb_lit = z(a["binned"][:, lit], b["binned"][:, lit])
    return {"view_z": zv.tolist(), "max_abs_view_z": float(np.abs(zv).max()),
            "binned_z_mean": float(zb.mean()), "binned_z_rms": float(np.sqrt(np.mean(zb**2))),
            "binned_lit_z_rms": float(np.sqrt(np.mean(zb_lit**2))), "binned_count": int(zb.size)}


def truncation_bias(cut: dict, full: dict) -> dict:
    """Relative differences of the cut images from the full ones: each view mean, and the
    lit 4x4 bins (above 10 % of the view's brightest bin), with z = difference / the pair's
    standard error."""
    def rel(a, b):
        d = a.mean(axis=0) - b.mean(axis=0)
        se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
        return d / b.mean(axis=0), d / se
    view_rel, view_z = rel(cut["view_batches"], full["view_batches"])
    fb = full["binned"].mean(axis=0)
    lit = fb > 0.1 * fb.max(axis=(1, 2), keepdims=True)
    bin_rel, bin_z = rel(cut["binned"][:, lit], full["binned"][:, lit])
    return {"view_relative": view_rel.tolist(), "view_z": view_z.tolist(),
            "bins_lit": int(lit.sum()), "bin_relative_mean": float(bin_rel.mean()),
            "bin_relative_rms": float(np.sqrt(np.mean(bin_rel**2))),
            "bin_z_mean": float(bin_z.mean()), "bin_z_rms": float(np.sqrt(np.mean(bin_z**2)))}


def gradient_noise(medium, scene, photons: int, aim: float, estimates: int = 4) -> dict:
    """``estimates`` independent score-function gradients at 0.8 x the extinction (residual
    from one pair of high-photon renders), over the cloudy voxels one by one and averaged
    over 4 x 4 x 4 blocks as a coarse retrieval stage uses them. Pooled over the pairs i < j:
    signal |g|^2 = mean g_i . g_j, noise E|n|^2 = mean |g_i - g_j|^2 / 2; the signal
    fraction of one estimate is |g|^2 / (|g|^2 + E|n|^2), its mean cosine with another
    the pairs' mean cos(g_i, g_j)."""
    start = medium.copy()
    start["cloud_extinction"] = 0.8 * medium["cloud_extinction"]
    truth, _ = render_batches(medium, scene, photons=4 * photons, seed=99, progress=False)
    now, _ = render_batches(start, scene, photons=4 * photons, seed=98, progress=False)
    residual = now.mean(axis=0) - truth.mean(axis=0)
    cloudy = medium["cloud_extinction"].values > 0
    g, wall = [], 0.0
    for seed in range(11, 11 + estimates):
        t = time.perf_counter()
        mean, _, info = score_function_gradient(start, scene, residual, photons=photons,
                                                seed=seed, aim_fraction=aim, progress=False)
        wall += time.perf_counter() - t
        g.append(mean)
    seconds = wall / estimates
    out = {"seconds": seconds, "estimates": estimates}
    for block in (1, 4):
        v = [block_mean(x, cloudy, block)[cloudy] for x in g]
        pairs = [(i, j) for i in range(estimates) for j in range(i + 1, estimates)]
        signal = float(np.mean([v[i] @ v[j] for i, j in pairs]))
        noise = float(np.mean([0.5 * np.sum((v[i] - v[j]) ** 2) for i, j in pairs]))
        out[f"block{block}"] = {
            "signal_fraction": signal / (signal + noise),
            "mean_cosine": float(np.mean([v[i] @ v[j] / np.linalg.norm(v[i])
                                          / np.linalg.norm(v[j]) for i, j in pairs])),
            "noise": noise, "signal": signal, "snr_per_s": signal / (noise * seconds),
        }
    return out


def piece_check() -> dict:
    """The --piece-check comparison (module documentation)."""
    from cloudct.mc.render import render
    from data_synth.single_cloud_piece import piece_microphysics, scene_of_piece

    medium = to_optical(piece_microphysics(), optics="mie")
    scene = scene_of_piece(medium)
    plain = [binned(render_batches(medium, scene, photons=3_200_000, seed=s, batches=64,
                                   aim_fraction=0.0, progress=False)[0]) for s in (11, 12, 13, 14)]
    aimed = binned(render_batches(medium, scene, photons=3_200_000, seed=7, batches=64,
                                  aim_fraction=0.1, progress=False)[0])
    bwd = render(medium, scene, photons=65536, method="backward", seed=15, progress=False)
    b_mean = binned(bwd.radiance.values[None])[0]
    b_se = np.sqrt(binned(bwd.radiance_std_error.values[None] ** 2)[0]) / 4.0

    def stats(x):
        return x.mean(axis=0), x.std(axis=0, ddof=1) / np.sqrt(len(x))

    a_mean, a_se = stats(aimed)
    p_mean, p_se = stats(np.concatenate(plain))
    lit = b_mean > 0.02 * b_mean.max()

    def z(m1, s1, m2, s2):
        v = ((m1 - m2) / np.hypot(s1, s2))[lit]
        return {"mean_z2": float(np.mean(v**2)), "max_abs_z": float(np.abs(v).max())}

    return {
        "bins": int(lit.sum()),
        "aimed_vs_plain_12.8M": z(a_mean, a_se, p_mean, p_se),
        "aimed_vs_backward": z(a_mean, a_se, b_mean, b_se),
        "plain_12.8M_vs_backward": z(p_mean, p_se, b_mean, b_se),
        "plain_3.2M_over_aimed": [
            [float(np.min(r)), float(np.max(r))]
            for r in (stats(x)[0][lit] / a_mean[lit] for x in plain)],
        "relative_se_median": {"aimed_3.2M": float(np.median((a_se / a_mean)[lit])),
                               "plain_3.2M": float(np.median((stats(plain[0])[1]
                                                              / stats(plain[0])[0])[lit]))},
    }


def markdown(result: dict) -> str:
    lines = [f"Photons per render {result['photons']}, {result['seeds']} seeds x {BATCHES} "
             f"batches pooled; aim fraction {result['aim']} against 0 (plain).", ""]
    rows = []
    for name, s in result["scenes"].items():
        for optics in ("hg", "mie"):
            for label in [k for k in s[optics] if k in ("plain", "aimed", "cut")
                          or k.startswith("combined")]:
                r = s[optics][label]
                if label.startswith("combined"):
                    label = (f"{label} ({r['pixel_samples']} samples/px, backward "
                             f"{100 * r['backward_share']:.0f} % of the light)")
                rows.append([name, optics, label, f"{r['relative_variance']:.4f}",
                             f"{r['wall_s']:.1f}", f"{r['efficiency']:.3f}",
                             f"{r['firefly_median']:.1f} / {r['firefly_max']:.1f}",
                             f"{np.mean(np.divide(r['view_mean_se'], r['view_mean'])):.2e}"])
    lines += markdown_table(
        ["scene", "optics", "sampling", "rel. variance (bright)", "wall s", "efficiency",
         "firefly ratio median / max", "view-mean rel. se"], rows)
    lines += ["", "Aimed against plain (same images expected):", ""]
    rows = []
    for name, s in result["scenes"].items():
        for optics in ("hg", "mie"):
            a = s[optics]["agreement"]
            rows.append([name, optics, f"{a['max_abs_view_z']:.2f}", f"{a['binned_z_mean']:+.3f}",
                         f"{a['binned_z_rms']:.3f}", f"{a['binned_lit_z_rms']:.3f}",
                         str(a["binned_count"])])
    lines += markdown_table(["scene", "optics", "max |z| view means", "mean z 4x4 bins",
                             "rms z 4x4 bins", "rms z lit bins", "bins"], rows)
    combined = [(name, optics, label, r["agreement"]) for name, s in result["scenes"].items()
                for optics in ("hg", "mie") for label, r in s[optics].items()
                if label.startswith("combined")]
    if combined:
        lines += ["", "Combined against the aimed forward images (Mie) or the plain ones (HG):",
                  ""]
        rows = [[name, optics, label, f"{a['max_abs_view_z']:.2f}",
                 f"{a['binned_z_mean']:+.3f}", f"{a['binned_z_rms']:.3f}",
                 f"{a['binned_lit_z_rms']:.3f}", str(a["binned_count"])]
                for name, optics, label, a in combined]
        lines += markdown_table(["scene", "optics", "estimator", "max |z| view means",
                                 "mean z 4x4 bins", "rms z 4x4 bins", "rms z lit bins",
                                 "bins"], rows)
    if "truncation" in result:
        lines += ["", f"Mie with the peak cut at {result['truncation']} degrees against the "
                  "full Mie images (aimed), relative difference (z = over the pair's "
                  "standard error):", ""]
        rows = []
        for name, s in result["scenes"].items():
            b = s["mie"]["cut_bias"]
            rows.append([name, " ".join(f"{r:+.3f}" for r in b["view_relative"]),
                         f"{max(abs(z) for z in b['view_z']):.1f}",
                         f"{b['bin_relative_mean']:+.4f} / {b['bin_relative_rms']:.4f}",
                         f"{b['bin_z_mean']:+.2f} / {b['bin_z_rms']:.2f}", str(b["bins_lit"])])
        lines += markdown_table(["scene", "view means, relative", "max |z| views",
                                 "lit 4x4 bins: mean / rms relative",
                                 "lit bins: mean / rms z", "bins"], rows)
    if "gradient" in result:
        lines += ["", "Score-function gradient at 0.8 x the true extinction (single cloud, "
                  f"{result['gradient_photons']} photons per estimate):", ""]
        rows = [[optics, label, f"{g['seconds']:.1f}"]
                + [f"{g[f'block{b}'][k]:.3g}" for b in (1, 4)
                   for k in ("signal_fraction", "mean_cosine", "snr_per_s")]
                for optics, d in result["gradient"].items() for label, g in d.items()]
        lines += markdown_table(["optics", "sampling", "s per estimate",
                                 "signal fraction, voxels", "mean cos, voxels",
                                 "signal / (noise x s), voxels", "signal fraction, 4^3 blocks",
                                 "mean cos, 4^3 blocks", "signal / (noise x s), 4^3 blocks"],
                                rows)
    if "piece" in result:
        p = result["piece"]
        lines += ["", f"Piece check ({p['bins']} lit 4x4 bins):", ""]
        rows = [[k, f"{v['mean_z2']:.2f}", f"{v['max_abs_z']:.2f}"] for k, v in p.items()
                if isinstance(v, dict) and "mean_z2" in v]
        lines += markdown_table(["comparison", "mean z^2", "max |z|"], rows)
        lines += ["", "plain (3.2 million photons) / aimed, range over the bins, per seed: "
                  + ", ".join(f"{a:.2f}-{b:.2f}" for a, b in p["plain_3.2M_over_aimed"]),
                  f"median relative standard error: {p['relative_se_median']}"]
    return "\n".join(lines) + "\n"


def gradients(media: dict, scene, args) -> dict:
    out = {optics: {label: gradient_noise(media[optics], scene, args.gradient_photons, a)
                    for label, a in (("plain", 0.0), ("aimed", args.aim))}
           for optics in ("hg", "mie")}
    if args.truncation:  # the residual, too, from images of the cut optics
        out["mie"]["cut"] = gradient_noise(with_phase_truncation(media["mie"], args.truncation),
                                           scene, args.gradient_photons, args.aim)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=1_000_000)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--aim", type=float, default=0.1)
    parser.add_argument("--gradient-photons", type=int, default=1_000_000)
    parser.add_argument("--piece-check", action="store_true")
    parser.add_argument("--gradient-only", action="store_true",
                        help="recompute only the gradient part of an existing --output")
    parser.add_argument("--truncation", type=float, default=0.0,
                        help="also render Mie with the peak cut at this many degrees")
    parser.add_argument("--combined", type=float, nargs="+", default=[], metavar="SHARE",
                        help="also the combined estimator with SHARE backward paths per "
                        "forward photon (several: one run each)")
    parser.add_argument("--output", default=str(RESULTS / "mie_variance"))
    args = parser.parse_args()
    if args.gradient_only:
        result = json.loads(Path(args.output).with_suffix(".json").read_text())
        media = scenes()["single_cloud"]
        result["gradient_photons"] = args.gradient_photons
        result["gradient"] = gradients(media, scene_of(media["hg"]), args)
        write_result(result, args.output, markdown)
        return
    result = {**run_header(args), "photons": args.photons, "seeds": args.seeds, "aim": args.aim,
              "gradient_photons": args.gradient_photons, "scenes": {}}
    if args.truncation:
        result["truncation"] = args.truncation
    if args.combined:
        result["combined"] = args.combined
    for name, media in scenes().items():
        scene = scene_of(media["hg"])
        render_batches(media["mie"], scene, photons=64, progress=False)  # JIT warm-up
        out = {}
        bright = None
        for optics in ("hg", "mie"):
            plain = pooled_render(media[optics], scene, args.photons, args.seeds, 0.0)
            aimed = pooled_render(media[optics], scene, args.photons, args.seeds, args.aim)
            if bright is None:
                bright = plain["mean"] > 0.1 * plain["mean"].max(axis=(1, 2), keepdims=True)
            out[optics] = {"plain": summary(plain, bright), "aimed": summary(aimed, bright),
                           "agreement": agreement(plain, aimed)}
            if args.combined:  # the aim fraction of the optics' default (Mie 0.1, HG 0)
                out[optics].update(combined_runs(
                    media[optics], scene, args, None, aimed if optics == "mie" else plain,
                    bright))
            if optics == "mie" and args.truncation:
                cut = pooled_render(with_phase_truncation(media["mie"], args.truncation),
                                    scene, args.photons, args.seeds, args.aim)
                out[optics]["cut"] = summary(cut, bright)
                out[optics]["cut_bias"] = truncation_bias(cut, aimed)
            print(name, optics, out[optics]["plain"]["efficiency"],
                  out[optics]["aimed"]["efficiency"], flush=True)
        result["scenes"][name] = out
        if name == "single_cloud" and args.gradient_photons > 0:
            result["gradient"] = gradients(media, scene, args)
    if args.piece_check:
        result["piece"] = piece_check()
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
