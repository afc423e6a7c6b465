// VoxNeRF dashboard: draws jobs, progress, PSNR plots, evaluation renders and renders from the REST API. Queued and
// running jobs update live from their events (GET /jobs/{id}/events); the job list itself is read again only every
// JOB_LIST_MS, for jobs made elsewhere (another tab, a script). No framework and no build step. Every request
// carries the API token saved in localStorage (if any).
"use strict";

const POLL_MS = 1000;  // imports and running outputs (they have no event stream)
const JOB_LIST_MS = 15000;  // the job list: new jobs made elsewhere appear within this; live jobs update from events
const MAX_FOLLOWED = 4;  // jobs followed live at once: each stream holds one of the browser's 6 connections per host
const HEALTH_MS = 5000;
const MAX_THUMBS = 12;
const SPLIT_COLOURS = ["#2f6fdb", "#d9822b", "#1f8a4c", "#9b59b6", "#c23b30", "#16a2b8"];
const SVG_NS = "http://www.w3.org/2000/svg";

const $ = (id) => document.getElementById(id);
const thumbsLoaded = new Set();  // job ids whose evaluation renders were fetched
const followed = new Map();  // job id -> its live event stream (followJobEvents)
const outputMedia = new Map();  // output id -> blob URL of its downloaded video or file
const OUTPUT_BUTTONS = [  // [data-output, label, endpoint, body builder]
  ["orbit", "Video (orbit)", "videos", () => videoBody("orbit")],
  ["interpolate", "Video (through cameras)", "videos", () => videoBody("interpolate")],
  ["mesh", "Mesh", "exports", () => ({ kind: "mesh" })],
  ["pointcloud", "Point cloud", "exports", () => ({ kind: "pointcloud" })],
];

// ------------------------------------------------------------------------------------------- API access
// savedToken, saveToken, api and apiBlobUrl are /static/api.js's (loaded first).

function showMessage(text, kind = "error") {
  const box = $("message");
  box.textContent = text;
  box.className = kind === "info" ? "message info" : "message";
  box.hidden = !text;
}

// ------------------------------------------------------------------------------------------- drawing

function svg(tag, attrs, text) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [key, value] of Object.entries(attrs)) node.setAttribute(key, value);
  if (text !== undefined) node.textContent = text;
  return node;
}

// PSNR (dB) of every split against training seconds, one polyline per split.
function psnrPlot(history) {
  const width = 260, height = 80, left = 30, right = 8, top = 8, bottom = 16;
  const series = new Map();
  for (const point of history || []) {
    for (const [split, value] of Object.entries(point.psnr || {})) {
      if (typeof value !== "number" || !Number.isFinite(value)) continue;
      if (!series.has(split)) series.set(split, []);
      series.get(split).push([point.elapsed_s, value]);
    }
  }
  const root = svg("svg", { width, height, class: "plot", role: "img", "aria-label": "PSNR against time" });
  const all = [...series.values()].flat();
  root.dataset.points = String(all.length);
  if (!all.length) {
    root.appendChild(svg("text", { x: left, y: height / 2 }, "no evaluation yet"));
    return root;
  }
  const xMax = Math.max(1, ...all.map((p) => p[0]));
  let yMin = Math.min(...all.map((p) => p[1])), yMax = Math.max(...all.map((p) => p[1]));
  if (yMax - yMin < 1) { yMin -= 0.5; yMax += 0.5; }
  const x = (s) => left + (s / xMax) * (width - left - right);
  const y = (v) => top + (1 - (v - yMin) / (yMax - yMin)) * (height - top - bottom);
  root.appendChild(svg("line", { x1: left, y1: top, x2: left, y2: height - bottom, class: "axis" }));
  root.appendChild(svg("line", { x1: left, y1: height - bottom, x2: width - right, y2: height - bottom, class: "axis" }));
  root.appendChild(svg("text", { x: 2, y: top + 6 }, yMax.toFixed(1)));
  root.appendChild(svg("text", { x: 2, y: height - bottom }, yMin.toFixed(1)));
  root.appendChild(svg("text", { x: width - right - 28, y: height - 3 }, `${xMax.toFixed(0)} s`));
  let index = 0;
  for (const [split, points] of series) {
    const colour = SPLIT_COLOURS[index % SPLIT_COLOURS.length];
    points.sort((a, b) => a[0] - b[0]);
    root.appendChild(svg("polyline", {
      points: points.map(([s, v]) => `${x(s).toFixed(1)},${y(v).toFixed(1)}`).join(" "),
      fill: "none", stroke: colour, "stroke-width": 1.5, "data-split": split,
    }));
    for (const [s, v] of points) {
      root.appendChild(svg("circle", { cx: x(s), cy: y(v), r: 2, fill: colour }));
    }
    root.appendChild(svg("text", { x: left + 4 + 70 * index, y: height - 3, fill: colour }, split));
    index += 1;
  }
  return root;
}

