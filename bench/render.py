"""Render benchmark: raster vs blender on one fixed set of θ, side by side.

For every (condition, difficulty) of Table 3 plus canonical, ``--n-per-stage`` θ are drawn
with a fixed seed at ``--size``² pixels. Each θ is rendered by every backend in turn
(interleaved, alternating which goes first, so machine load hits both alike), timed around
``render_theta``. Reported:

* images per second per backend and their ratio (raster / blender) for the whole
  ``render_theta`` and for its 3D ``render`` stage alone, with the mean of each pipeline
  stage's time (``RenderResult.timings``) so it is plain where the time goes. The headline
  ratio (``speed_ratio.value``) times raster as a raster render worker runs: in a process of
  its own that never loads bpy, over the θ set (``--own-pass-repeats`` passes before the
  interleaved loop and as many after it, so drift in machine load cancels). In the loop's
  process raster runs after Cycles on each θ: Cycles' threads sweep every CPU cache, and once
  bpy has rendered, raster stays ~15% slower in that process. That interleaved figure is
  reported beside the headline (``speed_ratio.interleaved``), never dropped;
* raster's all-cores throughput (``--processes``, default the CPUs allowed; 0 skips it): Cycles
  keeps every core busy with threads in one process, raster is mostly single-threaded, so the
  same θ set is also dealt round-robin to that many single-threaded raster processes (caches
  warmed untimed, ``--parallel-repeats`` passes, timed from a common start to the last
  worker's end) and its ratio to blender is reported beside, never instead of, the
  single-process one (``speed_ratio.value`` vs ``speed_ratio.all_cores``);
* box agreement: IoU between the two backends' boxes (the visible box after occlusion and
  border crop) per θ, its mean, min and the worst θ, also per condition and per difficulty;
  the IoU of the visible masks themselves likewise;
  amodal-box IoU, the visible-fraction difference and the mean absolute difference of the
  two final images (uint8 levels) alongside;
* rejections (``RenderRejected``) per backend, with their reasons, and any other exception
  (a backend bug) with the θ it happened on; such θ are left out of the timings and IoUs.

Prints JSON to stdout (and to ``--out FILE``). Example::

    python bench/render.py --n-per-stage 3 --samples 16 --size 256 --out render.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

BACKENDS = ("raster", "blender")


def cpu_model() -> str:
    """The CPU's model name (Linux), else what platform knows."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def box_iou(a, b) -> float:
    """IoU of two [x0, y0, x1, y1] boxes (pixel-edge coordinates)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    inter_w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    inter_h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = inter_w * inter_h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def fixed_thetas(n_per_stage: int, size: int, seed: int, assets, conditions: tuple[str, ...] | None = None) -> list:
    """The benchmark's θ: canonical, then every condition × difficulty of ``conditions``
    (default: Table 3, the set the speed goals were set on)."""
    from foldwise.conditions import load_condition_table
    from foldwise.sampling import derive_seed, generate_parameters

    table = load_condition_table()
    codes = conditions or table.table3
    stages = [(codes[0], "canonical")] + [(c, d) for c in codes for d in table.difficulties]
    thetas = []
    for index, (condition, difficulty) in enumerate(stages):
        thetas += generate_parameters(
            condition, difficulty, n_per_stage, derive_seed(seed, index), image_size=size, assets=assets
        )
    return thetas


def stage_of(theta: dict) -> str:
    return "canonical" if theta.difficulty == "canonical" else f"{theta.condition}/{theta.difficulty}"


def summarise(values: list[float]) -> dict:
    if not values:
        return {"n": 0}
    array = np.asarray(values, dtype=np.float64)
    return {"n": int(array.size), "mean": float(array.mean()), "min": float(array.min())}


def _raster_worker(thetas: list[dict], repeats: int, barrier, results, opencv_threads: int | None = 1) -> None:
    """One raster process: OpenCV with ``opencv_threads`` (1 when the processes are the
    parallelism, None for its default), caches warmed on its θ untimed, then its θ
    ``repeats`` times between two barriers."""
    try:
        import cv2

        if opencv_threads is not None:
            cv2.setNumThreads(opencv_threads)
        from workers.render.assets import load_assets
        from workers.render.pipeline import RenderRejected, render_theta

        assets = load_assets()
        for theta in thetas:
            with contextlib.suppress(Exception):
                render_theta(theta, backend="raster", assets=assets)
    except BaseException:
        barrier.abort()  # the parent stops waiting at once
        raise
    rendered = rejected = errors = 0
    barrier.wait()
    begin = time.perf_counter()
    for _ in range(repeats):
        for theta in thetas:
            try:
                render_theta(theta, backend="raster", assets=assets)
                rendered += 1
            except RenderRejected:
                rejected += 1
            except Exception:  # a backend bug: the single-process run reports it with its θ
                errors += 1
    end = time.perf_counter()
    results.put({"rendered": rendered, "rejected": rejected, "errors": errors, "begin": begin, "end": end})


def _raster_pass(thetas: list[dict], repeats: int) -> dict:
    """``repeats`` timed raster passes over ``thetas`` in one fresh process that never loads
    bpy, as a raster render worker runs (OpenCV with its default threads; caches warmed
    untimed). In the benchmark's own process, once bpy has rendered, raster runs ~15% slower."""
    measured = raster_in_processes(thetas, 1, repeats, opencv_threads=None)
    return {key: measured[key] for key in ("images", "rejected", "errors", "wall_seconds", "images_per_second")}


