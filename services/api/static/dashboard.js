// foldwise dashboard: reads the REST routes and redraws; no framework, no build step.
"use strict";

const body = document.body;
const experimentId = body.dataset.experiment;
const refreshMs = Number(body.dataset.refreshMs || 3000);
const SVG = "http://www.w3.org/2000/svg";
// Stage colours (matplotlib's tab10, as in the report's PNG).
const COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
const colour = (order) => COLOURS[order % COLOURS.length];

let config = null;
let drawn = { history: -1, model: null, trainKey: null };

function el(tag, attributes = {}, ...children) {
  const node = tag.startsWith("svg:") ? document.createElementNS(SVG, tag.slice(4)) : document.createElement(tag);
  for (const [key, value] of Object.entries(attributes)) {
    if (key === "text") node.textContent = value;
    else node.setAttribute(key, value);
  }
  children.forEach((child) => node.append(child));
  return node;
}

async function read(path) {
  const response = await fetch(path, { headers: { Accept: "application/json" } });
  if (!response.ok) throw new Error(`${path}: ${response.status}`);
  return response.json();
}

function duration(seconds) {
  if (seconds === null || seconds === undefined || !isFinite(seconds)) return "–";
  const s = Math.max(0, Math.round(seconds));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), r = s % 60;
  return h ? `${h} h ${String(m).padStart(2, "0")} min` : m ? `${m} min ${String(r).padStart(2, "0")} s` : `${r} s`;
}

const fixed = (value, digits = 3) => (value === null || value === undefined ? "–" : Number(value).toFixed(digits));

// ---------------------------------------------------------------- summary and ETA

// Time left at the pace so far: finished stages plus the current stage's share of its cap
// (a learnability experiment trains exactly learnability.kappa increments per stage, the
// canonical baseline canonical_baseline.increments in its one stage, and the canonical stage
// of learnability.start: canonical its learnability.canonical_increments).
const FIXED_INCREMENTS = {
  learnability: (stage) => (stage.condition === "canonical" ? config.learnability.canonical_increments : config.learnability.kappa),
  canonical_baseline: () => config.canonical_baseline.increments,
};
function eta(summary, stages) {
  if (summary.status !== "running" || !summary.elapsed_seconds) return null;
  let done = stages.filter((s) => s.status === "done").length;
  const current = stages.find((s) => s.status === "running");
  if (current) {
    const cap = (FIXED_INCREMENTS[config.kind] || (() => config.active_learning.max_increments))(current);
    done += Math.min(current.increments / cap, 0.99);
  }
  if (done <= 0) return null;
  return (summary.elapsed_seconds / done) * (stages.length - done);
}

function drawSummary(summary, stages) {
  const current = summary.current_stage;
  const cards = [
    ["status", summary.status],
    ["stage", current ? `${current.order}: ${current.condition}/${current.difficulty}` : "–"],
    ["k", current && current.k !== null ? current.k : "–"],
    ["stages done", `${stages.filter((s) => s.status === "done").length} / ${stages.length}`],
    ["elapsed", duration(summary.elapsed_seconds)],
    ["ETA", summary.status === "running" ? duration(eta(summary, stages)) : "–"],
    ["best mAP", summary.best ? `${fixed(summary.best.map)} (ω ${summary.best.model_id})` : "–"],
    ["evaluations", summary.counts.evaluations],
  ];
  const box = document.getElementById("summary");
  box.replaceChildren(...cards.map(([label, value]) => el("div", { class: "card", "data-field": label },
    el("span", { class: "label", text: label }), el("span", { class: `value ${label === "status" ? summary.status : ""}`, text: String(value) }))));
  document.getElementById("title").textContent = `Experiment ${summary.id}: ${summary.name}`;
  if (summary.error) box.append(el("div", { class: "card error", text: summary.error }));
}

function drawStages(stages) {
  const rows = stages.map((s) => el("tr", { class: s.status },
    el("td", {}, el("span", { class: "swatch", style: `background:${colour(s.order)}` }), String(s.order)),
    el("td", { text: s.condition }), el("td", { text: s.difficulty }), el("td", { text: s.status }),
    el("td", { text: String(s.increments) }), el("td", { text: s.end_reason || "" }),
    el("td", { text: fixed(s.best_map) }), el("td", { text: duration(s.seconds) })));
  document.querySelector("#stages tbody").replaceChildren(...rows);
}

// ---------------------------------------------------------------- P curve