function progressBar(job) {
  const percent = Math.round(100 * Math.max(0, Math.min(1, job.progress || 0)));
  const wrap = document.createElement("div");
  wrap.className = "bar";
  wrap.setAttribute("role", "progressbar");
  wrap.setAttribute("aria-valuemin", "0");
  wrap.setAttribute("aria-valuemax", "100");
  wrap.setAttribute("aria-valuenow", String(percent));
  const fill = document.createElement("div");
  fill.className = "fill";
  fill.style.width = `${percent}%`;
  wrap.appendChild(fill);
  const text = document.createElement("span");
  text.className = "bar-text";
  text.textContent = `${percent}% · it ${job.iteration}${job.stage ? " · " + job.stage : ""}`;
  const cell = document.createElement("div");
  cell.style.display = "flex";
  cell.style.alignItems = "center";
  cell.append(wrap, text);
  return cell;
}

function formatEta(job) {
  if (job.state !== "running" || job.eta_s === null || job.eta_s === undefined) return "";
  const s = Math.round(job.eta_s);
  return s >= 60 ? `${Math.floor(s / 60)} min ${s % 60} s` : `${s} s`;
}

async function loadThumbnails(job, cell) {
  thumbsLoaded.add(job.id);
  try {
    const renders = await (await api(`/jobs/${job.id}/renders`)).json();
    for (const item of renders.slice(0, MAX_THUMBS)) {
      const blob = await (await api(item.url)).blob();
      const img = document.createElement("img");
      img.src = URL.createObjectURL(blob);
      img.alt = `${item.split}/${item.name}`;
      img.title = `${item.split}/${item.name}`;
      cell.appendChild(img);
    }
  } catch (err) {
    thumbsLoaded.delete(job.id);  // try again on the next poll
    showMessage(`Evaluation renders of ${job.id}: ${err.message}`);
  }
}

function cancelButton(job) {
  const button = document.createElement("button");
  button.className = "secondary";
  button.textContent = "Cancel";
  button.addEventListener("click", async () => {
    try {
      await api(`/jobs/${job.id}/cancel`, { method: "POST" });
      refreshJobs();
    } catch (err) {
      showMessage(err.message);
    }
  });
  return button;
}

function jobRow(job) {
  let row = document.querySelector(`tr[data-job-id="${job.id}"]`);
  if (!row) {
    row = document.createElement("tr");
    row.dataset.jobId = job.id;
    for (const name of ["id", "scene", "by", "state", "progress", "eta", "plot", "thumbs", "actions", "outputs"]) {
      const cell = document.createElement("td");
      cell.className = `col-${name}`;
      row.appendChild(cell);
    }
    row.querySelector(".col-thumbs").appendChild(Object.assign(document.createElement("div"), { className: "thumbs" }));
    row.querySelector(".col-outputs").append(
      Object.assign(document.createElement("div"), { className: "output-buttons" }),
      Object.assign(document.createElement("ul"), { className: "outputs" }),
    );
  }
  return row;
}

// A link to a job's or scene's own page, showing the id's first 8 digits.
function pageLink(href, id, className) {
  const link = Object.assign(document.createElement("a"), { href, className, title: id });
  link.appendChild(Object.assign(document.createElement("code"), { textContent: id.slice(0, 8) }));
  return link;
}

// The viewer of a succeeded job, or of a running, cancelled or failed one's latest checkpoint (api.js `viewable`).
function viewerLink(job) {
  return Object.assign(document.createElement("a"), { href: `/static/viewer.html?job=${job.id}`, className: "viewer-link", textContent: "view" });
}

