"""What an experiment produced, for reading and download: rendered images with their boxes,
COCO documents, the report, checkpoints. Read-only and open, like the other reads."""

from dataclasses import asdict
from pathlib import Path as FilePath
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query, status
from fastapi.responses import FileResponse, JSONResponse

from db.models import Split
from foldwise.config import ExperimentConfig
from services import artifacts, baseline, learnability, queries
from services.api import drawings
from services.api.deps import MAX_ID, MAX_INT_COLUMN, ExperimentId, ModelId, SessionDep
from services.api.schemas import NOT_FOUND

router = APIRouter(tags=["artifacts"])

ImageId = Annotated[int, Path(ge=1, le=MAX_ID, description="image (θ) id")]


@router.get("/experiments/{experiment_id}/images", responses=NOT_FOUND)
def experiment_images(
    experiment_id: ExperimentId,
    session: SessionDep,
    split: Split = Split.train,
    stage: Annotated[int | None, Query(ge=0, le=MAX_INT_COLUMN, description="stage order (train split)")] = None,
    k: Annotated[int | None, Query(ge=1, le=MAX_INT_COLUMN, description="increment (train split)")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> dict[str, Any]:
    """Rendered images and their boxes: by default the newest increment's training images."""
    return artifacts.images(session, experiment_id, split, stage=stage, k=k, limit=limit)


@router.get(
    "/experiments/{experiment_id}/images/{image_id}.png",
    response_class=FileResponse,
    responses={**NOT_FOUND, 200: {"content": {"image/png": {}}}},
)
def experiment_image(experiment_id: ExperimentId, image_id: ImageId, session: SessionDep) -> FileResponse:
    """One rendered image (PNG)."""
    path = artifacts.image_file(session, experiment_id, image_id)
    # Rendered once, never rewritten: browsers may keep it.
    return FileResponse(path, media_type="image/png", headers={"Cache-Control": "public, max-age=86400"})


@router.get("/experiments/{experiment_id}/coco", responses=NOT_FOUND)
def experiment_coco(experiment_id: ExperimentId, session: SessionDep, split: Split = Split.test) -> JSONResponse:
    """A split's rendered images and boxes as a COCO document (download)."""
    document = artifacts.coco_document(session, experiment_id, split)
    filename = f"experiment-{experiment_id}-{split.value}-coco.json"
    return JSONResponse(document, headers={"Content-Disposition": f'attachment; filename="{filename}"'})


@router.get(
    "/experiments/{experiment_id}/report.{extension}",
    response_class=FileResponse,
    responses={**NOT_FOUND, 200: {"content": {"image/png": {}, "text/csv": {}}}},
)
async def experiment_report(
    experiment_id: ExperimentId, extension: Annotated[str, Path(pattern="^(png|csv)$")]
) -> FileResponse:
    """The report of ``foldwise report`` (error against time), drawn once per state of the record."""

    def draw(folder: FilePath) -> dict[str, FilePath]:
        from services.report import write_report

        files = write_report(experiment_id, folder)
        return {"png": files.png, "csv": files.csv}

    folder, files = await drawings.drawn(experiment_id, "report", lambda: drawings.report_content(experiment_id), draw)
    path = folder / files[extension]
    media_type = "image/png" if extension == "png" else "text/csv"
    return FileResponse(path, media_type=media_type, filename=path.name)


@router.get(
    "/models/{model_id}/checkpoint",
    response_class=FileResponse,
    responses={**NOT_FOUND, 200: {"content": {"application/octet-stream": {}}}},
)
def model_checkpoint(model_id: ModelId, session: SessionDep) -> FileResponse:
    """ω's checkpoint file (``foldwise evaluate/detect/export --model`` read it)."""
    path = artifacts.checkpoint_file(session, model_id)
    return FileResponse(path, media_type="application/octet-stream", filename=f"model-{model_id}.pt")


FIGURE_MEDIA = {"png": "image/png", "svg": "image/svg+xml", "csv": "text/csv"}


@router.get(
    "/experiments/{experiment_id}/figures/{name}.{extension}",
    response_class=FileResponse,
    responses={**NOT_FOUND, 200: {"content": {media: {} for media in FIGURE_MEDIA.values()}}},
)
async def experiment_figure(
    experiment_id: ExperimentId,
    name: Annotated[str, Path(pattern="^fig(4|5|6|7|8)$", description="fig4 to fig8 (services/figures.py)")],
    extension: Annotated[str, Path(pattern="^(png|svg|csv)$")],
) -> FileResponse:
    """One of the paper's figures for this experiment, drawn once per state of the record."""

    def draw(folder: FilePath) -> dict[str, FilePath]:
        from services.figures import write_figures

        paths = write_figures([experiment_id], folder, names=(name,))[name]
        return {p.suffix.lstrip("."): p for p in paths}

    folder, files = await drawings.drawn(
        experiment_id, name, lambda: drawings.figure_content(experiment_id, name), draw
    )
    path = folder / files[extension]
    return FileResponse(path, media_type=FIGURE_MEDIA[extension], filename=path.name)


def _require_kind(session, experiment_id: int, kind: str) -> None:
    """409 unless the experiment is of ``kind`` (its route reads what only that kind records)."""
    config = ExperimentConfig.model_validate(queries.get_experiment(session, experiment_id).config)
    if config.kind != kind:
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"experiment {experiment_id} is of kind {config.kind}, not {kind}"
        )


@router.get(
    "/experiments/{experiment_id}/learnability",
    responses={**NOT_FOUND, 409: {"description": "the experiment is not of kind learnability"}},
)
def experiment_learnability(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
    """A learnability experiment's (Algorithm 2) order of conditions beside the paper's, with
    Spearman's ρ, from the scores so far (services/learnability.py defines the score)."""
    _require_kind(session, experiment_id, "learnability")
    order = learnability.experiment_learnability(session, experiment_id)
    return {
        "score": "mean mAP over every increment of the condition, each on its own test set",
        "spearman_rho": order.spearman_rho,
        "compared": list(order.compared),
        "paper_order": list(learnability.PAPER_ORDER),
        "conditions": [asdict(row) for row in order.rows],
    }


@router.get(
    "/experiments/{experiment_id}/table2",
    responses={**NOT_FOUND, 409: {"description": "the experiment is not of kind canonical_baseline"}},
)
def experiment_table2(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
    """A canonical baseline's Table 2 (paper §3.2): its model's mAP per condition, over every
    difficulty and at each, beside the paper's Fast R-CNN figure. ``final`` once the experiment
    has finished; before then, the scores of its latest evaluated model."""
    _require_kind(session, experiment_id, "canonical_baseline")
    table = baseline.experiment_table2(session, experiment_id)
    return {
        "model_id": table.model_id,
        "increment": table.increment,
        "final": table.final,
        "detector": table.detector,
        "score_threshold": table.score_threshold,
        "iou_threshold": table.iou_threshold,
        "difficulties": table.difficulties,
        "paper": baseline.PAPER_SETUP,
        "conditions": [asdict(row) for row in table.rows],
    }
