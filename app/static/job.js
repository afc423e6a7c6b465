// VoxNeRF job page (/static/job.html?id=JOB): state, progress and ETA (live from the job's events, GET
// /jobs/{id}/events, after one GET /jobs/{id}), the
// error against training time (PSNR per split from the job's history, the training loss from its loss_series),
// the stages that ran and why, final metrics per split and per view (render beside ground truth), the config
// and links to report.json, the checkpoint and the job's outputs. Uses api.js (token, fetch) and chart.js.
"use strict";

const OUTPUTS_POLL_MS = 5000;  // once finished: only its outputs still change (they have no event stream)
const RETRY_MS = 3000;  // after a failed GET /jobs/{id}
const IMAGE_LOADS_AT_ONCE = 4;
const FINISHED = ["succeeded", "failed", "cancelled"];

const $ = (id) => document.getElementById(id);
const jobId = new URLSearchParams(location.search).get("id") || "";
const loaded = { report: false, views: false };  // what a finished job needs fetched only once
const downloads = new Map();  // API path -> blob URL already downloaded

function showMessage(text, kind = "error") {
  const box = $("message");
  box.textContent = text;
  box.className = kind === "info" ? "message info" : "message";
  box.hidden = !text;
}

function fixed(value, digits) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

function duration(seconds) {
  if (typeof seconds !== "number" || !Number.isFinite(seconds)) return "–";
  const s = Math.round(seconds);
  return s >= 60 ? `${Math.floor(s / 60)} min ${s % 60} s` : `${s} s`;
}

function when(iso) {
  return iso ? new Date(iso).toLocaleString() : "–";
}

// ------------------------------------------------------------------------------------------- state

function progressBar(job) {
  const percent = Math.round(100 * Math.max(0, Math.min(1, job.progress || 0)));
  const bar = el("div", { className: "bar" }, el("div", { className: "fill" }));
  bar.setAttribute("role", "progressbar");
  bar.setAttribute("aria-valuemin", "0");
  bar.setAttribute("aria-valuemax", "100");
  bar.setAttribute("aria-valuenow", String(percent));
  bar.querySelector(".fill").style.width = `${percent}%`;
  return el("span", { className: "progress" }, bar, el("span", { className: "bar-text" }, `${percent}%`));
}

function drawSummary(job) {
  const iterations = job.options.max_iters;
  const facts = [
    ["State", el("span", { className: `state state-${job.state}`, id: "job-state" }, job.state)],
    ["Stage", job.stage || "–"],
    ["Progress", progressBar(job)],
    ["ETA", job.state === "running" ? duration(job.eta_s) : "–"],
    ["Iteration", iterations ? `${job.iteration} of ${iterations}` : String(job.iteration)],
    ["Training time", duration(job.elapsed_s)],
    ["Last loss", fixed(job.loss ?? (job.loss_series.at(-1) || [])[1], 5)],
    ["Created", when(job.created_at)],
    ["Started", when(job.started_at)],
    ["Finished", when(job.finished_at)],
    ["Attempts", `${job.attempt} (requeued ${job.requeues} times)`],
  ];
  if (job.error) facts.push(["Error", el("span", { className: "error" }, job.error)]);
  $("summary").replaceChildren(...facts.flatMap(([term, value]) => [el("dt", {}, term), el("dd", { data: { fact: term } }, value)]));
  $("summary").dataset.state = job.state;
  const active = !FINISHED.includes(job.state);
  showActions([...(active && !job.cancel_requested ? [actionElements.cancel ??= cancelButton()] : []),
    viewerEntry(job)]);
}

// The action row's elements, made once and updated in place: an update that replaced them (one per progress
// event) could swallow a click that landed on the element it removed.
const actionElements = { cancel: null, link: null, pending: null };

function showActions(parts) {
  const row = $("actions");
  if (parts.length !== row.children.length || parts.some((part, i) => part !== row.children[i])) {
    row.replaceChildren(...parts);
  }
}

