"""Paper model benchmark: cost of ``sample_sheet`` per ruling count, minimal vs refined mesh.

For every guiding-ruling count, the same seeds are drawn with both meshes, side by side in
one run (interleaved, alternating which goes first, so machine load hits both alike):

* ``minimal``: the default, ``sample_sheet(n, rng, W, H)``: sheet corners and ruling ends
  only, ``2 n_fold + 2`` triangles;
* ``refined``: ``max_edge`` = the layout step (sqrt(W H)/16 for an A4 sheet), the mesh the
  paper model always built before the minimal one (border and rulings subdivided, grid
  points inside every region, Delaunay per region);
* with ``--baseline REV``, ``baseline``: the default minimal mesh of the paper model as it
  was at git revision REV (loaded from ``git show``), to time a change old against new in
  one process. Its sheets are compared with today's: the same seeds should give the same
  rulings and faces, and vertices within 1e-12 of the sheet size.

Reported per count and mesh: milliseconds per call, wall clock and CPU time (process time,
less sensitive to other processes on a shared machine), as median, mean, p10 and p90, over
every call (sheets rejected as self-intersecting included: the pipeline pays for them too);
triangle and vertex counts; rejections. Then the refined / minimal ratio of median times
(and baseline / minimal, with how many sheets and rejections agree),
the targets (minimal, CPU median: 8 rulings <= 2 ms, 2 rulings <= 1 ms) met or not, and the
load average before and after. ``--profile`` adds the functions where the minimal mesh's
time goes (cProfile, own time per sheet) for the largest count.

Prints JSON to stdout (and to ``--out FILE``). Example::

    python bench/paper_model.py --seeds 300 --out paper_model.json
    python bench/paper_model.py --counts 2 3 5 8 --baseline HEAD~1
"""

from __future__ import annotations

import argparse
import cProfile
import importlib.util
import json
import math
import os
import platform
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TARGETS_MS = {8: 2.0, 2: 1.0}  # minimal mesh, CPU median per sheet
ROOT = Path(__file__).resolve().parent.parent


def layout_step(width: float, height: float) -> float:
    """The paper model's default layout step, which its refined mesh used as edge length."""
    return min(math.sqrt(width * height) / 16.0, min(width, height) / 4.0)


def summarise_ms(seconds: list[float]) -> dict:
    ms = np.asarray(seconds) * 1e3
    return {
        "median": float(np.median(ms)),
        "mean": float(ms.mean()),
        "p10": float(np.percentile(ms, 10)),
        "p90": float(np.percentile(ms, 90)),
    }


def time_one(n_rulings: int, seed: int, width: float, height: float, opts: dict, sample_sheet, rejection):
    """(wall seconds, cpu seconds, mesh or None when rejected)."""
    rng = np.random.default_rng(seed)  # made outside the clock
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        mesh = sample_sheet(n_rulings, rng, width, height, **opts)
    except rejection:
        mesh = None
    return time.perf_counter() - wall, time.process_time() - cpu, mesh


