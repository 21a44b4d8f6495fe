"""The texture check and the cascade replayed on stored network detections: as built and with
variants of the check's constants, side by side (JSON out).

A change to the check (how many FLANN checks, a map's inliers, the cascade's rule) changes what
the detector draws without changing what its network sees. So the network runs once per set, at
the cascade's first view and at every view, its detections kept in ``--cache``
(``bench/calibrate.network_detections``), and each variant runs only the check and the cascade
again (``bench/calibrate.cascade_pass``): minutes a variant, where a full ``bench/wild.py`` score
takes tens. As built, the replay draws the boxes ``detect_object`` draws (the tests check it box
for box).

A variant is ``NAME: SETTING, SETTING...``, each setting ``texture_check.CONSTANT=VALUE`` (a
constant of ``workers/train/texture_check.py``) or ``cascade.FIELD=VALUE`` (``size``, the first
view's; ``unsure``), each value a Python literal. Each set is scored whole and on its even and odd
images apart, so that a setting chosen on one half is reported on the other.

    python bench/replay_check.py --model var/studies/quick-members-*/ensemble.pt \\
        --data var/bench/wild-ood-large --data var/bench/wild-ood-hard \\
        --variant "fewer checks: texture_check.FLANN_CHECKS=128" --out bench/results/replay.json
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import hashlib
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.calibrate import cascade_pass, network_detections  # noqa: E402
from bench.report import machine, write_report  # noqa: E402
from bench.wild_scoring import _scores  # noqa: E402

AS_BUILT = "as built"


@dataclasses.dataclass
class Variant:
    """A name, the check's constants it sets, and the cascade's fields it sets."""

    name: str
    constants: dict = dataclasses.field(default_factory=dict)
    cascade: dict = dataclasses.field(default_factory=dict)


def parse_variant(text: str) -> Variant:
    """``NAME: texture_check.CONSTANT=VALUE, cascade.FIELD=VALUE, ...``; a ValueError naming what is wrong."""
    from workers.train import texture_check
    from workers.train.checkpoint import Cascade

    name, colon, settings = text.partition(":")
    if not colon or not name.strip():
        raise ValueError(f"variant {text!r}: expected NAME: SETTING, SETTING...")
    variant = Variant(name.strip())
    fields = {field.name for field in dataclasses.fields(Cascade)}
    for setting in filter(None, (part.strip() for part in settings.split(","))):
        target, equals, value = setting.partition("=")
        owner, dot, attribute = target.strip().partition(".")
        if not equals or not dot:
            raise ValueError(
                f"variant {name!r}: {setting!r} is not texture_check.CONSTANT=VALUE or cascade.FIELD=VALUE"
            )
        try:
            parsed = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise ValueError(f"variant {name!r}: {value.strip()!r} is not a Python literal") from None
        if owner == "texture_check" and attribute.isupper() and hasattr(texture_check, attribute):
            variant.constants[attribute] = parsed
        elif owner == "cascade" and attribute in fields:
            variant.cascade[attribute] = parsed
        else:
            raise ValueError(
                f"variant {name!r}: {target.strip()!r} is neither a texture_check constant nor a cascade field"
            )
    return variant


def replay(detector, images, network_for, variant: Variant) -> tuple[list[dict], dict]:
    """Each image's detections as the detector draws them under ``variant``, and what that took:
    the check's seconds per image and the share of images the cascade sent on to every view.
    ``network_for(first_size)``: the stored network detections with the first view at that size."""
    from workers.train import texture_check
    from workers.train.texture_check import TextureCheck

    built = detector.active_cascade()
    cascade = dataclasses.replace(built, **variant.cascade) if built is not None else None
    first_size = cascade.first_size(detector.model.test_sizes) if cascade is not None else None
    network = network_for(first_size)
    # The constants are restored after the block (patch.multiple needs at least one).
    constants = mock.patch.multiple(texture_check, **variant.constants) if variant.constants else nullcontext()
    with constants:
        # The detector's own check as built; made anew inside a variant, whose constants may change
        # the textures' keypoints too.
        check = (
            TextureCheck(
                detector.textures,
                detector.classes,
                search=detector.config.texture_search,
                calibration=detector.calibration,
                lookalikes=detector.lookalikes,
            )
            if variant.constants
            else detector.texture_check()
        )
        sent_on = 0
        started = time.perf_counter()
        found = []
        for index, image in enumerate(images):
            checked, went_on = cascade_pass(check, image, network, index, cascade, check.matches(image))
            sent_on += went_on
            found.append({key: checked[key] for key in ("boxes", "scores", "labels", "confirmed")})
        seconds = time.perf_counter() - started
    return found, {
        "check_seconds_per_image": seconds / max(len(images), 1),
        "second_pass": sent_on / max(len(images), 1) if cascade is not None else None,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a checkpoint or ensemble with a texture check")
    parser.add_argument("--data", type=Path, action="append", required=True, help="a COCO folder (repeatable)")
    parser.add_argument("--variant", action="append", default=[], help="NAME: SETTING, ... (repeatable)")
    parser.add_argument(
        "--cache", type=Path, default=ROOT / "var/bench/replay", help="where network detections are kept"
    )
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    try:
        variants = [Variant(AS_BUILT)] + [parse_variant(text) for text in args.variant]
    except ValueError as error:
        raise SystemExit(str(error)) from None
    if len({variant.name for variant in variants}) < len(variants):
        raise SystemExit(f"variant names must differ from each other and from {AS_BUILT!r}")
    if not args.model.is_file():
        raise SystemExit(f"{args.model}: no such checkpoint")
    for data in args.data:
        if not (data / "annotations.json").is_file():
            raise SystemExit(f"{data}: no annotations.json")

    import numpy as np

    from workers.train.checkpoint import load_detector
    from workers.train.data import load_coco_dataset, read_image_rgb

    detector = load_detector(args.model, device="cpu")
    if detector.texture_check() is None:
        raise SystemExit(f"{args.model}: the detector has no texture check to replay")
    classes = detector.classes
    # The model's bytes name its network detections in the cache: another model, another file.
    digest = hashlib.sha256(args.model.read_bytes()).hexdigest()[:12]
    report: dict = {"model": str(args.model), "variants": {v.name: dataclasses.asdict(v) for v in variants}, "sets": {}}
    for data in args.data:
        samples, set_classes = load_coco_dataset(data)
        unknown = sorted(set(set_classes) - set(classes))
        if unknown:
            raise SystemExit(f"{data}: classes {unknown} are none of the detector's {classes}")
        to_model = np.array([classes.index(name) for name in set_classes], np.int64)
        truth = [{"boxes": s.boxes, "labels": to_model[np.asarray(s.labels, np.int64)]} for s in samples]
        groups = [{"condition": s.condition, "difficulty": s.difficulty} for s in samples]
        images = [read_image_rgb(s.image_path) for s in samples]
        halves = {"even": list(range(0, len(samples), 2)), "odd": list(range(1, len(samples), 2))}

        def network_for(first_size, data=data, samples=samples, set_classes=set_classes):
            cache = args.cache / f"{args.model.stem}-{digest}-{data.name}-{first_size}.pkl"
            return network_detections(detector, samples, set_classes, cache, first_size)[0]

        rows = {}
        for variant in variants:
            found, cost = replay(detector, images, network_for, variant)
            scored = _scores(found, truth, classes, groups, args.threshold, args.iou, 0.0, parts=halves)
            for key in ("seconds", "seconds_per_image"):  # the network's time is not replayed: the check's is below
                scored.pop(key, None)
            rows[variant.name] = {**scored, **cost}
        report["sets"][data.name] = {"dir": str(data), "images": len(samples), "variants": rows}
    report["headline"] = "; ".join(
        f"{name}: "
        + ", ".join(
            f"{variant} {row['map']:.3f} (P {_fmt(row['at_threshold']['precision'])}, R {_fmt(row['at_threshold']['recall'])})"
            for variant, row in entry["variants"].items()
        )
        for name, entry in report["sets"].items()
    )
    report["machine"] = machine()
    return write_report(report, args.out)


def _fmt(value) -> str:
    return "–" if value is None else f"{value:.2f}"


if __name__ == "__main__":
    main()