// The viewer's link from the job's first checkpoint on (while it trains: its latest checkpoint), else why not yet.
function viewerEntry(job) {
  if (!viewable(job)) {
    const why = FINISHED.includes(job.state) ? "no checkpoint to view" : "the viewer opens at the first checkpoint";
    actionElements.pending ??= el("span", { id: "viewer-pending", className: "muted" });
    actionElements.pending.textContent = ` ${why}`;
    return actionElements.pending;
  }
  const which = job.state === "succeeded" ? "" : ` (iteration ${job.checkpoint_iteration}, ${
    job.state === "running" ? "training" : job.state})`;
  const link = actionElements.link ??= el("a", { id: "viewer-link", className: "viewer-link",
    href: `/static/viewer.html?job=${jobId}` });
  link.dataset.iteration = String(job.checkpoint_iteration ?? "");
  link.textContent = `Open the viewer${which}`;
  return link;
}

function cancelButton() {
  const button = el("button", { className: "secondary", type: "button", textContent: "Cancel job" });
  button.addEventListener("click", async () => {
    try {
      await api(`/jobs/${jobId}/cancel`, { method: "POST" });
      showMessage("Cancel requested: a running job stops at its next iteration.", "info");
    } catch (err) {
      showMessage(`Cancel refused: ${err.message}`);
    }
  });
  return button;
}

// ------------------------------------------------------------------------------------------- plots

// PSNR per split: the progress views' PSNR of every evaluation (progress_psnr when a full or final one has
// it), the final evaluation's all-view PSNR as a square.
function psnrSeries(history) {
  const bySplit = new Map();
  const series = (split) => {
    if (!bySplit.has(split)) bySplit.set(split, { name: split, points: [], marks: [] });
    return bySplit.get(split);
  };
  for (const point of history || []) {
    const curve = point.progress_psnr || point.psnr || {};
    for (const [split, value] of Object.entries(curve)) series(split).points.push([point.elapsed_s, value]);
    if (point.final) {
      for (const [split, value] of Object.entries(point.psnr || {})) {
        series(split).marks.push([point.elapsed_s, value, `final evaluation, all views: ${fixed(value, 2)} dB`]);
      }
    }
  }
  return [...bySplit.values()];
}

function drawPlots(job) {
  const key = JSON.stringify([job.history.map((h) => h.elapsed_s), job.loss_series.length, job.elapsed_s]);
  if ($("psnr-plot").dataset.key === key) return;
  $("psnr-plot").dataset.key = key;
  const losses = job.loss_series || [];
  const xMax = Math.max(job.elapsed_s || 0, ...job.history.map((h) => h.elapsed_s), ...losses.map((p) => p[0]));
  $("psnr-plot").replaceChildren(lineChart({
    xMax, xLabel: "training seconds", yLabel: "PSNR (dB)", series: psnrSeries(job.history),
    label: "PSNR per evaluation split against training seconds",
  }));
  $("loss-plot").replaceChildren(lineChart({
    xMax, xLabel: "training seconds", yLabel: "training loss", log: true,
    series: [{ name: "training loss", points: losses, dots: losses.length < 60 }],
    label: "training loss against training seconds",
  }));
}

// ------------------------------------------------------------------------------------------- stages

function drawStages(job) {
  const rows = (job.stages || []).map((stage) => el("tr", { data: { stage: stage.name, ran: String(stage.ran) } },
    el("td", {}, el("code", {}, stage.name)),
    el("td", { className: stage.ran ? "ran" : "skipped" }, stage.ran ? "yes" : "no"),
    el("td", { className: "why" }, stage.why),
    el("td", {}, fixed(stage.seconds, 2))));
  $("stages").tBodies[0].replaceChildren(...rows);
}

// ------------------------------------------------------------------------------------------- config

function valueText(value) {
  return value !== null && typeof value === "object" ? JSON.stringify(value) : String(value);
}

function keyValueRows(table, entries, highlighted = new Set()) {
  table.tBodies[0].replaceChildren(...entries.map(([key, value]) => el("tr",
    { className: highlighted.has(key) ? "set" : "", data: { key } },
    el("th", {}, el("code", {}, key)), el("td", {}, el("code", {}, valueText(value))))));
}

function drawOptions(job) {
  keyValueRows($("options"), Object.entries(job.options || {}));
}