def load_baseline(revision: str):
    """The paper model module as it was at a git revision, imported from a temporary file (a
    file, not a string, so that compiled code can cache as usual)."""
    source = subprocess.run(
        ["git", "show", f"{revision}:workers/render/paper_model.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    path = Path(tempfile.mkdtemp(prefix="paper_model_baseline_")) / "paper_model_baseline.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("paper_model_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


def same_sheet(first, second) -> bool:
    """Both rejected, or the same rulings and mesh with vertices within 1e-12 of the size."""
    if first is None or second is None:
        return first is None and second is None
    scale = max(first.width, first.height)
    return (
        first.rulings == second.rulings
        and first.fold_lines == second.fold_lines
        and np.array_equal(first.flat, second.flat)
        and np.array_equal(first.faces, second.faces)
        and np.allclose(first.vertices, second.vertices, rtol=0, atol=1e-12 * scale)
    )


def run(counts: list[int], seeds: int, width: float, height: float, profile: bool, baseline: str | None = None) -> dict:
    from workers.render.paper_model import SelfIntersection, sample_sheet

    # mode -> (sample_sheet, options, rejection)
    modes = {
        "minimal": (sample_sheet, {}, SelfIntersection),
        "refined": (sample_sheet, {"max_edge": layout_step(width, height)}, SelfIntersection),
    }
    if baseline is not None:
        old = load_baseline(baseline)
        modes["baseline"] = (old.sample_sheet, {}, old.SelfIntersection)
    # Warm-up outside the clock: imports (scipy for the refined mesh), compiled code, caches.
    for function, opts, rejection in modes.values():
        for n in counts:
            time_one(n, 10**6, width, height, opts, function, rejection)

    load_before = os.getloadavg()
    results = {}
    for n in counts:
        wall = {m: [] for m in modes}
        cpu = {m: [] for m in modes}
        triangles = {m: [] for m in modes}
        vertices = {m: [] for m in modes}
        rejected = {m: 0 for m in modes}
        agree = 0
        names = list(modes)
        for seed in range(seeds):
            meshes = {}
            for mode in names if seed % 2 == 0 else names[::-1]:
                function, opts, rejection = modes[mode]
                seconds, cpu_seconds, mesh = time_one(n, seed, width, height, opts, function, rejection)
                meshes[mode] = mesh
                wall[mode].append(seconds)
                cpu[mode].append(cpu_seconds)
                if mesh is None:
                    rejected[mode] += 1
                else:
                    triangles[mode].append(len(mesh.faces))
                    vertices[mode].append(len(mesh.flat))
            if baseline is not None:
                agree += same_sheet(meshes["minimal"], meshes["baseline"])
        row = {}
        for mode in modes:
            row[mode] = {
                "wall_ms": summarise_ms(wall[mode]),
                "cpu_ms": summarise_ms(cpu[mode]),
                "triangles": {
                    "mean": float(np.mean(triangles[mode])),
                    "min": int(np.min(triangles[mode])),
                    "max": int(np.max(triangles[mode])),
                }
                if triangles[mode]
                else None,
                "vertices_mean": float(np.mean(vertices[mode])) if vertices[mode] else None,
                "rejected": rejected[mode],
            }
        for other in ("refined", "baseline"):
            if other in modes:
                row[f"{other}_over_minimal"] = {
                    clock: row[other][clock]["median"] / row["minimal"][clock]["median"]
                    for clock in ("wall_ms", "cpu_ms")
                }
        if baseline is not None:
            row["baseline_same_sheets"] = f"{agree}/{seeds}"
        results[str(n)] = row

    targets = {
        str(n): {
            "limit_ms": limit,
            "cpu_median_ms": results[str(n)]["minimal"]["cpu_ms"]["median"],
            "met": results[str(n)]["minimal"]["cpu_ms"]["median"] <= limit,
        }
        for n, limit in TARGETS_MS.items()
        if str(n) in results
    }
    report = {
        "sheet_m": [width, height],
        "seeds_per_count": seeds,
        "modes": {m: opts for m, (_, opts, _) in modes.items()},
        "baseline_revision": baseline,
        "by_rulings": results,
        "minimal_ms_per_sheet": {n: row["minimal"]["wall_ms"]["median"] for n, row in results.items()},
        "targets_minimal_cpu_median": targets,
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
            "load_average_1min_before": load_before[0],
            "load_average_1min_after": os.getloadavg()[0],
        },
    }
    if profile:
        report["profile_minimal"] = profile_minimal(max(counts), seeds, width, height, sample_sheet, SelfIntersection)
    return report


def profile_minimal(n: int, seeds: int, width: float, height: float, sample_sheet, rejection) -> dict:
    """Own time per sheet (ms) of the functions that take the most, under cProfile (which
    slows everything down: compare the entries with each other, not with the timings)."""
    rngs = [np.random.default_rng(seed) for seed in range(seeds)]
    profiler = cProfile.Profile()
    profiler.enable()
    for rng in rngs:
        try:
            sample_sheet(n, rng, width, height)
        except rejection:
            pass
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    rows = sorted(stats.items(), key=lambda item: item[1][2], reverse=True)[:15]
    return {
        "rulings": n,
        "top_own_time": [
            {
                "function": f"{Path(file).name}:{line}({name})",
                "calls_per_sheet": calls / seeds,
                "own_ms_per_sheet": own * 1e3 / seeds,
                "cumulative_ms_per_sheet": cumulative * 1e3 / seeds,
            }
            for (file, line, name), (_, calls, own, cumulative, _) in rows
        ],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[0, 2, 3, 5, 8], help="guiding ruling counts")
    parser.add_argument("--seeds", type=int, default=200, help="sheets per count and mesh")
    parser.add_argument("--width", type=float, default=0.21, help="sheet width, metres")
    parser.add_argument("--height", type=float, default=0.297, help="sheet height, metres")
    parser.add_argument("--profile", action="store_true", help="add a cProfile breakdown of the minimal mesh")
    parser.add_argument("--baseline", metavar="REV", help="also time the paper model of this git revision")
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    args = parser.parse_args(argv)
    if args.seeds < 1 or any(n < 0 for n in args.counts):
        parser.error("--seeds must be >= 1 and --counts non-negative")
    report = run(args.counts, args.seeds, args.width, args.height, args.profile, args.baseline)
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
