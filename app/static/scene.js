// VoxNeRF scene page (/static/scene.html?id=SCENE): the scene's summary (GET /scenes/{id}: frames per split,
// image size, prior kind and sigma, depth) and its jobs (GET /jobs?scene_id=...), each linking to its job page.
// Queued and running jobs update live from their events (GET /jobs/{id}/events); the list is read again every
// LIST_MS, for jobs made meanwhile elsewhere. Uses api.js (token, fetch, followJobEvents).
"use strict";

const LIST_MS = 15000;
const MAX_FOLLOWED = 4;  // jobs followed live at once: each stream holds one of the browser's 6 connections per host
const $ = (id) => document.getElementById(id);
const sceneId = new URLSearchParams(location.search).get("id") || "";
let jobs = [];  // the scene's jobs as last drawn, newest first
const followed = new Set();  // ids of the jobs whose events are followed

function showMessage(text) {
  $("message").textContent = text;
  $("message").hidden = !text;
}

function megabytes(bytes) {
  return `${(bytes / 1e6).toFixed(1)} MB`;
}

// The prior's line: its file, kind, noise sigma (scene units) and where it came from.
function priorText(prior) {
  if (!prior) return "none (training fuses one from depth maps when the scene has them)";
  const parts = [prior.file];
  if (prior.kind) parts.push(prior.kind);
  if (typeof prior.sigma === "number") {
    parts.push(`sigma ${prior.sigma.toPrecision(3)} scene units${prior.sigma_estimated ? " (estimated)" : ""}`);
  } else {
    parts.push("sigma not stated");
  }
  if (prior.source) parts.push(`from ${prior.source}`);
  return parts.join(" · ");
}

function depthText(summary) {
  if (!summary.depth) return "no";
  const frames = summary.depth_frames;
  return frames ? `yes: ${frames.all} frames (${frames.train} training frames)` : "yes";
}

function imageSizeText(summary) {
  const sizes = Object.entries(summary.image_sizes || {});
  if (sizes.length < 2) return `${summary.image_size[0]} x ${summary.image_size[1]} pixels`;
  return sizes.map(([size, n]) => `${size.replace("x", " x ")} (${n} frames)`).join(", ") + " pixels";
}

function drawScene(scene) {
  const s = scene.summary;
  $("scene-name").textContent = scene.name;
  document.title = `VoxNeRF · scene ${scene.name}`;
  const facts = [
    ["Frames", String(s.frames)],
    ["Image size", imageSizeText(s)],
    ["Prior", priorText(s.prior)],
    ["Depth maps", depthText(s)],
    ["Camera models", Object.entries(s.camera_models || {}).map(([m, n]) => `${m}: ${n}`).join(", ") || "–"],
    ["Uploaded", new Date(scene.created_at).toLocaleString()],
    ["Size", megabytes(scene.size_bytes)],
  ];
  if (scene.imported) facts.push(["Imported from", `${scene.imported.format}: ${scene.imported.frames} frames`]);
  $("summary").replaceChildren(...facts.flatMap(([term, value]) => [el("dt", {}, term), el("dd", { data: { fact: term } }, value)]));
  $("splits").tBodies[0].replaceChildren(...Object.entries(s.splits).map(([split, n]) => el("tr", { data: { split } },
    el("th", {}, split), el("td", {}, String(n)))));
  $("warnings").replaceChildren(...(s.warnings || []).map((w) => el("li", {}, w)));
}

function finalPsnr(job) {
  if (!job.metrics) return "–";
  return Object.entries(job.metrics).map(([split, m]) => `${split} ${typeof m.psnr === "number" ? m.psnr.toFixed(2) : "–"}`).join(", ");
}

function drawJobs() {
  $("jobs").tBodies[0].replaceChildren(...jobs.map((job) => el("tr", { data: { jobId: job.id, state: job.state } },
    el("td", {}, el("a", { href: `/static/job.html?id=${job.id}`, title: job.id }, el("code", {}, job.id.slice(0, 8)))),
    el("td", {}, el("span", { className: `state state-${job.state}` }, job.state)),
    el("td", {}, `${Math.round(100 * (job.progress || 0))}%`),
    el("td", {}, new Date(job.created_at).toLocaleString()),
    el("td", { className: "options" }, Object.entries(job.options).map(([k, v]) => `${k}=${JSON.stringify(v)}`).join(" ")),
    el("td", {}, finalPsnr(job)))));
  $("no-jobs").hidden = jobs.length > 0;
}

// Follow a queued or running job's events: each progress and state event carries the whole job.
function follow(job) {
  if (followed.has(job.id) || followed.size >= MAX_FOLLOWED || !(job.state === "queued" || job.state === "running")) return;
  followed.add(job.id);
  followJobEvents(job.id, (type, data) => {
    if (type !== "progress" && type !== "state") return;
    jobs = jobs.map((known) => (known.id === data.id ? data : known));
    drawJobs();
    if (FINAL_STATES.includes(data.state)) followed.delete(data.id);
  }, (message) => showMessage(`Live events of job ${job.id.slice(0, 8)}: ${message} (reconnecting)`));
}

async function refresh() {
  try {
    const [scene, listed] = await Promise.all([
      api(`/scenes/${sceneId}`).then((r) => r.json()),
      api(`/jobs?scene_id=${sceneId}&limit=100`).then((r) => r.json()),
    ]);
    drawScene(scene);
    const current = new Map(jobs.map((job) => [job.id, job]));  // a followed job's events are newer than the list
    jobs = listed.map((job) => (followed.has(job.id) && current.has(job.id) ? current.get(job.id) : job));
    drawJobs();
    jobs.forEach(follow);
    showMessage("");
  } catch (err) {
    showMessage(`Scene ${sceneId}: ${err.message}`);
  }
}

$("scene-id").textContent = sceneId.slice(0, 8);
$("scene-id").title = sceneId;
if (/^[0-9a-f]{32}$/.test(sceneId)) {
  refresh();
  setInterval(refresh, LIST_MS);
} else {
  showMessage("No scene id: open this page from the dashboard.");
}