function updateRow(row, job) {
  const cell = (name) => row.querySelector(`.col-${name}`);
  if (!cell("id").firstChild) {  // a job's own links never change: made once, so a click on them is never lost
    cell("id").appendChild(pageLink(`/static/job.html?id=${job.id}`, job.id, "job-page"));
    cell("scene").appendChild(pageLink(`/static/scene.html?id=${job.scene_id}`, job.scene_id, "scene-page"));
  }
  cell("by").textContent = job.created_by || "";
  const state = Object.assign(document.createElement("span"), { className: `state state-${job.state}`, textContent: job.state });
  cell("state").replaceChildren(state);
  if (job.error) cell("state").appendChild(Object.assign(document.createElement("div"), { className: "error", textContent: job.error }));
  cell("progress").replaceChildren(progressBar(job));
  cell("eta").textContent = formatEta(job);
  const historyKey = JSON.stringify(job.history.map((h) => [h.elapsed_s, h.psnr]));
  if (row.dataset.historyKey !== historyKey) {
    row.dataset.historyKey = historyKey;
    cell("plot").replaceChildren(psnrPlot(job.history));
  }
  if (job.state === "succeeded" && !thumbsLoaded.has(job.id)) loadThumbnails(job, cell("thumbs").firstChild);
  const actionsKey = `${job.state} ${viewable(job)}`;
  if (row.dataset.actionsKey !== actionsKey) {  // rebuilt only when they change (a link being clicked stays)
    row.dataset.actionsKey = actionsKey;
    cell("actions").replaceChildren(...(job.state === "queued" || job.state === "running" ? [cancelButton(job)] : []),
      ...(viewable(job) ? [viewerLink(job)] : []));
  }
  if (job.state === "succeeded") {
    const buttons = cell("outputs").querySelector(".output-buttons");
    if (!buttons.childElementCount) buttons.append(...outputButtons(job));
    refreshOutputs(job, cell("outputs").querySelector(".outputs"));
  }
  row.dataset.state = job.state;
}

// ------------------------------------------------------------------------------------------- outputs

function videoBody(path) {
  const body = { path, frames: Number($("video-frames").value), fps: Number($("video-fps").value) };
  const width = $("video-width").value, height = $("video-height").value;
  if (width && height) Object.assign(body, { width: Number(width), height: Number(height) });
  return body;
}

function outputButtons(job) {
  return OUTPUT_BUTTONS.map(([name, label, endpoint, body]) => {
    const button = Object.assign(document.createElement("button"), { className: "secondary", textContent: label });
    button.type = "button";
    button.dataset.output = name;
    button.addEventListener("click", async () => {
      try {
        const output = await (await api(`/jobs/${job.id}/${endpoint}`, {
          method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body()),
        })).json();
        showMessage(`${label} of job ${job.id.slice(0, 8)} queued (output ${output.id.slice(0, 8)}).`, "info");
        refreshOutputs(job, button.closest("td").querySelector(".outputs"));
      } catch (err) {
        showMessage(`${label} refused: ${err.message}`);
      }
    });
    return button;
  });
}

// The output's blob URL, downloaded once with the API token (a <video> or a link cannot send the header).
async function outputBlobUrl(output) {
  if (!outputMedia.has(output.id)) {
    const blob = await (await api(output.file_url)).blob();
    outputMedia.set(output.id, URL.createObjectURL(blob));
  }
  return outputMedia.get(output.id);
}

function outputMediaNode(output) {
  if (output.kind === "video") {
    const video = Object.assign(document.createElement("video"), { controls: true, muted: true, loop: true });
    outputBlobUrl(output).then((url) => { video.src = url; }, (err) => showMessage(`Video: ${err.message}`));
    return video;
  }
  const link = Object.assign(document.createElement("a"), { href: "#", textContent: `download ${output.file_name}` });
  link.addEventListener("click", async (event) => {
    event.preventDefault();
    try {
      const save = Object.assign(document.createElement("a"), { href: await outputBlobUrl(output) });
      save.download = `${output.id.slice(0, 8)}-${output.file_name}`;
      save.click();
    } catch (err) {
      showMessage(`Download: ${err.message}`);
    }
  });
  return link;
}

function outputItem(list, output) {
  let item = list.querySelector(`li[data-output-id="${output.id}"]`);
  if (!item) {
    item = Object.assign(document.createElement("li"), { className: "output" });
    item.dataset.outputId = output.id;
    item.dataset.kind = output.kind;
    item.append(document.createElement("span"), document.createElement("span"));
  }
  const [label, status] = item.children;
  label.textContent = output.kind + (output.params && output.params.path ? ` (${output.params.path})` : "");
  const percent = Math.round(100 * (output.progress || 0));
  status.className = `state state-${output.state}`;
  status.textContent = output.state === "running" ? `${percent}% · ${output.done}/${output.total ?? "?"} ${output.unit}`
    : output.state + (output.error ? `: ${output.error}` : "");
  if (output.state === "succeeded" && item.dataset.state !== "succeeded") item.appendChild(outputMediaNode(output));
  item.dataset.state = output.state;
  return item;
}

