"""Several trained detectors scored side by side on the same out-of-domain sets, in one run.

Each ``--model NAME=PATH`` (a checkpoint or an ensemble; ``NAME=PATH1,PATH2`` scores
checkpoints as one ensemble) is scored on sets made by ``bench/wild_sets.py`` that no training
renders: the default out-of-domain recipe and the held-apart photographs (optionally the hard
set), at the paper's cut: mAP, the unthresholded mAP, and precision and recall at the threshold.

    python bench/compare_models.py --model new=var/a.pt --model old=var/b.pt --out bench/results/curricula.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402

# (set name, photo pool, seed, hard scene): the recipes bench/wild.py's sets of the same name use.
SETS = (("default", "training", 2026, False), ("apart", "held_apart", 11, False), ("hard", "held_apart", 17, True))


def ood_sets(config_path: Path, counts: dict[str, int]) -> dict[str, Path]:
    """The out-of-domain sets (cached by recipe under var/bench), ``counts[name]`` images each."""
    from bench.wild_scene import OodRecipe
    from bench.wild_sets import make_ood_set
    from foldwise.config import load_config
    from foldwise.sampling import asset_names

    config = load_config(config_path)
    classes = tuple(asset_names(config.assets).classes)
    sets = {}
    for name, photos, seed, hard in SETS:
        n = counts.get(name, 0)
        if n:
            size = {"width": 480, "height": 360} if hard else {}
            recipe = OodRecipe(n=n, seed=seed, classes=classes, photos=photos, hard=hard, **size)
            folder = ROOT / f"var/bench/ood-{name}-{n}"
            sets[name] = make_ood_set(folder, recipe, echo=lambda *a, **k: None, assets=config.assets)
    return sets


def score_set(checkpoint, folder: Path, score_threshold: float = 0.8, iou_threshold: float = 0.5) -> dict:
    """One detector (a path, or a list of paths scored as one ensemble) on one set."""
    from bench.wild_scoring import score

    result = score(checkpoint, folder, score_threshold, iou_threshold)
    return {
        "map": result["map"],
        "map_unthresholded": result["map_unthresholded"],
        "at_threshold": result.get("at_threshold"),
        "images": result.get("images"),
        "seconds_per_image": result.get("seconds_per_image"),
    }


def parse_model(text: str) -> tuple[str, list[str]]:
    name, sep, paths = text.partition("=")
    if not sep or not name or not paths:
        raise argparse.ArgumentTypeError(f"--model {text!r}: expected NAME=PATH or NAME=PATH1,PATH2")
    return name, paths.split(",")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=parse_model, action="append", required=True, help="NAME=PATH[,PATH...]")
    parser.add_argument("--config", type=Path, default=ROOT / "configs/quick.yaml", help="whose assets the sets use")
    parser.add_argument("--n-ood", type=int, default=80)
    parser.add_argument("--n-ood-apart", type=int, default=80)
    parser.add_argument("--n-ood-hard", type=int, default=0)
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)

    for name, paths in args.model:
        missing = [path for path in paths if not Path(path).is_file()]
        if missing:
            raise SystemExit(f"bench/compare_models.py: --model {name}: no checkpoint at {', '.join(missing)}")
    sets = ood_sets(args.config, {"default": args.n_ood, "apart": args.n_ood_apart, "hard": args.n_ood_hard})
    models = {
        name: {
            "checkpoints": paths,
            "sets": {set_name: score_set(paths, folder, args.threshold) for set_name, folder in sets.items()},
        }
        for name, paths in args.model
    }
    report = {"protocol": {"score_threshold": args.threshold, "iou_threshold": 0.5}, "models": models}
    report["machine"] = machine()
    report["headline"] = "; ".join(
        f"{name}: " + ", ".join(f"{s} {r['map']:.3f}" for s, r in model["sets"].items())
        for name, model in models.items()
    )
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
