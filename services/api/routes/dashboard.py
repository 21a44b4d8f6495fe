"""GET /: the dashboard. Read-only and open, like the REST reads it is drawn from.

The page is rendered here with the experiment list and the layout; ``dashboard.js`` (no
framework, no build step) then reads the same REST routes a client would (summary, stages,
history, config, the latest model, images) and redraws every few seconds. Nothing shown is
computed for the page alone, apart from the ETA (the pace so far, extrapolated).
"""

from html import escape
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse, HTMLResponse

from services import queries
from services.api.deps import SessionDep

STATIC = Path(__file__).resolve().parent.parent / "static"
REFRESH_MS = 3000

router = APIRouter(include_in_schema=False)

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>foldwise{title}</title>
<link rel="stylesheet" href="/dashboard.css">
</head>
<body data-experiment="{experiment}" data-refresh-ms="{refresh_ms}">
<header><h1><a href="/">foldwise</a></h1><span class="muted">model-based active learning of a detector
 &middot; <a href="/docs">API</a></span><span id="updated" class="muted"></span></header>
<main>
<section id="experiments"><h2>Experiments</h2>
<table><thead><tr><th>id</th><th>name</th><th>status</th><th>created</th></tr></thead>
<tbody id="experiment-rows">{rows}</tbody></table></section>
{detail}
</main>
<script src="/dashboard.js"></script>
</body>
</html>
"""

DETAIL = """<section id="experiment">
<h2 id="title">Experiment {experiment}</h2>
<div id="summary" class="cards"></div>
<div class="grid">
<figure><figcaption>P: error (1 &minus; mAP) against wall time; the current stage's windows
 <span class="swatch window-m"></span> M and <span class="swatch window-n"></span> N</figcaption>
<svg id="p-curve" viewBox="0 0 640 300" role="img" aria-label="error against time"></svg>
<div id="legend" class="legend"></div></figure>
<figure><figcaption>mAP of the latest model per condition &times; difficulty
 <span id="heatmap-model" class="muted"></span></figcaption>
<table id="heatmap"></table></figure>
</div>
<h3>Stages</h3>
<table id="stages"><thead><tr><th>#</th><th>c</th><th>&delta;</th><th>status</th><th>k</th>
<th>end</th><th>best mAP</th><th>time</th></tr></thead><tbody></tbody></table>
<h3>Training images of the current increment <span id="train-caption" class="muted"></span></h3>
<div id="train-strip" class="strip"></div>
<h3>The latest model on test images <span id="test-caption" class="muted"></span></h3>
<div id="test-strip" class="strip"></div>
<h3>Downloads</h3>
<ul id="downloads" class="downloads"></ul>
</section>"""


def _row(item) -> str:
    return (
        f'<tr data-id="{item.id}"><td><a href="/?experiment={item.id}">{item.id}</a></td>'
        f'<td>{escape(item.name)}</td><td class="status {item.status.value}">{item.status.value}</td>'
        f"<td>{escape((item.created_at or '')[:19].replace('T', ' '))}</td></tr>"
    )


@router.get("/", response_class=HTMLResponse)
def dashboard(
    session: SessionDep,
    experiment: Annotated[int | None, Query(description="the experiment to show")] = None,  # any other id: 404 below
) -> HTMLResponse:
    listed = queries.list_experiments(session)
    if experiment is None and listed:
        experiment = listed[-1].id  # the newest
    elif experiment is not None:
        queries.get_experiment(session, experiment)  # 404 for an unknown id
    rows = "".join(_row(item) for item in listed) or '<tr><td colspan="4">none yet</td></tr>'
    return HTMLResponse(
        PAGE.format(
            title=f" · experiment {experiment}" if experiment else "",
            experiment=experiment or "",
            refresh_ms=REFRESH_MS,
            rows=rows,
            detail=DETAIL.format(experiment=experiment) if experiment else "",
        )
    )


@router.get("/dashboard.js")
def dashboard_script() -> FileResponse:
    return FileResponse(STATIC / "dashboard.js", media_type="text/javascript")


@router.get("/dashboard.css")
def dashboard_style() -> FileResponse:
    return FileResponse(STATIC / "dashboard.css", media_type="text/css")
