"""``foldwise render`` (a COCO dataset, or a preview contact sheet) and ``foldwise mesh``.

Heavy imports (OpenCV, scikit-image) stay inside the commands so ``foldwise --help`` is light.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import typer

PREVIEW_COLUMNS = ("canonical", "easy", "medium", "hard")
# Stable indices for deriving per-(condition, difficulty) seeds.
_DIFFICULTY_INDEX = {"canonical": 0, "easy": 1, "medium": 2, "hard": 3}


def _split(value: str) -> list[str]:
    return [part.strip() for part in value.split(",") if part.strip()]


def resolve_conditions(value: str) -> list[str]:
    """Codes from "po", "pose", "fb,mb", "mixed" or "all" (every condition and the mixed stage)."""
    from foldwise.conditions import load_condition_table
    from foldwise.sampling import resolve_condition

    table = load_condition_table()
    names = _split(value)
    if not names:
        raise typer.BadParameter("no condition given")
    if names == ["all"]:
        from foldwise.theta import MIXED

        return [*table.codes, MIXED]
    try:
        codes = [resolve_condition(name, table) for name in names]
    except ValueError as error:
        raise typer.BadParameter(str(error)) from None
    return list(dict.fromkeys(codes))


def resolve_difficulties(value: str) -> list[str]:
    from foldwise.conditions import load_condition_table

    table = load_condition_table()
    names = [name.lower() for name in _split(value)]
    if names == ["all"]:
        return list(table.difficulties)
    known = ("canonical", *table.difficulties)
    for name in names:
        if name not in known:
            raise typer.BadParameter(f"unknown difficulty {name!r}; known: {', '.join(known)}, all")
    if not names:
        raise typer.BadParameter("no difficulty given")
    return list(dict.fromkeys(names))


def _pair_seed(seed: int, condition: str, difficulty: str) -> int:
    from foldwise.conditions import load_condition_table
    from foldwise.seeds import derive_seed
    from foldwise.theta import MIXED

    codes = load_condition_table().codes + (MIXED,)
    return derive_seed(seed, codes.index(condition), _DIFFICULTY_INDEX[difficulty])


def _write_png(path: Path, image_rgb) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR)):
        raise typer.BadParameter(f"cannot write {str(path)!r}")


def render_dataset(
    out: Path,
    conditions: list[str],
    difficulties: list[str],
    n: int,
    seed: int,
    image_size: int,
    backend: str,
    assets,
    max_resamples: int = 20,
    samples: int = 16,
    echo=print,
    on_image=None,
) -> dict:
    """Render n images per (condition, difficulty) into ``out``: images/ + annotations.json (COCO).

    ``on_image(images_done)`` is called after every image, rendered or failed (progress display).
    """
    from foldwise.sampling import generate_parameters
    from workers.render.pipeline import RenderRejected, render_with_resample

    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    images, annotations, failures = [], [], []
    started = time.perf_counter()
    done = 0
    for condition in conditions:
        for difficulty in difficulties:
            thetas = generate_parameters(
                condition, difficulty, n, _pair_seed(seed, condition, difficulty), image_size=image_size, assets=assets
            )
            pair_start = time.perf_counter()
            resampled = 0
            for index, theta in enumerate(thetas):
                if on_image is not None and done:
                    on_image(done)
                done += 1
                name = f"{condition}_{difficulty}_{index:05d}"
                try:
                    result, used, reasons = render_with_resample(
                        theta, backend=backend, max_resamples=max_resamples, assets=assets, samples=samples
                    )
                except RenderRejected as rejected:
                    failures.append({"name": name, "theta": theta.to_dict(), "reasons": rejected.reasons})
                    continue
                resampled += bool(reasons)
                file_name = f"images/{name}.png"
                _write_png(out / file_name, result.image)
                image_id = len(images) + 1
                images.append(
                    {
                        "id": image_id,
                        "file_name": file_name,
                        "width": int(result.image.shape[1]),
                        "height": int(result.image.shape[0]),
                        "condition": condition,
                        "difficulty": difficulty,
                        "theta": used.to_dict(),
                        "rejections": reasons,
                    }
                )
                for obj, mask in zip(result.objects, result.masks):
                    x0, y0, x1, y1 = obj.box
                    ax0, ay0, ax1, ay1 = obj.amodal_box
                    annotations.append(
                        {
                            "id": len(annotations) + 1,
                            "image_id": image_id,
                            "category_id": int(obj.label) + 1,
                            "bbox": [x0, y0, x1 - x0, y1 - y0],
                            "area": float(mask.sum()),
                            "iscrowd": 0,
                            "amodal_bbox": [ax0, ay0, ax1 - ax0, ay1 - ay0],
                            "visible_fraction": float(obj.visible_fraction),
                        }
                    )
            seconds = time.perf_counter() - pair_start
            echo(
                f"{condition}/{difficulty}: {len(thetas)} images in {seconds:.2f} s"
                + (f", {resampled} resampled" if resampled else "")
            )
    if on_image is not None:
        on_image(done)
    coco = {
        "info": {
            "description": "foldwise rendered dataset",
            "backend": backend,
            "seed": seed,
            "image_size": image_size,
        },
        "images": images,
        "annotations": annotations,
        "categories": [{"id": i + 1, "name": name} for i, name in enumerate(assets.classes)],
    }
    if failures:
        coco["failures"] = failures
    (out / "annotations.json").write_text(json.dumps(coco, indent=1))
    echo(
        f"wrote {len(images)} images to {out} in {time.perf_counter() - started:.1f} s"
        + (f"; {len(failures)} failed" if failures else "")
    )
    return coco


def describe(theta) -> str:
    """What the image varies, in a few characters, for labels: the values of the parameters
    its condition(s) draw (from the condition table, so every condition has its caption)."""
    from foldwise.conditions import load_condition_table

    if theta.difficulty == "canonical":
        return "canonical"
    if theta.is_mixed:
        codes = "+".join(c.condition for c in theta.components)
        return codes + (" no object" if theta.instances == 0 else "")
    table = load_condition_table()
    values = dict(theta)
    parts = [theta.variant] if theta.variant != "default" else []
    for name in table.conditions[theta.condition].variants[theta.variant][theta.difficulty]:
        value = values[name]
        if name in ("roll", "pitch", "yaw", "rotation", "tilt", "motion_blur_angle", "light_spread", "wrinkle_depth"):
            parts.append(f"{math.degrees(value):.0f}deg")
        elif isinstance(value, int):
            parts.append(str(value))
        else:
            parts.append(f"{value:.2f}")
    return " ".join(parts)


def dashed_rectangle(image, box, colour, dash: int = 4, thickness: int = 1, pixel_edges: bool = True) -> None:
    """A dashed rectangle drawn on ``image`` in place (``box`` xyxy; ``pixel_edges``: its far
    edges are pixel edges, drawn on the last pixel they cover)."""
    import cv2

    x0, y0, x1, y1 = (int(round(float(v))) for v in box)
    if pixel_edges:
        x1, y1 = x1 - 1, y1 - 1
    for a, b in (((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))):
        length = max(abs(b[0] - a[0]), abs(b[1] - a[1]))
        for start in range(0, length + 1, 2 * dash):
            end = min(start + dash, length)
            p = (a[0] + (b[0] - a[0]) * start // max(length, 1), a[1] + (b[1] - a[1]) * start // max(length, 1))
            q = (a[0] + (b[0] - a[0]) * end // max(length, 1), a[1] + (b[1] - a[1]) * end // max(length, 1))
            cv2.line(image, p, q, colour, thickness)


def draw_boxes(image, objects):
    """A copy of an RGB image with each object's visible box (solid green) and amodal box
    (dashed yellow)."""
    import cv2

    canvas = image.copy()
    for obj in objects:
        dashed_rectangle(canvas, obj.amodal_box, (255, 220, 0))
    for obj in objects:
        x0, y0, x1, y1 = (int(round(v)) for v in obj.box)
        cv2.rectangle(canvas, (x0, y0), (x1 - 1, y1 - 1), (0, 255, 0), 1)
    return canvas


def preview_rows(table, conditions) -> list[tuple[str, str | None]]:
    """(condition, variant) per contact-sheet row: one row per variant where a condition has
    several (scale small and large, lighting dark and bright, lens narrow and wide), so each
    shows at every difficulty; variant None for a condition with one (and the mixed stage)."""
    rows = []
    for code in conditions:
        variants = list(table.conditions[code].variants) if code in table.conditions else [None]
        rows.extend([(code, variant) for variant in variants] if len(variants) > 1 else [(code, None)])
    return rows


def _wrap(text: str, font, scale: float, width: int) -> list[str]:
    """``text`` in lines no wider than ``width`` pixels (words kept whole), for the label column."""
    import cv2

    lines: list[str] = []
    for word in text.split():
        candidate = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(candidate, font, scale, 1)[0][0] <= width:
            lines[-1] = candidate
        else:
            lines.append(word)
    return lines


def render_preview(out: Path, image_size: int, seed: int, backend: str, assets, conditions=None, samples: int = 16):
    """Contact sheet: one row per condition (per variant where it has several), columns
    canonical, easy, medium, hard; boxes drawn. The rows of one condition's variants show the
    same objects and backgrounds, so only the variant's parameter differs between them."""
    import cv2
    import numpy as np

    from foldwise.conditions import load_condition_table
    from foldwise.sampling import generate_parameters
    from foldwise.theta import CANONICAL, MIXED
    from workers.render.pipeline import RenderRejected, render_with_resample

    table = load_condition_table()
    rows = preview_rows(table, conditions or [*table.codes, MIXED])
    label_w, header_h, caption_h, pad = 150, 24, 16, 4
    cell_h = image_size + caption_h
    height = header_h + len(rows) * (cell_h + pad)
    width = label_w + len(PREVIEW_COLUMNS) * (image_size + pad)
    sheet = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for col, difficulty in enumerate(PREVIEW_COLUMNS):
        x = label_w + col * (image_size + pad)
        cv2.putText(sheet, difficulty, (x + 4, header_h - 8), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    first_row_of = {}  # condition -> y of its first row: its variants share the canonical cell
    for row, (code, variant) in enumerate(rows):
        y = header_h + row * (cell_h + pad)
        name = table.name(code) + (f" ({variant})" if variant else "")
        cv2.putText(sheet, code, (6, y + image_size // 2 - 6), font, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
        for line_index, line in enumerate(_wrap(name, font, 0.42, label_w - 10)):
            cv2.putText(
                sheet, line, (6, y + image_size // 2 + 14 + 16 * line_index), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA
            )
        for col, difficulty in enumerate(PREVIEW_COLUMNS):
            x = label_w + col * (image_size + pad)
            if difficulty == CANONICAL and code in first_row_of:  # the same θ: copy, do not render again
                y0 = first_row_of[code]
                sheet[y : y + cell_h, x : x + image_size] = sheet[y0 : y0 + cell_h, x : x + image_size]
                continue
            theta = generate_parameters(
                code,
                difficulty,
                1,
                _pair_seed(seed, code, difficulty),
                image_size=image_size,
                assets=assets,
                variant=None if difficulty == CANONICAL else variant,
            )[0]
            try:
                result, used, reasons = render_with_resample(theta, backend=backend, assets=assets, samples=samples)
            except RenderRejected as rejected:
                cv2.putText(sheet, "rejected", (x + 4, y + 20), font, 0.4, (200, 0, 0), 1, cv2.LINE_AA)
                cv2.putText(sheet, rejected.reason[:24], (x + 4, y + 36), font, 0.3, (200, 0, 0), 1, cv2.LINE_AA)
                continue
            sheet[y : y + image_size, x : x + image_size] = draw_boxes(result.image, result.objects)
            caption = describe(used) + (f" (+{len(reasons)})" if reasons else "")
            cv2.putText(sheet, caption, (x + 2, y + image_size + 12), font, 0.34, (0, 0, 0), 1, cv2.LINE_AA)
        first_row_of.setdefault(code, y)
    _write_png(Path(out), sheet)
    return sheet


def register(app: typer.Typer) -> None:
    """Add ``render`` and ``mesh`` to the root ``foldwise`` app."""

    @app.command("render")
    def render_command(
        out: Path = typer.Option(..., "--out", help="dataset folder (or the PNG file with --preview)"),
        condition: str = typer.Option(
            "all", "--condition", "-c", help="code or name (po, pose, focus_blur...), comma-separated, or all"
        ),
        difficulty: str = typer.Option(
            "all", "--difficulty", "-d", help="canonical, easy, medium, hard, comma-separated, or all"
        ),
        n: int = typer.Option(10, "-n", min=1, help="images per (condition, difficulty)"),
        backend: str = typer.Option("raster", "--backend", help="raster or blender"),
        seed: int = typer.Option(0, "--seed", min=0),
        image_size: int = typer.Option(128, "--image-size", min=16, max=4096),
        preview: bool = typer.Option(False, "--preview", help="write a contact sheet PNG instead of a dataset"),
        max_resamples: int = typer.Option(20, "--max-resamples", min=0),
        samples: int = typer.Option(16, "--samples", min=1, help="Cycles samples (blender backend)"),
        objects: Path | None = typer.Option(None, "--objects", help="folder of object textures (default: built-in)"),
        backgrounds: Path | None = typer.Option(None, "--backgrounds", help="folder of background images"),
        occluders: Path | None = typer.Option(None, "--occluders", help="folder of occluder images"),
    ) -> None:
        """Render images with ground-truth boxes (COCO JSON: 0..n per image) for any condition or the mixed stage, or a preview sheet."""
        from foldwise.config import AssetsConfig
        from workers.render.assets import AssetError, load_assets
        from workers.render.pipeline import BACKENDS

        if backend not in BACKENDS:
            raise typer.BadParameter(
                f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}", param_hint="--backend"
            )
        codes = resolve_conditions(condition)
        try:
            assets = load_assets(AssetsConfig(objects=objects, backgrounds=backgrounds, occluders=occluders))
        except AssetError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        if preview:
            if out.suffix.lower() != ".png":
                raise typer.BadParameter("with --preview, --out is a .png file", param_hint="--out")
            render_preview(out, image_size, seed, backend, assets, conditions=codes, samples=samples)
            typer.echo(f"wrote {out}")
            return
        from foldwise.progress import CommandProgress, command_console

        difficulties = resolve_difficulties(difficulty)
        console = command_console()
        # Off a terminal: a progress line at most every 5 s, beside the line per (c, δ).
        total = len(codes) * len(difficulties) * n
        with CommandProgress(console, "rendering", total, "images", interval_s=5.0) as bar:
            coco = render_dataset(
                out, codes, difficulties, n, seed, image_size, backend, assets,
                max_resamples=max_resamples, samples=samples,
                echo=lambda line: console.print(line, markup=False, highlight=False),
                on_image=lambda images_done: bar.update(images_done),
            )  # fmt: skip
        if coco.get("failures"):
            for failure in coco["failures"]:
                typer.echo(f"failed: {failure['name']}: {failure['reasons'][-1]}", err=True)
            raise typer.Exit(1)

    @app.command("mesh")
    def mesh_command(
        out: Path = typer.Option(..., "--out", help="OBJ file to write"),
        rulings: int = typer.Option(2, "--rulings", min=0, help="guiding rulings (Table 3: 2 canonical, 3, 5, 8)"),
        seed: int = typer.Option(0, "--seed", min=0),
        width: float = typer.Option(3.0, "--width", min=1e-6, help="sheet width, metres"),
        height: float = typer.Option(2.0, "--height", min=1e-6, help="sheet height, metres"),
    ) -> None:
        """Sample one randomly bent sheet and write it as a Wavefront OBJ (v, vt, f)."""
        import numpy as np

        from workers.render.paper_model import SelfIntersection, sample_sheet, write_obj

        try:
            mesh = sample_sheet(rulings, np.random.default_rng(seed), width, height)
        except SelfIntersection as error:
            typer.echo(
                f"error: the sheet drawn from seed {seed} intersects itself ({error}); try another seed", err=True
            )
            raise typer.Exit(1) from None
        except ValueError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        out.parent.mkdir(parents=True, exist_ok=True)
        write_obj(mesh, out)
        typer.echo(
            f"wrote {out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, {len(mesh.rulings)} guiding rulings"
        )
