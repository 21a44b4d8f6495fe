"""Out-of-domain benchmark: does the detector foldwise trains find the object in images foldwise did not render?

Trains with a config as ``make run`` does (default ``configs/quick.yaml``, two curricula handed
over as one ensemble; ``--members 1``: one) or takes a checkpoint, then scores the model, under the paper's protocol (score ≥ 0.8, IoU 0.5) and
unthresholded, on two sets:

* **in-domain**: foldwise's own renders, every (condition, difficulty) of the config's
  curriculum plus its mixed stage, drawn by ``foldwise.sampling`` and rendered by the config's
  backend (the standard test set's recipe, with a seed of its own);
* **out-of-domain**: a scene built in Blender (Cycles, bench/wild_scene.py) that no training path uses.
  Nothing of foldwise's θ, camera, sheet model, lighting, compositing or imaging code is
  called: the sheet lies on a textured ground in a 3D world and is bent by a cylindrical curl
  of its own (not foldwise's ruling model); a principled BSDF with a glossy coat; a sun of
  random colour, height and softness casting real shadows, a sky or coloured ambient world
  light, sometimes a point light; a camera anywhere on the upper hemisphere with a focal length
  from 8° to 100° of field of view (beyond the training range at both ends), the sheet filling
  from a tenth to more than the whole frame, partly outside it; primitives and sheets of
  other photographs as clutter, beside the target, over it, and casting shadows on it; a
  second target; Blender's own tone mapping (Standard or AgX) and exposure; sensor noise and
  JPEG at random quality; 10% images without the object; 4:3 frames. Boxes are the visible
  extent of each target, read from an object-index render (one sample, no pixel filter).

The set is written as a COCO folder (``--ood-dir``) and reused when its recipe is unchanged.
A second set of the same scene, drawn apart (100 images at 480×360, seed 7: ``--n-ood-second``,
``--ood-second-size``, ``--ood-second-seed``; 0 images skips it), is scored beside it, so that
no lever is judged on one set of draws (a set of 100 images moves by about ±0.05 between draws).
Both cover the ground and the clutter with photographs that are also foldwise's training
backgrounds and occluders; a third set (100 images at 320×240, seed 11: ``--n-ood-apart``,
``--ood-apart-size``, ``--ood-apart-seed``) uses photographs that no training path reads
(``PHOTO_POOLS["held_apart"]``), so a detector that knew its training backgrounds by heart
would be seen to fail there.
It is a proxy for photographs, made by independent code; it is not the held-out set that
scores foldwise's landings, and nothing in foldwise is tuned to it.

    python bench/wild.py                                  # train configs/quick.yaml, then score
    python bench/wild.py --model var/.../model.pt         # score a checkpoint
    python bench/wild.py --model M.pt --n-ood 300 --out bench/results/wild.json
    python bench/wild.py --model M.pt --test-sizes 128         # detect at one input size only
    python bench/wild.py --model M.pt --test-turns 0           # upright views only

Two more in-domain scores: ``in_domain_reframed`` puts the in-domain images in 4:3 and 3:4 frames
(mirrored borders): the same objects, other frames; ``in_domain_rotated`` turns them by
quarter turns (boxes exact): the same objects, any camera roll.

JSON out: the mAPs, the out-of-domain / in-domain ratio of each out-of-domain set (the goal,
≥ 0.8, is met only when every one reaches it), each set's class-agnostic mAP (any
class at a target counts: finding the sheet apart from naming it), the out-of-domain breakdown by scene
kind (negatives, small / medium / large / frame-filling sheets, occluded, several targets),
the time each part took and the machine.

The parts, a module each: bench/wild_scene.py (the recipe, the sheet's bends and the Blender
scene), bench/wild_sets.py (the named sets: out of domain, in domain, reframed, rotated),
bench/wild_scoring.py (mAP, precision and recall at the threshold, the keypoint baseline beside
foldwise) and bench/report.py (the machine and the JSON report). This file trains or takes the
model and is the command line.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402
from bench.wild_scene import FACTORS, OodRecipe, lookalike_names  # noqa: E402
from bench.wild_scoring import score, score_keypoint_baseline  # noqa: E402
from bench.wild_sets import make_in_domain_set, make_ood_set, make_reframed_set, make_rotated_set  # noqa: E402

# --------------------------------------------------------------------------- training


def train_with_config(config_path: Path, data_dir: Path, echo=print, members: int = 1) -> tuple[Path, dict]:
    """Run ``foldwise run CONFIG --members N`` in a data directory of its own; return the final
    model's checkpoint (with several members, the ensemble file the run hands over)."""
    env = {**os.environ, "FOLDWISE_DATA_DIR": str(data_dir), "FOLDWISE_DATABASE_URL": ""}
    env.pop("FOLDWISE_DATABASE_URL")
    started = time.perf_counter()
    completed = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(config_path), "--members", str(members)],
        cwd=ROOT, env=env, capture_output=True, text=True,
    )  # fmt: skip
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        raise RuntimeError(
            f"foldwise run {config_path} failed ({completed.returncode}):\n{completed.stdout[-3000:]}{completed.stderr[-3000:]}"
        )
    echo(f"trained {config_path} in {seconds:.0f} s")
    training = {"config": str(config_path), "members": members, "seconds": seconds}
    if members > 1:
        ensembles = sorted((data_dir / "studies").glob("*/ensemble.pt"), key=lambda path: path.stat().st_mtime)
        if not ensembles:
            raise RuntimeError(f"{config_path}: the run finished without an ensemble file under {data_dir / 'studies'}")
        return ensembles[-1], training
    import sqlite3

    with sqlite3.connect(data_dir / "foldwise.db") as connection:
        row = connection.execute(
            "SELECT m.checkpoint_path FROM experiments e JOIN models m ON m.id = e.final_model_id ORDER BY e.id DESC LIMIT 1"
        ).fetchone()
    if row is None or not row[0]:
        raise RuntimeError(f"{config_path}: the experiment finished without a final model")
    checkpoint = Path(row[0])
    if not checkpoint.is_absolute():
        checkpoint = data_dir / checkpoint
    return checkpoint, training