function drawCurve(history, stages) {
  const svg = document.getElementById("p-curve");
  const W = 640, H = 300, left = 48, right = 12, top = 12, bottom = 36;
  const xmax = Math.max(1, ...history.map((e) => e.wall_seconds || 0)) * 1.04;
  const x = (t) => left + ((t || 0) / xmax) * (W - left - right);
  const y = (error) => top + error * (H - top - bottom);  // error 0 at the top: lower is better
  const parts = [];
  // Axes and grid.
  for (let g = 0; g <= 4; g++) {
    const value = g / 4;
    parts.push(el("svg:line", { x1: left, x2: W - right, y1: y(value), y2: y(value), class: "grid" }));
    parts.push(el("svg:text", { x: left - 6, y: y(value) + 4, class: "tick", "text-anchor": "end", text: value.toFixed(2) }));
  }
  for (let g = 0; g <= 4; g++) {
    const t = (xmax / 4) * g;
    parts.push(el("svg:text", { x: x(t), y: H - bottom + 16, class: "tick", "text-anchor": "middle", text: duration(t) }));
  }
  parts.push(el("svg:text", { x: W / 2, y: H - 4, class: "axis", "text-anchor": "middle", text: "wall time" }));
  parts.push(el("svg:text", { x: 12, y: H / 2, class: "axis", transform: `rotate(-90 12 ${H / 2})`, "text-anchor": "middle", text: "error" }));

  // The stopping windows on the current stage: the last M scores and the N before them.
  const running = stages.find((s) => s.status === "running") || stages[stages.length - 1];
  if (running) {
    const own = history.filter((e) => e.stage === running.order);
    const M = config.active_learning.M, N = config.active_learning.N;
    const windows = [["window-m", own.slice(-M)], ["window-n", own.slice(Math.max(0, own.length - M - N), Math.max(0, own.length - M))]];
    for (const [name, entries] of windows) {
      if (!entries.length) continue;
      const x0 = x(entries[0].wall_seconds) - 6, x1 = x(entries[entries.length - 1].wall_seconds) + 6;
      parts.push(el("svg:rect", { class: `window ${name}`, x: x0, y: top, width: x1 - x0, height: H - top - bottom }));
    }
  }
  // One polyline per stage, then the points (one per entry of P).
  const byStage = new Map();
  history.forEach((e) => byStage.set(e.stage, [...(byStage.get(e.stage) || []), e]));
  for (const [order, entries] of byStage) {
    const points = entries.filter((e) => e.map !== null).map((e) => `${x(e.wall_seconds)},${y(1 - e.map)}`).join(" ");
    parts.push(el("svg:polyline", { points, class: "stage-line", stroke: colour(order) }));
  }
  history.forEach((e) => {
    const undefinedScore = e.map === null;
    const point = el("svg:circle", {
      class: `point${undefinedScore ? " undefined" : ""}`, cx: x(e.wall_seconds), cy: y(undefinedScore ? 1 : 1 - e.map), r: 4,
      fill: undefinedScore ? "white" : colour(e.stage), stroke: colour(e.stage), "data-model": e.model_id,
    });
    point.append(el("svg:title", { text: `${e.condition}/${e.difficulty} k=${e.k}: mAP ${fixed(e.map)} at ${duration(e.wall_seconds)} (ω ${e.model_id})` }));
    parts.push(point);
  });
  svg.replaceChildren(...parts);
  document.getElementById("legend").replaceChildren(...stages.map((s) =>
    el("span", {}, el("span", { class: "swatch", style: `background:${colour(s.order)}` }), `${s.order}: ${s.condition}/${s.difficulty}`)));
}

// ---------------------------------------------------------------- heat map

function heat(value) {
  if (value === null || value === undefined) return "#eee";
  const hue = Math.round(120 * value);  // red (0) to green (1)
  return `hsl(${hue}, 65%, ${80 - 25 * value}%)`;
}

function drawHeatmap(model, stages) {
  const conditions = [...new Set(stages.map((s) => s.condition))];
  const difficulties = [...new Set(stages.map((s) => s.difficulty))];
  const breakdown = (model && model.evaluation && model.evaluation.details.breakdown || {})["condition/difficulty"] || {};
  const head = el("tr", {}, el("th", { text: "c \\ δ" }), ...difficulties.map((d) => el("th", { text: d })));
  const rows = conditions.map((c) => el("tr", {}, el("th", { text: c }), ...difficulties.map((d) => {
    const group = breakdown[`${c}/${d}`];
    const value = group ? group.map : null;
    return el("td", { class: "cell", "data-key": `${c}/${d}`, style: `background:${heat(value)}`,
      title: group ? `${group.num_images} test images, unthresholded mAP ${fixed(group.map_unthresholded)}` : "not in the test set",
      text: group ? fixed(value, 2) : "–" });
  })));
  document.getElementById("heatmap").replaceChildren(el("thead", {}, head), el("tbody", {}, ...rows));
  document.getElementById("heatmap-model").textContent = model ? `(ω ${model.id}: ${model.stage.condition}/${model.stage.difficulty} k=${model.k})` : "";
}

// ---------------------------------------------------------------- image strips

