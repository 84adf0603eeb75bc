"""The engine's speed against an earlier commit: the forward render and the gradients of the
seed paper's single cloud, timed for this work tree and for a commit's tree in alternating
runs on the same machine (issue 36: "at least as fast as 669ae1a's, as ratios measured in
one run against that commit").

Each run is a new process that imports cloudct from one tree (``PYTHONPATH``; the commit is
checked out with ``git worktree`` into the work folder), loads or compiles its kernels in a
warm-up call (not timed), then times one call of each estimator: the forward render of
``--photons`` photons, the score-function gradient of as many paths, and DRT at
``--drt-spp`` samples per pixel, with the same random residual. The runs alternate between
the trees ``--repeats`` times, so that a change of the machine's load falls on both; each
run records its wall time and its CPU time (all threads). The images and gradients of the
two trees are compared (bitwise where the estimator's random stream is unchanged). Usage::

    python -m benchmarks gradients.against_commit [--commit 669ae1a] [--photons 1000000]
        [--drt-spp 4] [--repeats 5] [--calls render score drt]
        [--output benchmarks/results/speed_against_669ae1a]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.common import REPO, RESULTS, WORK, markdown_table, run_header, write_result

#: What one run times, in a new process; argv: photons, DRT samples per pixel, the calls
#: (comma-separated names of ``calls``).
TIMED = """
import hashlib, json, sys, time
import numpy as np
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import single_cloud_scene
from cloudct.medium import cell_edges
from cloudct.mc.gradient import score_function_gradient
try:
    from cloudct.mc.gradient import drt_gradient
except ImportError:  # where DRT lived before the estimators were gathered
    from cloudct.mc.drt import drt_gradient

photons, spp, chosen = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3].split(",")
medium = single_cloud_medium()
edges = cell_edges(medium)
scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
shape = (len(scene.cameras), scene.cameras[0].nrows, scene.cameras[0].ncols)
residual = np.random.default_rng(1).normal(size=shape)
calls = {  # the images, or the gradient's mean
    "render": lambda n, k: render(medium, scene, photons=n, progress=False)["radiance"].values,
    "score": lambda n, k: score_function_gradient(medium, scene, residual, photons=n,
                                                  progress=False)[0],
    "drt": lambda n, k: drt_gradient(medium, scene, residual, samples_per_pixel=k,
                                     progress=False)[0],
}
out = {}
for name in chosen:
    call = calls[name]
    call(64, 1)  # compile or load the kernels
    start, cpu = time.perf_counter(), time.process_time()
    value = np.ascontiguousarray(call(photons, spp), dtype=np.float64)
    out[name] = {"seconds": time.perf_counter() - start,
                 "cpu_seconds": time.process_time() - cpu,
                 "sha256": hashlib.sha256(value.tobytes()).hexdigest()[:16],
                 "sum": float(value.sum())}
print("RESULT " + json.dumps(out))
"""


#: The names of TIMED's calls.
CALLS = ("render", "score", "drt")


def worktree(commit: str, work: Path) -> Path:
    """A checkout of ``commit`` under ``work`` (made once)."""
    tree = work / f"tree_{commit}"
    if not (tree / "cloudct").is_dir():
        subprocess.run(["git", "worktree", "add", "--force", "--detach", str(tree), commit],
                       cwd=REPO, check=True, capture_output=True)
    return tree


def timed_run(tree: Path, photons: int, spp: int, cache: Path, calls: list[str]) -> dict:
    """One process of :data:`TIMED` importing cloudct from ``tree``, timing ``calls``."""
    env = dict(os.environ, PYTHONPATH=str(tree), CLOUDCT_CACHE_DIR=str(cache),
               NUMBA_CACHE_DIR=str(cache / "numba"))
    proc = subprocess.run([sys.executable, "-c", TIMED, str(photons), str(spp), ",".join(calls)],
                          env=env, cwd=tempfile.gettempdir(), text=True, capture_output=True,
                          check=True)
    line = [s for s in proc.stdout.splitlines() if s.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def markdown(result: dict) -> str:
    base, now = result["commit_timed"], "this tree"
    runs = result["runs"]
    rows = []
    for name in runs[0]["this"]:
        same = all(r["base"][name]["sha256"] == r["this"][name]["sha256"] for r in runs)
        for clock in ("seconds", "cpu_seconds"):
            old = [r["base"][name][clock] for r in runs]
            new = [r["this"][name][clock] for r in runs]
            ratios = [o / n for o, n in zip(old, new, strict=True)]
            rows.append([name, "wall" if clock == "seconds" else "CPU",
                         " ".join(f"{t:.2f}" for t in old), " ".join(f"{t:.2f}" for t in new),
                         " ".join(f"{q:.3f}" for q in ratios), f"{np.median(ratios):.3f}",
                         f"{sum(old) / sum(new):.3f}", "bitwise" if same else "differ"])
    return "\n".join([
        f"# Speed against {base} ({result['date']}, {result['machine']})", "",
        *markdown_table([
            "estimator", "clock", f"{base} [s]", f"{now} [s]", f"{base} / {now} per run",
            "median ratio", "ratio of sums", "results"], rows),
        "", f"A ratio above 1: {now} is faster. Runs alternate between the trees.", ""])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commit", default="669ae1a")
    parser.add_argument("--photons", type=int, default=1_000_000)
    parser.add_argument("--drt-spp", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--calls", nargs="+", choices=CALLS, default=list(CALLS),
                        help="what to time (default: all)")
    parser.add_argument("--work", type=Path, default=WORK / "against_commit")
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    output = args.output or str(RESULTS / f"speed_against_{args.commit}")
    result = run_header(args)
    result["commit_timed"] = args.commit
    args.work.mkdir(parents=True, exist_ok=True)
    trees = {"base": worktree(args.commit, args.work), "this": REPO}
    caches = {k: args.work / f"cache_{k}" for k in trees}
    with ThreadPoolExecutor() as pool:  # compile each tree's kernels once, untimed, together
        list(pool.map(lambda k: timed_run(trees[k], 64, 1, caches[k], args.calls), trees))
    result["runs"] = []
    for _ in range(args.repeats):
        result["runs"].append({k: timed_run(t, args.photons, args.drt_spp, caches[k],
                                            args.calls)
                               for k, t in trees.items()})
        write_result(result, output, markdown)


if __name__ == "__main__":
    main()