async function refreshOutputs(job, list) {
  try {
    const outputs = await (await api(`/jobs/${job.id}/outputs?limit=20`)).json();
    list.replaceChildren(...outputs.map((output) => outputItem(list, output)));
  } catch (err) {
    showMessage(`Outputs of ${job.id}: ${err.message}`);
  }
}

function fillSelect(select, items, label) {
  const previous = select.value;
  select.replaceChildren(...items.map((item) => new Option(label(item), item.id)));
  if (items.some((item) => item.id === previous)) select.value = previous;
}

// ------------------------------------------------------------------------------------------- live jobs

// Follow a queued or running job's events (at most MAX_FOLLOWED at once; the others update with the job list):
// each progress and state event carries the whole job and redraws its row; at its final state the list is read
// again (the render form lists succeeded jobs).
function follow(job) {
  if (followed.has(job.id) || followed.size >= MAX_FOLLOWED || !(job.state === "queued" || job.state === "running")) return;
  followed.set(job.id, followJobEvents(job.id, (type, data) => {
    if (type !== "progress" && type !== "state") return;
    updateRow(jobRow(data), data);
    if (FINAL_STATES.includes(data.state)) {
      followed.delete(data.id);
      refreshJobs();
    }
  }, (message) => showMessage(`Live events of job ${job.id.slice(0, 8)}: ${message} (reconnecting)`)));
}

// Refresh the outputs of the rows that have one queued or running (they have no event stream).
function refreshActiveOutputs() {
  for (const row of document.querySelectorAll("#jobs tr[data-job-id]")) {
    if (row.querySelector('li.output[data-state="queued"], li.output[data-state="running"]')) {
      refreshOutputs({ id: row.dataset.jobId }, row.querySelector(".outputs"));
    }
  }
}

// ------------------------------------------------------------------------------------------- job list

async function refreshJobs() {
  try {
    const jobs = await (await api("/jobs?limit=50")).json();
    const body = $("jobs").tBodies[0];
    const rows = jobs.map((job) => {
      const row = jobRow(job);
      if (!followed.has(job.id)) updateRow(row, job);  // a followed job's events are newer than this list
      follow(job);
      return row;
    });
    if (rows.length !== body.rows.length || rows.some((row, i) => body.rows[i] !== row)) body.replaceChildren(...rows);
    $("no-jobs").hidden = jobs.length > 0;
    const done = jobs.filter((job) => job.state === "succeeded");
    fillSelect($("render-job"), done, (job) => `${job.id.slice(0, 8)} (scene ${job.scene_id.slice(0, 8)})`);
  } catch (err) {
    showMessage(err.message);
  }
}

function importRow(item) {
  // one capture import: its state and stage, progress, and the scene it made (or why it failed)
  const row = document.createElement("tr");
  row.dataset.importId = item.id;
  const percent = Math.round(100 * item.progress);
  const bar = document.createElement("progress");
  bar.max = 100;
  bar.value = percent;
  bar.setAttribute("aria-label", `import ${item.id.slice(0, 8)}`);
  const outcome = document.createElement("td");
  if (item.scene_id) outcome.textContent = `scene ${item.scene_id.slice(0, 8)} · ${item.summary.frames} frames`;
  else if (item.error) outcome.textContent = item.error;
  const stage = item.stage && item.step && item.state === "running" ? `${item.stage}: ${item.step}` : item.stage || "";
  const cells = [item.id.slice(0, 8), `${item.name} (${item.layout})`, item.created_by || "", item.state, stage];
  row.append(...cells.map((text) => Object.assign(document.createElement("td"), { textContent: text })));
  const progressCell = document.createElement("td");
  progressCell.append(bar, ` ${percent}%`);
  const actions = document.createElement("td");
  if (item.state === "queued" || item.state === "running") {
    const button = Object.assign(document.createElement("button"), { textContent: "Cancel", type: "button" });
    button.addEventListener("click", () => api(`/imports/${item.id}/cancel`, { method: "POST" })
      .then(refreshImports).catch((err) => showMessage(err.message)));
    actions.append(button);
  }
  row.append(progressCell, outcome, actions);
  row.dataset.state = item.state;
  return row;
}

let importsSucceeded = 0;