async function loadReport(job) {
  loaded.report = true;
  let report;
  try {
    report = await (await api(`/jobs/${jobId}/report`)).json();
  } catch (err) {
    $("no-config").textContent = `No report.json: ${err.message}`;
    return;
  }
  $("no-config").hidden = true;
  keyValueRows($("config"), Object.entries(report.config || {}), new Set(Object.keys(job.options || {})));
  $("warnings").replaceChildren(...(report.warnings || []).map((w) => el("li", {}, w)));
  drawFiles(job, true);
}

// ------------------------------------------------------------------------------------------- metrics

function drawMetrics(job) {
  const metrics = job.metrics || {};
  const rows = Object.entries(metrics).map(([split, m]) => el("tr", { data: { split } },
    el("td", {}, split), el("td", {}, String((m.views || []).length)), el("td", {}, fixed(m.psnr, 2)),
    el("td", {}, fixed(m.ssim, 4)), el("td", { title: m.lpips_note || "" }, m.lpips === null ? `– ${m.lpips_note || ""}` : fixed(m.lpips, 4)),
    el("td", { className: "muted" }, m.renderer || "")));
  $("metrics").tBodies[0].replaceChildren(...rows);
  $("no-metrics").hidden = rows.length > 0;
}

// The stem of a file path, as Python's PurePosixPath(path).stem.
function fileStem(path) {
  const base = path.split("/").pop();
  const dot = base.lastIndexOf(".");
  return dot > 0 ? base.slice(0, dot) : base;
}

// "split/view name" -> the frame's ground-truth image URL, from the scene's cameras (GET /jobs/{id}/cameras).
// A view is named as voxnerf.inference.evaluation.view_names names it: its file's stem, or stem-<frame index> when
// several frames of the split share that stem.
function truthUrls(cameras) {
  const urls = new Map();
  const splits = new Set(cameras.frames.flatMap((f) => f.splits));
  for (const split of splits) {
    const frames = cameras.frames.filter((f) => f.splits.includes(split));
    const counts = new Map();
    for (const f of frames) counts.set(fileStem(f.name), (counts.get(fileStem(f.name)) || 0) + 1);
    for (const f of frames) {
      const stem = fileStem(f.name);
      urls.set(`${split}/${counts.get(stem) > 1 ? `${stem}-${f.index}` : stem}`, f.image_url);
    }
  }
  return urls;
}

// Download `images` (each an <img> with data-src) a few at a time, as blob URLs.
async function loadImages(images) {
  const queue = [...images];
  const worker = async () => {
    for (let img = queue.shift(); img; img = queue.shift()) {
      try {
        img.src = await apiBlobUrl(img.dataset.src);
      } catch (err) {
        img.replaceWith(el("span", { className: "error" }, `${img.alt}: ${err.message}`));
      }
    }
  };
  await Promise.all(Array.from({ length: IMAGE_LOADS_AT_ONCE }, worker));
}

async function loadViews(job) {
  loaded.views = true;
  let renders = [], truths = new Map(), truthError = "";
  try {
    renders = await (await api(`/jobs/${jobId}/renders`)).json();
  } catch (err) {
    showMessage(`Evaluation renders: ${err.message}`);
  }
  try {
    truths = truthUrls(await (await api(`/jobs/${jobId}/cameras`)).json());
  } catch (err) {
    truthError = err.message;
  }
  const renderUrls = new Map(renders.map((r) => [`${r.split}/${r.name}`, r.url]));
  const image = (url, alt, kind) => (url
    ? el("img", { alt, className: "view-image", data: { src: url, kind } })
    : el("span", { className: "muted" }, kind === "truth" && truthError ? `unavailable: ${truthError}` : "none"));
  const rows = [];
  for (const [split, m] of Object.entries(job.metrics || {})) {
    for (const view of m.views || []) {
      const key = `${split}/${view.name}`;
      rows.push(el("tr", { data: { split, view: view.name } },
        el("td", {}, split), el("td", {}, el("code", {}, view.name)), el("td", {}, fixed(view.psnr, 2)),
        el("td", {}, fixed(view.ssim, 4)), el("td", {}, fixed(view.lpips, 4)),
        el("td", {}, image(renderUrls.get(key), `render ${key}`, "render")),
        el("td", {}, image(truths.get(key), `ground truth ${key}`, "truth"))));
    }
  }
  $("views").tBodies[0].replaceChildren(...rows);
  loadImages([...$("views").querySelectorAll("img[data-src]")]);  // in the background: live updates go on
}

