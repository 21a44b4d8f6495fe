"""How long one image takes a fresh process to detect, with the texture check's cache and without (JSON out).

`foldwise detect` on one photograph, a detect worker's first request and every `bench/wild.py`
score start a process that loads the checkpoint and builds the detector's texture check (SIFT over
each texture and its tilted views, then FLANN's KD-trees) before the network sees a pixel. With
``FOLDWISE_CACHE_DIR`` the check's keypoints and trees are read back instead of made. Each case
runs in a process of its own, the cases interleaved ``--repeats`` times, timed in phases:

- ``without_cache``: ``FOLDWISE_CACHE_DIR`` empty, the check made each time;
- ``cache_cold``: an empty cache folder, the check made and written;
- ``cache_warm``: the folder the cold run wrote, the check read back.

    python bench/detect_startup.py --model var/studies/quick-members-*/ensemble.pt \\
        --image var/bench/wild-ood/images/0000.png --out bench/results/detect_startup.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402  (light: the standard library)

CASES = ("without_cache", "cache_cold", "cache_warm")
PHASES = ("import", "load", "texture_check", "detect")

# One detection, timed in phases, in the process the case set up; prints its phases as JSON.
_CHILD = """
import hashlib, json, sys, time
started = time.perf_counter()
from workers.train.checkpoint import detect_ensemble, load_detector
from workers.train.data import read_image_rgb
phases = {"import": time.perf_counter() - started}
mark = time.perf_counter()
detectors = [load_detector(path, device="cpu") for path in sys.argv[2:]]
phases["load"] = time.perf_counter() - mark
mark = time.perf_counter()
checks = [detector.texture_check() for detector in detectors]
phases["texture_check"] = time.perf_counter() - mark
image = read_image_rgb(sys.argv[1])
mark = time.perf_counter()
(found,) = detect_ensemble(detectors, [image])
phases["detect"] = time.perf_counter() - mark
digest = hashlib.sha256(b"".join(found[key].tobytes() for key in ("boxes", "scores", "labels"))).hexdigest()
print(json.dumps({"phases": phases, "checked": any(check is not None for check in checks), "detections": len(found["scores"]), "digest": digest}))
"""


def run_case(models: list[Path], image: Path, cache_dir: Path | None) -> dict:
    """One fresh process detecting ``image``: its phases (s), its whole wall time, what it found."""
    environment = {**os.environ, "FOLDWISE_CACHE_DIR": "" if cache_dir is None else str(cache_dir)}
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(image), *map(str, models)],
        env=environment,
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"detection process failed ({done.returncode}):\n{done.stderr[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["wall"] = wall
    return result


def _files(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder``, its inode and size: a file written again is renamed into place,
    a new inode (reading a check only touches its time, to keep it in the cache)."""
    stats = {str(path.relative_to(folder)): path.stat() for path in folder.rglob("*") if path.is_file()}
    return {name: (stat.st_ino, stat.st_size) for name, stat in stats.items()}


def measure(models: list[Path], image: Path, repeats: int) -> dict:
    """The three cases, interleaved ``repeats`` times: per case the median of each phase and of the
    wall time, and every run's figures."""
    runs: dict[str, list[dict]] = {case: [] for case in CASES}
    written, rewritten = [], []
    for _ in range(repeats):
        folder = Path(tempfile.mkdtemp(prefix="foldwise-startup-"))
        try:
            runs["without_cache"].append(run_case(models, image, None))
            runs["cache_cold"].append(run_case(models, image, folder))
            cold = _files(folder)
            runs["cache_warm"].append(run_case(models, image, folder))
            written.append(len(cold))
            rewritten.append(_files(folder) != cold)
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    report: dict = {}
    for case, results in runs.items():
        report[case] = {
            "median_seconds": {phase: statistics.median(r["phases"][phase] for r in results) for phase in PHASES},
            "median_wall_seconds": statistics.median(r["wall"] for r in results),
            "texture_checked": all(r["checked"] for r in results),
            "detections": [r["detections"] for r in results],
            "runs": results,
        }
    # The cache changes the time, not the answer: every run found the same boxes, to the byte.
    report["same_detections"] = len({r["digest"] for results in runs.values() for r in results}) == 1
    report["cache_files_written"] = written
    report["warm_run_wrote"] = any(rewritten)
    warm, without = report["cache_warm"], report["without_cache"]
    report["texture_check_speedup"] = without["median_seconds"]["texture_check"] / max(
        warm["median_seconds"]["texture_check"], 1e-9
    )
    report["wall_ratio"] = without["median_wall_seconds"] / max(warm["median_wall_seconds"], 1e-9)
    return report


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--model", type=Path, action="append", required=True, help="a checkpoint; given again, an ensemble"
    )
    parser.add_argument("--image", type=Path, required=True)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    missing = [str(path) for path in [*args.model, args.image] if not path.is_file()]
    if missing:
        parser.error(f"not found: {', '.join(missing)}")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    report = {"models": [str(path) for path in args.model], "image": str(args.image), "repeats": args.repeats}
    report.update(measure(args.model, args.image, args.repeats))
    report["machine"] = machine()
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