function thumbnail(url, boxes, caption, size) {
  const overlay = el("svg:svg", { viewBox: `0 0 ${size} ${size}`, class: "boxes" });
  boxes.forEach(({ box, label, kind }) => {
    const [x0, y0, x1, y1] = box;
    overlay.append(el("svg:rect", { x: x0, y: y0, width: x1 - x0, height: y1 - y0, class: kind }));
    if (label) overlay.append(el("svg:text", { x: x0 + 1, y: Math.max(y0 - 1, 6), class: "box-label", text: label }));
  });
  return el("figure", { class: "thumb" }, el("div", { class: "frame" }, el("img", { src: url, alt: caption, loading: "eager" }), overlay),
    el("figcaption", { text: caption }));
}

function drawTrainStrip(images, classes, size) {
  const key = `${images.stage}/${images.k}/${images.images.length}`;
  if (key === drawn.trainKey) return;
  drawn.trainKey = key;
  document.getElementById("train-caption").textContent = images.k ? `(stage ${images.stage}, k=${images.k}: ${images.images.length} images)` : "";
  document.getElementById("train-strip").replaceChildren(...images.images.slice(0, 12).map((image) => thumbnail(
    image.url, image.objects.map((o) => ({ box: o.box, label: classes[o.label], kind: "truth" })), `${image.condition}/${image.difficulty}`, size)));
}

function drawTestStrip(model, classes, size) {
  const samples = (model && model.evaluation && model.evaluation.details.test_detections) || [];
  const threshold = config.evaluation.score_threshold;
  document.getElementById("test-caption").textContent = model ? `(ω ${model.id}; solid: score ≥ ${threshold}, dashed: below)` : "";
  document.getElementById("test-strip").replaceChildren(...samples.map((sample) => thumbnail(
    `/experiments/${experimentId}/images/${sample.image_id}.png`,
    sample.boxes.map((box, i) => sample.scores[i] >= threshold
      ? { box, kind: "detection", label: `${classes[sample.labels[i]] || sample.labels[i]} ${sample.scores[i].toFixed(2)}` }
      : { box, kind: "weak" }),
    `${sample.condition}/${sample.difficulty}: ${sample.boxes.length ? "best " + sample.scores[0].toFixed(2) : "nothing found"}`, size)));
}

function drawDownloads(summary, latest) {
  const links = [];
  const model = summary.final_model_id || (summary.best && summary.best.model_id);
  if (model) links.push([`/models/${model}/checkpoint`, `checkpoint of ω ${model} (${summary.final_model_id ? "final" : "best so far"})`]);
  if (latest && latest.id !== model) links.push([`/models/${latest.id}/checkpoint`, `checkpoint of the latest ω ${latest.id}`]);
  links.push([`/experiments/${experimentId}/coco?split=test`, "COCO: test set"], [`/experiments/${experimentId}/coco?split=train`, "COCO: training images"],
    [`/experiments/${experimentId}/report.png`, "report (PNG)"], [`/experiments/${experimentId}/report.csv`, "report (CSV)"],
    [`/experiments/${experimentId}/history`, "P (JSON)"]);
  document.getElementById("downloads").replaceChildren(...links.map(([href, text]) => el("li", {}, el("a", { href, text }))));
}

// ---------------------------------------------------------------- the loop

async function refreshList() {
  const experiments = await read("/experiments");
  const rows = experiments.map((e) => el("tr", { "data-id": e.id, class: String(e.id) === experimentId ? "selected" : "" },
    el("td", {}, el("a", { href: `/?experiment=${e.id}`, text: String(e.id) })), el("td", { text: e.name }),
    el("td", { class: `status ${e.status}`, text: e.status }), el("td", { text: (e.created_at || "").slice(0, 19).replace("T", " ") })));
  document.getElementById("experiment-rows").replaceChildren(...rows);
}

async function refresh() {
  await refreshList();
  if (!experimentId) return "idle";
  const base = `/experiments/${experimentId}`;
  if (!config) config = await read(`${base}/config`);
  const [summary, stages, history, training] = await Promise.all([
    read(base), read(`${base}/stages`), read(`${base}/history`), read(`${base}/images?split=train&limit=12`)]);
  const classes = summary.classes || [];
  const size = config.render.image_size;
  drawSummary(summary, stages);
  drawStages(stages);
  drawTrainStrip(training, classes, size);
  const latestId = history.length ? history[history.length - 1].model_id : null;
  if (history.length !== drawn.history || latestId !== drawn.model) {
    const latest = latestId ? await read(`/models/${latestId}`) : null;
    drawCurve(history, stages);
    drawHeatmap(latest, stages);
    drawTestStrip(latest, classes, size);
    drawDownloads(summary, latest);
    drawn.history = history.length;
    drawn.model = latestId;
  }
  body.dataset.historyLength = String(history.length);
  return summary.status;
}

async function loop() {
  try {
    await refresh();
    document.getElementById("updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
    body.dataset.refreshed = String(Number(body.dataset.refreshed || 0) + 1);
  } catch (error) {
    document.getElementById("updated").textContent = `update failed: ${error.message}`;
  }
  setTimeout(loop, refreshMs);
}

loop();