def raster_in_processes(thetas: list[dict], processes: int, repeats: int, opencv_threads: int | None = 1) -> dict:
    """Raster throughput with ``processes`` fresh worker processes that never load bpy (θ dealt
    round-robin), measured from a common start to the last worker's end. With as many
    processes as CPUs: the same θ set, all cores busy, as Cycles keeps them busy with its
    threads inside one process."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")  # never fork a process that holds bpy
    barrier = context.Barrier(processes + 1)
    results = context.Queue()
    workers = [
        context.Process(
            target=_raster_worker,
            args=(thetas[index::processes], repeats, barrier, results, opencv_threads),
            daemon=True,
        )
        for index in range(processes)
    ]
    for worker in workers:
        worker.start()
    try:
        barrier.wait(timeout=600)  # every worker warm
        reports = [results.get(timeout=600) for _ in workers]
        # perf_counter is the system-wide monotonic clock on Linux: comparable across processes.
        wall = max(r["end"] for r in reports) - min(r["begin"] for r in reports)
    finally:
        for worker in workers:
            worker.join(timeout=30)
            if worker.is_alive():
                worker.terminate()
    rendered = sum(r["rendered"] for r in reports)
    return {
        "processes": processes,
        "opencv_threads_per_process": opencv_threads if opencv_threads is not None else "default",
        "repeats_of_theta_set": repeats,
        "images": rendered,
        "rejected": sum(r["rejected"] for r in reports),
        "errors": sum(r["errors"] for r in reports),
        "wall_seconds": wall,
        "images_per_second": rendered / wall if wall > 0 else math.nan,
        "worker_seconds": [r["end"] - r["begin"] for r in reports],
    }


def run(
    n_per_stage: int,
    samples: int,
    size: int,
    backends: list[str],
    seed: int,
    progress: bool,
    processes: int = 0,
    parallel_repeats: int = 5,
    own_pass_repeats: int = 3,
    conditions: tuple[str, ...] | None = None,
) -> dict:
    from foldwise.conditions import load_condition_table
    from workers.render.assets import load_assets
    from workers.render.pipeline import RenderRejected, render_theta

    assets = load_assets()
    thetas = fixed_thetas(n_per_stage, size, seed, assets, conditions)

    # Warm-up outside the clock: imports and the bpy scene (one θ per backend), then every θ
    # once through the fastest backend so per-asset caches (background crops, occluders,
    # texture pyramids) are warm for both: otherwise whichever backend goes first pays them.
    warm = fixed_thetas(1, size, seed + 1, assets)[0]
    for backend in backends:
        with contextlib.suppress(Exception):
            render_theta(warm, backend=backend, assets=assets, samples=samples)
    if "raster" in backends:
        for theta in thetas:
            with contextlib.suppress(Exception):
                render_theta(theta, backend="raster", assets=assets)

    load_before = os.getloadavg()
    own_passes = []  # raster alone over the θ set, before and after the interleaved loop
    if "raster" in backends and len(backends) > 1:
        own_passes.append(_raster_pass(thetas, own_pass_repeats))
    seconds = {b: 0.0 for b in backends}
    rendered = {b: 0 for b in backends}
    stage_seconds = {b: defaultdict(float) for b in backends}
    rejections = {b: defaultdict(int) for b in backends}
    failures = {b: [] for b in backends}  # exceptions other than RenderRejected (untimed)
    per_theta = []
    started = time.perf_counter()
    for index, theta in enumerate(thetas):
        results = {}
        # Alternate which backend goes first, so neither always runs on caches the other
        # just cooled (Cycles' threads sweep the CPU caches).
        for backend in backends if index % 2 == 0 else backends[::-1]:
            begin = time.perf_counter()
            try:
                result = render_theta(theta, backend=backend, assets=assets, samples=samples)
            except RenderRejected as rejected:
                seconds[backend] += time.perf_counter() - begin
                rejections[backend][rejected.reason] += 1
                results[backend] = None
                continue
            except Exception as error:  # a backend bug: record it, keep measuring the rest
                failures[backend].append({"index": index, "stage": stage_of(theta), "error": repr(error)[:300]})
                results[backend] = None
                continue
            seconds[backend] += time.perf_counter() - begin
            rendered[backend] += 1
            for stage, value in result.timings.items():
                stage_seconds[backend][stage] += float(value)
            results[backend] = result
        row = {"index": index, "stage": stage_of(theta), "theta": theta.to_dict()}
        for backend in backends:
            result = results[backend]
            row[backend] = (
                None
                if result is None
                else {
                    "box": [float(v) for v in result.box],
                    "visible_fraction": float(result.visible_fraction),
                    "amodal_box": None if result.amodal_box is None else [float(v) for v in result.amodal_box],
                }
            )
        if len(backends) == 2 and all(results[b] is not None for b in backends):
            first, second = (results[b] for b in backends)
            row["box_iou"] = box_iou(first.box, second.box)
            if first.amodal_box is not None and second.amodal_box is not None:
                row["amodal_box_iou"] = box_iou(first.amodal_box, second.amodal_box)
            row["visible_fraction_diff"] = abs(float(first.visible_fraction) - float(second.visible_fraction))
            if first.mask is not None and second.mask is not None:
                union = np.count_nonzero(first.mask | second.mask)
                row["mask_iou"] = float(np.count_nonzero(first.mask & second.mask) / union) if union else 1.0
            # How alike the final images look (uint8 levels, whole image incl. background).
            row["image_mean_abs_diff"] = float(
                np.abs(first.image.astype(np.int16) - second.image.astype(np.int16)).mean()
            )
        per_theta.append(row)
        if progress:
            print(f"\r{index + 1}/{len(thetas)} θ", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    if own_passes:
        own_passes.append(_raster_pass(thetas, own_pass_repeats))

    speed = {}
    for backend in backends:
        count = rendered[backend]
        speed[backend] = {
            "images": count,
            "rejected": int(sum(rejections[backend].values())),
            "seconds": seconds[backend],
            "images_per_second": count / seconds[backend] if seconds[backend] > 0 else math.nan,
            "mean_stage_seconds": {k: v / max(count, 1) for k, v in sorted(stage_seconds[backend].items())},
            "rejection_reasons": dict(rejections[backend]),
            "errors": failures[backend],
        }
    if own_passes:
        images = sum(p["images"] for p in own_passes)
        own_seconds = sum(p["wall_seconds"] for p in own_passes)
        speed["raster"]["interleaved_images_per_second"] = speed["raster"]["images_per_second"]
        speed["raster"]["own_passes"] = {
            "passes": own_passes,
            "images_per_second": images / own_seconds if own_seconds > 0 else math.nan,
        }
    report: dict = {
        "settings": {
            "conditions": list(conditions or load_condition_table().table3),
            "n_per_stage": n_per_stage,
            "samples": samples,
            "size": size,
            "backends": backends,
            "seed": seed,
            "thetas": len(thetas),
        },
        "speed": speed,
        "wall_seconds": time.perf_counter() - started,
        # Timings depend on what else runs: say how busy the machine was.
        "machine": {
            "cpus_allowed": len(os.sched_getaffinity(0)),
            "load_average_1min_before": load_before[0],
            "load_average_1min_after": os.getloadavg()[0],
            "python": platform.python_version(),
            # The ratio depends on the CPU: raster is mostly scalar code, Cycles vectorised (the
            # same code gave 88x on one of this project's 2-core machines and 118x on another).
            "cpu": cpu_model(),
        },
    }
    if "raster" in backends and processes > 0:
        report["raster_all_cores"] = raster_in_processes(thetas, processes, parallel_repeats)
    if len(backends) == 2:
        fast, slow = "raster", "blender"  # the ratio reads the same whatever order was asked
        report["speed_ratio"] = {
            "of": f"{fast}/{slow} images per second, whole render_theta, each in one process "
            f"(Cycles with {report['machine']['cpus_allowed']} threads, raster's OpenCV with its default threads); "
            f"{fast} timed as a raster worker runs: in a process of its own that never loads bpy, before and after the interleaved loop",
            "value": speed[fast]["own_passes"]["images_per_second"] / speed[slow]["images_per_second"],
            "interleaved": {
                "of": f"{fast} timed per θ right after or before {slow} on the same θ",
                "value": speed[fast]["interleaved_images_per_second"] / speed[slow]["images_per_second"],
            },
            # The 3D backend alone (the "render" stage): what differs between the two.
            "render_stage": speed[slow]["mean_stage_seconds"].get("render", math.nan)
            / speed[fast]["mean_stage_seconds"].get("render", math.nan),
        }
        if "raster_all_cores" in report:
            report["speed_ratio"]["all_cores"] = {
                "of": f"{fast} in {processes} single-threaded processes / {slow} in one process using "
                f"{report['machine']['cpus_allowed']} threads, images per second, whole render_theta",
                "value": report["raster_all_cores"]["images_per_second"] / speed[slow]["images_per_second"],
            }
        compared = [row for row in per_theta if "box_iou" in row]
        ious = [row["box_iou"] for row in compared]
        by_condition, by_difficulty, mask_by_condition = defaultdict(list), defaultdict(list), defaultdict(list)
        for row in compared:
            condition = row["theta"]["condition"] if row["stage"] != "canonical" else "canonical"
            by_condition[condition].append(row["box_iou"])
            by_difficulty[row["theta"]["difficulty"]].append(row["box_iou"])
            if "mask_iou" in row:
                mask_by_condition[condition].append(row["mask_iou"])
        worst = min(compared, key=lambda row: row["box_iou"]) if compared else None
        report["box_iou"] = {
            **summarise(ious),
            "below_0.98": int(sum(v < 0.98 for v in ious)),
            "amodal": summarise([row["amodal_box_iou"] for row in compared if "amodal_box_iou" in row]),
            "visible_fraction_abs_diff": summarise([row["visible_fraction_diff"] for row in compared]),
            "image_mean_abs_diff_uint8": {
                **summarise([row["image_mean_abs_diff"] for row in compared]),
                "max": max((row["image_mean_abs_diff"] for row in compared), default=None),
            },
            "per_condition": {k: summarise(v) for k, v in sorted(by_condition.items())},
            "per_difficulty": {k: summarise(v) for k, v in sorted(by_difficulty.items())},
            "worst": worst,
            "rejected_by_one_backend_only": int(sum((row[fast] is None) != (row[slow] is None) for row in per_theta)),
        }
        mask_ious = [row["mask_iou"] for row in compared if "mask_iou" in row]
        report["mask_iou"] = {
            **summarise(mask_ious),
            "per_condition": {k: summarise(v) for k, v in sorted(mask_by_condition.items())},
        }
        report["targets"] = {
            "mean_box_iou_at_least_0.98": bool(ious) and float(np.mean(ious)) >= 0.98,
            f"{fast}_at_least_100x_{slow}_whole_pipeline": report["speed_ratio"]["value"] >= 100.0,
            f"{fast}_interleaved_at_least_100x_{slow}_whole_pipeline": report["speed_ratio"]["interleaved"]["value"]
            >= 100.0,
            f"{fast}_at_least_100x_{slow}_render_stage": report["speed_ratio"]["render_stage"] >= 100.0,
        }
        if "all_cores" in report["speed_ratio"]:
            report["targets"][f"{fast}_all_cores_at_least_100x_{slow}_whole_pipeline"] = (
                report["speed_ratio"]["all_cores"]["value"] >= 100.0
            )
        report["worst_5"] = sorted(compared, key=lambda row: row["box_iou"])[:5]
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-per-stage", type=int, default=3, help="θ per (condition, difficulty) and canonical")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (blender)")
    parser.add_argument("--size", type=int, default=256, help="image side in pixels")
    parser.add_argument("--backends", default="raster,blender", help="comma-separated, e.g. raster,blender")
    parser.add_argument("--seed", type=int, default=2018)
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    parser.add_argument(
        "--processes",
        type=int,
        default=len(os.sched_getaffinity(0)),
        help="raster worker processes for the all-cores figure (default: the CPUs allowed; 0: skip it)",
    )
    parser.add_argument("--parallel-repeats", type=int, default=5, help="times each all-cores worker renders its θ")
    parser.add_argument(
        "--own-pass-repeats",
        type=int,
        default=3,
        help="raster's own passes over the θ set before, and again after, the interleaved loop",
    )
    parser.add_argument(
        "--conditions",
        default="table3",
        help="table3 (the paper's 7, the default), all (every condition of the table) or codes, comma-separated",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    args = parser.parse_args(argv)
    from foldwise.conditions import load_condition_table

    table = load_condition_table()
    if args.conditions == "table3":
        conditions = table.table3
    elif args.conditions == "all":
        conditions = table.codes
    else:
        conditions = tuple(c.strip() for c in args.conditions.split(",") if c.strip())
        strangers = [c for c in conditions if c not in table.conditions]
        if strangers or not conditions:
            parser.error(
                f"--conditions: unknown {strangers or args.conditions!r}; known: table3, all, {', '.join(table.codes)}"
            )
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = [b for b in backends if b not in BACKENDS]
    if unknown or not backends or len(set(backends)) != len(backends):
        parser.error(f"--backends: expected distinct names among {', '.join(BACKENDS)}, got {args.backends!r}")
    if args.n_per_stage < 1 or args.samples < 1 or args.size < 16:
        parser.error("--n-per-stage and --samples must be >= 1, --size >= 16")
    if args.processes < 0 or args.parallel_repeats < 1 or args.own_pass_repeats < 1:
        parser.error("--processes must be >= 0, --parallel-repeats and --own-pass-repeats >= 1")
    report = run(
        args.n_per_stage,
        args.samples,
        args.size,
        backends,
        args.seed,
        progress=not args.quiet,
        processes=args.processes,
        parallel_repeats=args.parallel_repeats,
        own_pass_repeats=args.own_pass_repeats,
        conditions=conditions,
    )
    text = json.dumps(report, indent=2, default=float)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