async function refreshImports() {
  try {
    const items = await (await api("/imports?limit=20")).json();
    $("imports").tBodies[0].replaceChildren(...items.map(importRow));
    $("imports-section").hidden = items.length === 0;
    const succeeded = items.filter((item) => item.state === "succeeded").length;
    if (succeeded !== importsSucceeded) refreshScenes();  // an import just made a scene
    importsSucceeded = succeeded;
  } catch (err) {
    showMessage(err.message);
  }
}

async function refreshScenes() {
  try {
    const scenes = await (await api("/scenes")).json();
    fillSelect($("job-scene"), scenes, (s) => `${s.name} · ${s.summary.frames} frames · ${s.id.slice(0, 8)}`);
  } catch (err) {
    showMessage(err.message);
  }
}

async function refreshHealth() {
  const badge = $("health");
  try {
    // with the token the details come too; without it (when the server needs one) the status alone
    const token = savedToken();
    const response = await fetch("/healthz", token ? { headers: { Authorization: `Bearer ${token}` } } : {});
    const health = await response.json();
    badge.className = `health ${response.ok ? "ok" : "bad"}`;
    if (!health.workers) {
      badge.textContent = health.status;
      badge.title = "details need the API token";
      return;
    }
    const workers = Object.entries(health.workers).map(([q, names]) => `${q}: ${names.length}`).join(", ");
    badge.textContent = `${health.status} · workers ${workers}`;
    badge.title = `database: ${health.database.detail}\nbroker: ${health.broker.detail}`;
  } catch (err) {
    badge.textContent = "API unreachable";
    badge.className = "health bad";
  }
}

// ------------------------------------------------------------------------------------------- forms

$("token-form").addEventListener("submit", (event) => {
  event.preventDefault();
  saveToken($("token").value.trim());
  showMessage("");
  refreshJobs();
  refreshScenes();
  refreshImports();
});

$("upload-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const file = $("upload-file").files[0];
  if (!file) return;
  const form = new FormData();
  form.append("file", file, file.name);
  try {
    showMessage(`Uploading ${file.name}…`, "info");
    const response = await api("/scenes", { method: "POST", body: form });
    const stored = await response.json();
    if (response.status === 202) {  // a capture: its import is queued, and its scene comes when it succeeds
      showMessage(`Capture ${file.name} queued for import (${stored.id}); its scene appears when it is done.`,
        "info");
      refreshImports();
      return;
    }
    const sizes = Object.keys(stored.summary.image_sizes || {});
    const pixels = sizes.length > 1 ? `images of ${sizes.length} sizes (${sizes.join(", ")})`
      : `${stored.summary.image_size.join("x")} pixels`;
    showMessage(`Scene ${stored.id} stored: ${stored.summary.frames} frames, ${pixels}.`, "info");
    refreshScenes();
  } catch (err) {
    showMessage(`Upload refused: ${err.message}`);
  }
});

$("job-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const sceneId = $("job-scene").value;
  const body = { max_seconds: Number($("job-seconds").value), sampler: $("job-sampler").value };
  try {
    const job = await (await api(`/scenes/${sceneId}/jobs`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    })).json();
    showMessage(`Job ${job.id} queued.`, "info");
    refreshJobs();
  } catch (err) {
    showMessage(`Job refused: ${err.message}`);
  }
});

$("render-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  let pose;
  try {
    pose = JSON.parse($("render-pose").value);
  } catch (err) {
    showMessage(`The pose is not valid JSON: ${err.message}`);
    return;
  }
  const body = { job_id: $("render-job").value, transform_matrix: pose, format: "png" };
  const width = $("render-width").value, height = $("render-height").value;
  if (width && height) Object.assign(body, { width: Number(width), height: Number(height) });
  const started = performance.now();
  try {
    const blob = await (await api("/render", {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    })).blob();
    const img = $("render-image");
    if (img.src) URL.revokeObjectURL(img.src);
    img.src = URL.createObjectURL(blob);
    $("render-caption").textContent = `rendered in ${Math.round(performance.now() - started)} ms`;
    $("render-figure").hidden = false;
    showMessage("");
  } catch (err) {
    showMessage(`Render refused: ${err.message}`);
  }
});

$("token").value = savedToken();
refreshHealth();
refreshScenes();
refreshJobs();
refreshImports();
setInterval(refreshJobs, JOB_LIST_MS);
setInterval(refreshActiveOutputs, POLL_MS);
setInterval(refreshImports, POLL_MS);
setInterval(refreshHealth, HEALTH_MS);