// ------------------------------------------------------------------------------------------- files

// A link that downloads `path` with the token (as a blob) and saves it as `fileName`.
function downloadLink(path, fileName, text) {
  const link = el("a", { href: "#", textContent: text, data: { path } });
  link.addEventListener("click", async (event) => {
    event.preventDefault();
    try {
      if (!downloads.has(path)) downloads.set(path, await apiBlobUrl(path));
      el("a", { href: downloads.get(path), download: fileName }).click();
    } catch (err) {
      showMessage(`Download of ${fileName}: ${err.message}`);
    }
  });
  return link;
}

function drawFiles(job, hasReport) {
  const items = [];
  if (hasReport) items.push(el("li", {}, downloadLink(`/jobs/${jobId}/report`, `report-${jobId}.json`, "report.json")));
  if (FINISHED.includes(job.state) && job.iteration > 0) {
    items.push(el("li", {}, downloadLink(`/jobs/${jobId}/checkpoint`, `checkpoint-${jobId}.pt`, "checkpoint.pt"),
      el("span", { className: "muted" }, " (the trained model; `voxnerf render` reads it from a run directory)")));
  }
  if (!items.length) items.push(el("li", { className: "muted" }, "report.json and the checkpoint come when the run ends."));
  $("files").replaceChildren(...items);
}

async function refreshOutputs() {
  try {
    const outputs = await (await api(`/jobs/${jobId}/outputs?limit=50`)).json();
    $("outputs").replaceChildren(...outputs.map((o) => el("li", { data: { outputId: o.id, kind: o.kind, state: o.state } },
      `${o.kind}${o.params && o.params.path ? ` (${o.params.path})` : ""} `,
      el("span", { className: `state state-${o.state}` }, o.state), " ",
      o.file_url ? downloadLink(o.file_url, `${o.id.slice(0, 8)}-${o.file_name}`, o.file_name) : null,
      o.error ? el("span", { className: "error" }, ` ${o.error}`) : null)));
    $("no-outputs").hidden = outputs.length > 0;
  } catch (err) {
    showMessage(`Outputs: ${err.message}`);
  }
}

// ------------------------------------------------------------------------------------------- live

let drawing = Promise.resolve();  // draws run one after another: an event never overtakes the one before
let outputsPolled = false;

async function draw(job) {
  showMessage("");
  $("scene-id").textContent = job.scene_id.slice(0, 8);
  $("scene-link").href = `/static/scene.html?id=${job.scene_id}`;
  drawSummary(job);
  drawPlots(job);
  drawStages(job);
  drawOptions(job);
  const finished = FINISHED.includes(job.state);
  if (!loaded.report) drawFiles(job, false);
  if (finished && !loaded.report) await loadReport(job);
  if (job.state === "succeeded") {
    drawMetrics(job);
    if (!loaded.views) await loadViews(job);
  }
  document.body.dataset.state = job.state;
  if (finished && !outputsPolled) {
    outputsPolled = true;
    await refreshOutputs();
    setInterval(refreshOutputs, OUTPUTS_POLL_MS);
  }
}

function show(job) {
  drawing = drawing.then(() => draw(job)).catch((err) => showMessage(`Job ${jobId}: ${err.message}`));
}

// The job once, then (while it is queued or running) its events: each progress and state event carries the whole
// job, so the page redraws from it; the stream ends with the final state.
async function start() {
  let job;
  try {
    job = await (await api(`/jobs/${jobId}`)).json();
  } catch (err) {
    showMessage(`Job ${jobId}: ${err.message}`);
    setTimeout(start, RETRY_MS);
    return;
  }
  show(job);
  if (FINISHED.includes(job.state)) return;
  followJobEvents(jobId, (type, data) => {
    if (type === "progress" || type === "state") show(data);
  }, (message) => showMessage(`Live events of job ${jobId}: ${message} (reconnecting)`));
}

$("job-id").textContent = jobId.slice(0, 8);
$("job-id").title = jobId;
document.title = `VoxNeRF · job ${jobId.slice(0, 8)}`;
if (/^[0-9a-f]{32}$/.test(jobId)) start(); else showMessage("No job id: open this page from the dashboard's job list.");