def make_run_members(config_path: Path) -> int:
    """The curricula ``make run`` trains for this config (the Makefile's MEMBERS default)."""
    return 2 if Path(config_path).resolve() == (ROOT / "configs" / "quick.yaml").resolve() else 1


def _config_argument(parser_name: str):
    """An argparse ``type`` that reads a list as ``foldwise.config.<parser_name>`` does (imported
    when an argument is read, so ``--help`` stays cheap); its error is argparse's message."""

    def read(text: str) -> tuple[int, ...]:
        from foldwise import config

        try:
            return getattr(config, parser_name)(text)
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    return read


def _positive_count(text: str) -> int:
    """An argparse ``type`` for the first set's size: 0 would replace a cached set by an empty one."""
    try:
        count = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if count < 1:
        raise argparse.ArgumentTypeError(f"{count}: the first out-of-domain set needs at least 1 image")
    return count


def _frame_argument(text: str) -> tuple[int, int]:
    """An argparse ``type`` for WIDTHxHEIGHT (every set's ``--…-size``): a bad one is argparse's message."""
    try:
        width, height = (int(value) for value in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be at least 1 pixel")
    return width, height


_test_sizes_argument = _config_argument("parse_test_sizes")
_test_turns_argument = _config_argument("parse_test_turns")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml")
    parser.add_argument(
        "--model",
        type=Path,
        action="append",
        help="score this checkpoint instead of training; given again, the checkpoints are scored as one ensemble",
    )
    parser.add_argument(
        "--members",
        type=_positive_count,
        default=None,
        help="when training: curricula side by side, handed over as one ensemble (default: make run's, "
        "2 for configs/quick.yaml, else 1)",
    )
    parser.add_argument("--n-ood", type=_positive_count, default=200, help="out-of-domain images (at least 1)")
    parser.add_argument(
        "--ood-size", type=_frame_argument, default="320x240", help="WIDTHxHEIGHT of out-of-domain images"
    )
    parser.add_argument("--ood-samples", type=int, default=24, help="Cycles samples per out-of-domain image")
    parser.add_argument("--ood-seed", type=int, default=2026)
    parser.add_argument("--ood-dir", type=Path, default=None, help="default: var/bench/wild-ood[-FACTORS]")
    # A second out-of-domain set, drawn apart (its own seed, larger frames), so that no lever is
    # chosen on one set of draws alone: the goal is met only when both ratios reach it.
    parser.add_argument(
        "--n-ood-second", type=int, default=100, help="images of the second out-of-domain set (0: none)"
    )
    parser.add_argument(
        "--ood-second-size", type=_frame_argument, default="480x360", help="WIDTHxHEIGHT of the second set's images"
    )
    parser.add_argument("--ood-second-seed", type=int, default=7)
    parser.add_argument("--ood-second-dir", type=Path, default=None, help="default: var/bench/wild-ood-b[-FACTORS]")
    # A third set whose ground and clutter photographs no training path uses (PHOTO_POOLS): the
    # first two reuse foldwise's own background and occluder photographs.
    parser.add_argument(
        "--n-ood-apart", type=int, default=100, help="images of the held-apart-photographs set (0: none)"
    )
    parser.add_argument(
        "--ood-apart-size", type=_frame_argument, default="320x240", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-apart-seed", type=int, default=11)
    parser.add_argument("--ood-apart-dir", type=Path, default=None, help="default: var/bench/wild-ood-apart[-FACTORS]")
    # A fourth, on request: larger frames (photographs are rarely as small as 320x240; a sheet then
    # holds more pixels for the network's larger views and for SIFT). Off by default: Cycles takes
    # about 10 min for 100 images at 640x480 on 2 cores.
    parser.add_argument("--n-ood-large", type=int, default=0, help="images of the large-frame set (0: none; e.g. 100)")
    parser.add_argument(
        "--ood-large-size", type=_frame_argument, default="640x480", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-large-seed", type=int, default=13)
    parser.add_argument("--ood-large-dir", type=Path, default=None, help="default: var/bench/wild-ood-large[-FACTORS]")
    # The hard set: small sheets, tubes and creases, lookalikes (with --lookalikes), extremes of
    # exposure and light colour, uneven ground, JPEG down to 35 (OodRecipe.hard).
    parser.add_argument("--n-ood-hard", type=int, default=100, help="images of the hard set (0: none)")
    parser.add_argument(
        "--ood-hard-size", type=_frame_argument, default="480x360", help="WIDTHxHEIGHT of that set's images"
    )
    parser.add_argument("--ood-hard-seed", type=int, default=17)
    parser.add_argument("--ood-hard-dir", type=Path, default=None, help="default: var/bench/wild-ood-hard[-FACTORS]")
    parser.add_argument(
        "--lookalikes",
        type=Path,
        default=None,
        help="a folder of printed sheets of the targets' kind that are none of them (bench/printed_documents.py "
        "writes one): one to three lie beside the targets in every out-of-domain image",
    )
    parser.add_argument(
        "--no-baseline",
        action="store_true",
        help="skip the keypoint recipe (bench/keypoint_baseline.py) scored beside foldwise on every set",
    )
    parser.add_argument(
        "--factors",
        default="all",
        help=f"which parts of the scene are wild: all, none, or a comma list of {','.join(FACTORS)} (the rest plain)",
    )
    parser.add_argument("--n-in-domain", type=int, default=6, help="in-domain images per (condition, difficulty)")
    parser.add_argument("--in-domain-dir", type=Path, default=None)
    parser.add_argument("--train-dir", type=Path, default=None, help="data directory for the training run")
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument(
        "--test-sizes",
        type=_test_sizes_argument,
        help="comma list of inference sizes to score at (default: the model's detector.test_sizes)",
    )
    parser.add_argument(
        "--test-turns",
        type=_test_turns_argument,
        help="comma list of quarter turns to detect on too, e.g. 0 for upright only (default: the model's detector.test_turns)",
    )
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--sets-only",
        action="store_true",
        help="render (or find) the benchmark's sets, report where they are, and stop: no training, no scoring",
    )
    args = parser.parse_args(argv)

    from foldwise.config import load_config

    def echo(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    config = load_config(args.config)
    from workers.render.assets import load_assets

    classes = tuple(load_assets(config.assets).classes)
    lookalikes = lookalike_names(args.lookalikes)
    width, height = args.ood_size
    factors = FACTORS if args.factors == "all" else () if args.factors == "none" else tuple(args.factors.split(","))
    recipe = OodRecipe(
        n=args.n_ood,
        width=width,
        height=height,
        samples=args.ood_samples,
        seed=args.ood_seed,
        classes=classes,
        factors=factors,
        lookalikes=lookalikes,
    )
    suffix = "" if factors == FACTORS else "-" + ("-".join(factors) or "plain")
    if args.ood_dir is None:
        args.ood_dir = ROOT / f"var/bench/wild-ood{suffix}"
    # Each out-of-domain set: (report key suffix, recipe, folder); a set of 0 images is skipped.
    ood_sets = [("", recipe, args.ood_dir)]
    for name, n, (frame_width, frame_height), seed, folder, photos in (
        ("second", args.n_ood_second, args.ood_second_size, args.ood_second_seed, args.ood_second_dir, "training"),
        ("apart", args.n_ood_apart, args.ood_apart_size, args.ood_apart_seed, args.ood_apart_dir, "held_apart"),
        ("large", args.n_ood_large, args.ood_large_size, args.ood_large_seed, args.ood_large_dir, "training"),
        ("hard", args.n_ood_hard, args.ood_hard_size, args.ood_hard_seed, args.ood_hard_dir, "held_apart"),
    ):
        if n:
            extra = OodRecipe(
                n=n,
                width=frame_width,
                height=frame_height,
                samples=args.ood_samples,
                seed=seed,
                classes=classes,
                factors=factors,
                photos=photos,
                lookalikes=lookalikes,
                hard=name == "hard",
            )
            default_folder = ROOT / f"var/bench/wild-ood-{'b' if name == 'second' else name}{suffix}"
            ood_sets.append((f"_{name}", extra, folder or default_folder))

    report: dict = {
        "config": str(args.config),
        "protocol": {"score_threshold": args.threshold, "iou_threshold": args.iou},
    }
    ood_dirs = []
    for key, set_recipe, folder in ood_sets:
        started = time.perf_counter()
        ood_dirs.append(make_ood_set(folder, set_recipe, echo, assets=config.assets, lookalikes=args.lookalikes))
        report[f"ood_set{key}"] = {
            "dir": str(ood_dirs[-1]),
            "recipe": asdict(set_recipe),
            "seconds": time.perf_counter() - started,
        }

    in_domain_dir = args.in_domain_dir or ROOT / f"var/bench/wild-in-domain-{config.name}"
    make_in_domain_set(config, in_domain_dir, args.n_in_domain, seed=config.seed + 7919, echo=echo)
    reframed_dir = make_reframed_set(in_domain_dir, in_domain_dir.with_name(in_domain_dir.name + "-reframed"))
    rotated_dir = make_rotated_set(in_domain_dir, in_domain_dir.with_name(in_domain_dir.name + "-rotated"))
    if args.sets_only:
        report["in_domain_set"] = {
            "dir": str(in_domain_dir),
            "reframed": str(reframed_dir),
            "rotated": str(rotated_dir),
        }
        return write_report(report, args.out)

    checkpoint = args.model  # several: scored as one ensemble
    if checkpoint is None:
        train_dir = args.train_dir or Path(tempfile.mkdtemp(prefix="foldwise-wild-train-"))
        members = args.members or make_run_members(args.config)
        trained, training = train_with_config(args.config, train_dir, echo, members=members)
        report["training"] = training
        checkpoint = [trained]
    report["model"] = str(checkpoint[0]) if len(checkpoint) == 1 else [str(path) for path in checkpoint]
    report["test_sizes"] = list(args.test_sizes) if args.test_sizes is not None else "the model's"
    report["test_turns"] = list(args.test_turns) if args.test_turns is not None else "the model's"
    views = {"test_sizes": args.test_sizes, "test_turns": args.test_turns}

    textures = load_assets(config.assets).textures(classes)

    def baseline(data: Path) -> dict | None:
        return None if args.no_baseline else score_keypoint_baseline(textures, data, args.threshold, args.iou)

    report["in_domain"] = score(checkpoint, in_domain_dir, args.threshold, args.iou, **views)
    report["baseline_in_domain"] = baseline(in_domain_dir)
    report["in_domain_reframed"] = score(checkpoint, reframed_dir, args.threshold, args.iou, **views)
    report["in_domain_rotated"] = score(checkpoint, rotated_dir, args.threshold, args.iou, **views)
    in_map = report["in_domain"]["map"]
    ratios = []
    for (key, _recipe, _folder), ood_dir in zip(ood_sets, ood_dirs):
        report[f"out_of_domain{key}"] = score(checkpoint, ood_dir, args.threshold, args.iou, **views)
        report[f"baseline_out_of_domain{key}"] = baseline(ood_dir)
        report[f"ratio{key}"] = None if not in_map else report[f"out_of_domain{key}"]["map"] / in_map
        if key != "_hard":  # the hard set has a goal of its own (its mAP), not a ratio to in domain
            ratios.append(report[f"ratio{key}"])
    report["goal"] = {"ratio_at_least": 0.8, "met": all(ratio is not None and ratio >= 0.8 for ratio in ratios)}
    report["machine"] = machine()
    report["headline"] = headline(report)
    return write_report(report, args.out)


def headline(report: dict) -> str:
    """Each scored set in one line: foldwise's mAP, precision and recall at the threshold beside
    the keypoint recipe's."""

    def figures(scores: dict) -> str:
        seen = scores["at_threshold"]
        shown = lambda value: "–" if value is None else f"{value:.2f}"  # noqa: E731
        return f"{scores['map']:.3f} (P {shown(seen['precision'])}, R {shown(seen['recall'])})"

    parts = []
    for key, scores in report.items():
        if not (key.startswith("out_of_domain") or key == "in_domain") or not isinstance(scores, dict):
            continue
        name = key.replace("out_of_domain", "out of domain").replace("_", " ").strip()
        line = f"{name}: foldwise {figures(scores)}"
        baseline = report.get(f"baseline_{key}")
        if baseline:
            line += f", keypoints {figures(baseline)}"
        parts.append(line)
    return "mAP at the cut (precision, recall at it): " + "; ".join(parts)


if __name__ == "__main__":
    main()
