// VoxNeRF viewer: look around a trained job. The server renders (POST /render); this page moves the camera,
// draws the scene's cameras over the render and a sparse sample of its prior while the frame of the current view
// is on its way (the stale frame fades), and manages keyframes. A job still training renders from its latest
// checkpoint: the page shows which one ("iteration N, training"), follows the job's live events (GET
// /jobs/{id}/events), and renders the view again when a newer checkpoint has been written.
// No framework and no build step; API access (the token) comes from /static/api.js.
//
// Poses are camera-to-world 4x4 row-major arrays, OpenGL axes (the camera looks along -Z, +Y up), scene units,
// as transforms.json and POST /render take them. A camera is {fl_x, fl_y, cx, cy, width, height} in pixels.
"use strict";

const SMALL_FACTOR = 4;  // the frame rendered while the camera moves is 1/4 of the full size per side
const REST_MS = 200;  // the camera is at rest this long after its last move: render the full frame
const RETRY_MS = 1000, MAX_RETRIES = 3;  // a refused render is asked again after a second, at most 3 times
const RETRY_JOB_MS = 3000;  // the job could not be read: try again after this
const ROTATE_RAD_PER_PX = 0.005;
const FLY_SPEED = 0.35;  // of the scene's extent per second
const MAX_PITCH_COS = 0.985;  // orbiting stops short of looking straight along the scene's up
const NEAR = 1e-3;  // of the scene's extent: nothing nearer the camera is drawn
const VIRIDIS = [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142], [31, 158, 137],
  [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37]];
const KEY_MOVES = { KeyW: [0, 0, -1], KeyS: [0, 0, 1], KeyA: [-1, 0, 0], KeyD: [1, 0, 0], KeyQ: [0, -1, 0], KeyE: [0, 1, 0] };

const $ = (id) => document.getElementById(id);
const jobId = new URLSearchParams(location.search).get("job") || "";

// ------------------------------------------------------------------------------------------- 3-vector maths

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => scale(a, 1 / (norm(a) || 1));

const column = (pose, j) => [pose[0][j], pose[1][j], pose[2][j]];
const position = (pose) => column(pose, 3);
const forwardOf = (pose) => scale(column(pose, 2), -1);

function poseFrom(right, up, back, eye) {
  return [[right[0], up[0], back[0], eye[0]], [right[1], up[1], back[1], eye[1]],
    [right[2], up[2], back[2], eye[2]], [0, 0, 0, 1]];
}

// Rotation of vector v about unit axis k by angle a (Rodrigues).
function rotate(v, k, a) {
  const c = Math.cos(a), s = Math.sin(a);
  return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
}

// The pose turned by angle a about the axis k through pivot (its axes re-orthonormalised).
function turn(pose, k, a, pivot) {
  const eye = add(pivot, rotate(sub(position(pose), pivot), k, a));
  const back = unit(rotate(column(pose, 2), k, a));
  const right = unit(cross(rotate(column(pose, 1), k, a), back));
  return poseFrom(right, cross(back, right), back, eye);
}

function translate(pose, offset) {
  return poseFrom(column(pose, 0), column(pose, 1), column(pose, 2), add(position(pose), offset));
}

// Camera coordinates (OpenGL) of world point p seen from pose.
function toCamera(pose, p) {
  const d = sub(p, position(pose));
  return [dot(column(pose, 0), d), dot(column(pose, 1), d), dot(column(pose, 2), d)];
}

// Pixel of camera-space point q through camera (scaled by k to the canvas), or null behind the near plane.
function project(camera, k, q, near) {
  if (-q[2] < near) return null;
  return [k * (camera.cx + camera.fl_x * q[0] / -q[2]), k * (camera.cy - camera.fl_y * q[1] / -q[2])];
}

function scaledCamera(camera, factor) {
  const width = Math.max(1, Math.round(camera.width / factor)), height = Math.max(1, Math.round(camera.height / factor));
  const sx = width / camera.width, sy = height / camera.height;
  return { fl_x: camera.fl_x * sx, fl_y: camera.fl_y * sy, cx: camera.cx * sx, cy: camera.cy * sy, width, height };
}

const cameraOf = (frame) => ({ fl_x: frame.fl_x, fl_y: frame.fl_y, cx: frame.cx, cy: frame.cy, width: frame.width, height: frame.height });
const poseKey = (pose) => JSON.stringify(pose);

// ------------------------------------------------------------------------------------------- state

const view = {
  pose: null, camera: null, mode: "rgb", moveMode: "orbit", orbitDistance: 1,
  up: [0, 0, 1], extent: 1, centre: [0, 0, 0], units: "scene units", depthUnitScale: 0.001,
  snapped: null,  // the camera frame the view was snapped to, until it moves
};
const scene = { frames: [], prior: null };
const frames = {  // progressive rendering: at most one request in flight
  inflight: null, shownKey: null, shownQuality: null, lastMoveAt: 0, resting: true, restTimer: 0, seq: 0, log: [],
  failures: 0, renderError: false,
  shownIteration: null,  // the training iteration of the checkpoint that rendered the frame on screen
  outdated: false,  // a newer checkpoint than the shown frame's was written: render the view again
  outdatedAfter: 0,  // ... by a request sent after this one (seq): one already in flight may show the older one
};
const job = { state: null, checkpointIteration: null, refreshedFor: null, events: null };  // GET /jobs/{id}, events
const path = { keyframes: [], frames: null, cameraPath: null, playing: 0 };
const currentKey = () => `${view.mode}|${poseKey(view.pose)}|${JSON.stringify(view.camera)}`;  // what a frame shows
window.viewerState = { view, frames, path, job, currentKey };  // read by the browser test and benchmarks/viewer_latency.py

function showMessage(text, kind = "error") {
  const box = $("message");
  box.textContent = text;
  box.className = kind === "info" ? "message info" : "message";
  box.hidden = !text;
}

// ------------------------------------------------------------------------------------------- rendering

// A frame's quality: "small" (1/SMALL_FACTOR of the size per side) and "full" (full size) with one ray per pixel,
// "final" full size and antialiased (five rays per pixel, POST /render's default).
function requestBody(quality) {
  const camera = quality === "small" ? scaledCamera(view.camera, SMALL_FACTOR) : view.camera;
  return {
    job_id: jobId, transform_matrix: view.pose, format: "png", outputs: [view.mode],
    width: camera.width, height: camera.height, fl_x: camera.fl_x, fl_y: camera.fl_y, cx: camera.cx, cy: camera.cy,
    ...(quality === "final" ? {} : { antialias: false }),
  };
}

// The view changed: abort a full-size render in flight (superseded), render the newest pose small now if nothing
// is in flight, and full size once the camera rests, then antialiased.
function viewChanged() {
  frames.lastMoveAt = performance.now();
  frames.failures = 0;
  frames.resting = false;
  if (frames.inflight && frames.inflight.quality !== "small") frames.inflight.controller.abort();
  if (view.snapped && poseKey(view.pose) !== poseKey(view.snapped.transform_matrix)) hideGroundTruth();
  $("render").classList.add("stale");
  drawOverlay();
  pump();
  clearTimeout(frames.restTimer);
  frames.restTimer = setTimeout(() => { frames.resting = true; pump(); }, REST_MS);
}

// The next frame the view needs, or null: small while the camera moves; once it rests, full size, then final
// (colour only: depth and opacity are the centre ray's either way).
function wantedFrame() {
  const key = currentKey();
  if (!frames.resting) return frames.shownKey === key ? null : { key, quality: "small" };
  if (frames.outdated || frames.shownKey !== key || frames.shownQuality === "small") return { key, quality: "full" };
  return frames.shownQuality === "full" && view.mode === "rgb" ? { key, quality: "final" } : null;
}

async function pump() {
  if (frames.inflight || !view.pose) return;
  const wanted = wantedFrame();
  if (!wanted) return;
  const request = { ...wanted, controller: new AbortController(), seq: ++frames.seq, requestedAt: performance.now(),
    movedAt: frames.lastMoveAt, mode: view.mode, body: requestBody(wanted.quality) };
  frames.inflight = request;
  try {
    const response = await api("/render", {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(request.body),
      signal: request.controller.signal,
    });
    const source = { iteration: response.headers.get("X-VoxNeRF-Iteration"),
      state: response.headers.get("X-VoxNeRF-Job-State") || "" };
    await showFrame(request, await response.arrayBuffer(), source);
  } catch (err) {
    if (err.name !== "AbortError") {  // e.g. 429 (renders busy): ask again a few times, then wait for a move
      showMessage(`Render: ${err.message}`);  // a job without a checkpoint yet: renders when one is written
      frames.renderError = true;
      frames.inflight = null;
      frames.failures += 1;
      if (frames.failures <= MAX_RETRIES) setTimeout(pump, RETRY_MS);
      return;
    }
  }
  frames.inflight = null;
  pump();
}

async function showFrame(request, buffer, source) {
  const canvas = $("render");
  if (request.mode === "depth") {
    const depth = await decodePng16(buffer);
    const image = colourDepth(depth, view.depthUnitScale);
    canvas.width = depth.width;
    canvas.height = depth.height;
    canvas.getContext("2d").putImageData(image.pixels, 0, 0);
    setColourBar(image.range, true);
  } else {
    const bitmap = await createImageBitmap(new Blob([buffer], { type: "image/png" }),
      { colorSpaceConversion: "none", premultiplyAlpha: "none" });
    canvas.width = bitmap.width;
    canvas.height = bitmap.height;
    canvas.getContext("2d").drawImage(bitmap, 0, 0);
    bitmap.close();
    setColourBar(request.mode === "opacity" ? [0, 1] : null, false);
  }
  frames.failures = 0;
  if (frames.renderError) showMessage("");
  frames.renderError = false;
  frames.shownKey = request.key;
  frames.shownQuality = request.quality;
  frames.shownBody = request.body;
  if (request.quality !== "small" && request.seq > frames.outdatedAfter) frames.outdated = false;
  showCheckpoint(source);
  canvas.classList.toggle("stale", request.key !== currentKey());
  canvas.classList.remove("empty");
  drawOverlay();
  Object.assign(canvas.dataset, { seq: String(request.seq), quality: request.quality, mode: request.mode });
  const shownAt = performance.now();
  frames.log.push({ seq: request.seq, quality: request.quality, key: request.key, movedAt: request.movedAt,
    requestedAt: request.requestedAt, shownAt });
  if (frames.log.length > 500) frames.log.shift();
  $("status").textContent = `${request.quality} frame ${canvas.width}x${canvas.height} in ` +
    `${Math.round(shownAt - request.requestedAt)} ms`;
}

// Which checkpoint rendered the frame on screen (the response's X-VoxNeRF-Iteration and X-VoxNeRF-Job-State).
function showCheckpoint(source) {
  const box = $("checkpoint"), iteration = source.iteration === null ? null : Number(source.iteration);
  frames.shownIteration = iteration;
  const how = { running: "training", cancelled: "cancelled: its last checkpoint",
    failed: "failed: its last good checkpoint" }[source.state];
  box.textContent = iteration === null ? "" : `iteration ${iteration}${how ? `, ${how}` : ""}`;
  box.hidden = iteration === null;
  Object.assign(box.dataset, { iteration: iteration === null ? "" : String(iteration), state: source.state });
}

// ------------------------------------------------------------------------------------------- a job in training

// Follow the job while it trains: the job once, then its live events (api.js followJobEvents; each progress and
// state event carries the whole job) until its final state. When the job names a checkpoint newer than the shown
// frame's (or its first), render the current view again: so the job's last checkpoint is shown once it has ended.
async function watchJob() {
  if (job.events) job.events.stop();
  job.events = null;
  let row;
  try {
    row = await (await api(`/jobs/${jobId}`)).json();
  } catch (err) {
    setTimeout(watchJob, RETRY_JOB_MS);
    return;
  }
  jobChanged(row);
  if (FINAL_STATES.includes(row.state)) return;
  job.events = followJobEvents(jobId, (type, data) => {
    if (type === "progress" || type === "state") jobChanged(data);
  });
}

function jobChanged(row) {
  job.state = row.state;
  job.checkpointIteration = row.checkpoint_iteration;
  $("job-label").textContent = `job ${jobId.slice(0, 8)} · ${row.state}`;
  const newer = viewable(row) && (row.checkpoint_iteration !== job.refreshedFor || frames.renderError)
    && (frames.shownIteration === null || row.checkpoint_iteration > frames.shownIteration);
  if (!newer || !view.pose) return;
  job.refreshedFor = row.checkpoint_iteration;  // once per checkpoint (unless its render failed), whatever
  // iteration the worker answers (with an object store a render worker may hold an older upload for a while)
  frames.outdated = true;
  frames.outdatedAfter = frames.seq;
  frames.failures = 0;
  pump();
}

// ------------------------------------------------------------------------------------------- depth and colour

// The 16-bit gray PNG that POST /render answers for depth: {width, height, values: Uint16Array}.
async function decodePng16(buffer) {
  const bytes = new Uint8Array(buffer), data = new DataView(buffer);
  const signature = [137, 80, 78, 71, 13, 10, 26, 10];
  if (signature.some((b, i) => bytes[i] !== b)) throw new Error("the depth render is not a PNG");
  let offset = 8, header = null;
  const chunks = [];
  while (offset + 8 <= bytes.length) {
    const length = data.getUint32(offset), type = String.fromCharCode(...bytes.subarray(offset + 4, offset + 8));
    const body = bytes.subarray(offset + 8, offset + 8 + length);
    if (type === "IHDR") header = { width: data.getUint32(offset + 8), height: data.getUint32(offset + 12), bits: body[8], colour: body[9], interlace: body[12] };
    if (type === "IDAT") chunks.push(body);
    if (type === "IEND") break;
    offset += 12 + length;
  }
  if (!header || header.bits !== 16 || header.colour !== 0 || header.interlace !== 0) {
    throw new Error("the depth render is not a 16-bit gray, non-interlaced PNG");
  }
  const stream = new Blob(chunks).stream().pipeThrough(new DecompressionStream("deflate"));
  const raw = new Uint8Array(await new Response(stream).arrayBuffer());
  return { width: header.width, height: header.height, values: unfilter(raw, header.width, header.height, 2) };
}

// PNG scanline filters undone (None, Sub, Up, Average, Paeth); bpp bytes per pixel; big-endian 16-bit samples.
function unfilter(raw, width, height, bpp) {
  const stride = width * bpp, out = new Uint8Array(stride * height);
  for (let y = 0; y < height; y += 1) {
    const filter = raw[y * (stride + 1)], src = y * (stride + 1) + 1, row = y * stride, prev = row - stride;
    for (let x = 0; x < stride; x += 1) {
      const a = x >= bpp ? out[row + x - bpp] : 0, b = y > 0 ? out[prev + x] : 0;
      const c = x >= bpp && y > 0 ? out[prev + x - bpp] : 0;
      let predictor = 0;
      if (filter === 1) predictor = a;
      else if (filter === 2) predictor = b;
      else if (filter === 3) predictor = (a + b) >> 1;
      else if (filter === 4) {
        const p = a + b - c, pa = Math.abs(p - a), pb = Math.abs(p - b), pc = Math.abs(p - c);
        predictor = pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
      }
      out[row + x] = (raw[src + x] + predictor) & 255;
    }
  }
  const values = new Uint16Array(width * height);
  for (let i = 0; i < values.length; i += 1) values[i] = (out[2 * i] << 8) | out[2 * i + 1];
  return values;
}

function viridis(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1), i = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const f = x - i;
  return VIRIDIS[i].map((v, c) => Math.round(v + f * (VIRIDIS[i + 1][c] - v)));
}

// Depth coloured over its valid range (0 and 65535 are "no depth": black); the range in scene units.
function colourDepth(depth, unitScale) {
  let low = Infinity, high = -Infinity;
  for (const v of depth.values) if (v > 0 && v < 65535) { low = Math.min(low, v); high = Math.max(high, v); }
  if (!Number.isFinite(low)) { low = 0; high = 1; }
  const span = Math.max(1, high - low), pixels = new ImageData(depth.width, depth.height);
  depth.values.forEach((v, i) => {
    const rgb = v > 0 && v < 65535 ? viridis((v - low) / span) : [0, 0, 0];
    pixels.data.set([...rgb, 255], 4 * i);
  });
  return { pixels, range: [low * unitScale, high * unitScale] };
}

function setColourBar(range, isDepth) {
  $("colorbar-box").hidden = !range;
  if (!range) return;
  const bar = $("colorbar"), context = bar.getContext("2d");
  for (let x = 0; x < bar.width; x += 1) {
    const t = x / (bar.width - 1), rgb = isDepth ? viridis(t) : [255 * t, 255 * t, 255 * t];
    context.fillStyle = `rgb(${rgb.join(",")})`;
    context.fillRect(x, 0, 1, bar.height);
  }
  const digits = isDepth ? 2 : 1;
  $("bar-min").textContent = range[0].toFixed(digits);
  $("bar-max").textContent = range[1].toFixed(digits);
  $("bar-units").textContent = isDepth ? `depth, ${view.units === "metres" ? "m" : "scene units"}` : "opacity";
}

// ------------------------------------------------------------------------------------------- overlay

function overlayContext() {
  const canvas = $("overlay"), ratio = window.devicePixelRatio || 1;
  const width = Math.round(canvas.clientWidth * ratio), height = Math.round(canvas.clientHeight * ratio);
  if (canvas.width !== width || canvas.height !== height) Object.assign(canvas, { width, height });
  const context = canvas.getContext("2d");
  context.clearRect(0, 0, width, height);
  return { context, k: width / view.camera.width };
}

function drawSegment(context, k, a, b, near) {
  let qa = toCamera(view.pose, a), qb = toCamera(view.pose, b);
  if (-qa[2] < near && -qb[2] < near) return;
  if (-qa[2] < near || -qb[2] < near) {  // clip at the near plane
    const t = (-near - qa[2]) / (qb[2] - qa[2]), cut = add(qa, scale(sub(qb, qa), t));
    if (-qa[2] < near) qa = cut; else qb = cut;
  }
  const pa = project(view.camera, k, qa, near * 0.999), pb = project(view.camera, k, qb, near * 0.999);
  if (!pa || !pb) return;
  context.moveTo(pa[0], pa[1]);
  context.lineTo(pb[0], pb[1]);
}

function frustumSegments(pose, camera, size) {
  const apex = position(pose);
  const corners = [[0, 0], [camera.width, 0], [camera.width, camera.height], [0, camera.height]].map(([u, v]) => {
    const local = [(u - camera.cx) / camera.fl_x, -(v - camera.cy) / camera.fl_y, -1];
    return add(apex, scale(add(add(scale(column(pose, 0), local[0]), scale(column(pose, 1), local[1])),
      scale(column(pose, 2), local[2])), size));
  });
  return corners.flatMap((corner, i) => [[apex, corner], [corner, corners[(i + 1) % 4]]]);
}

function strokeFrusta(context, k, items, colour, width) {
  const near = NEAR * view.extent;
  context.beginPath();
  for (const [pose, camera] of items) {
    for (const [a, b] of frustumSegments(pose, camera, 0.03 * view.extent)) drawSegment(context, k, a, b, near);
  }
  context.strokeStyle = colour;
  context.lineWidth = width;
  context.stroke();
}

function drawOverlay() {
  if (!view.pose) return;
  const { context, k } = overlayContext();
  const near = NEAR * view.extent;
  const waiting = $("render").matches(".stale, .empty");  // the prior shows until the current frame is drawn
  if (scene.prior && $("show-prior").checked && waiting) {
    const { points, colors } = scene.prior;
    for (let i = 0; i < points.length; i += 3) {
      const p = project(view.camera, k, toCamera(view.pose, [points[i], points[i + 1], points[i + 2]]), near);
      if (!p) continue;
      context.fillStyle = colors ? `rgb(${255 * colors[i]},${255 * colors[i + 1]},${255 * colors[i + 2]})` : "#9fb3c8";
      context.fillRect(p[0] - 1, p[1] - 1, 2, 2);
    }
  }
  if ($("show-frusta").checked) {
    const isTrain = (f) => f.splits.includes("train");
    strokeFrusta(context, k, scene.frames.filter(isTrain).map((f) => [f.transform_matrix, cameraOf(f)]), "#4f8ff7", 1);
    strokeFrusta(context, k, scene.frames.filter((f) => !isTrain(f)).map((f) => [f.transform_matrix, cameraOf(f)]), "#f0a030", 1.5);
  }
  strokeFrusta(context, k, path.keyframes.map((key) => [key.pose, key.camera]), "#3ccf6e", 2);
  if (path.frames) {
    context.beginPath();
    for (let i = 1; i < path.frames.length; i += 1) {
      drawSegment(context, k, position(path.frames[i - 1].transform_matrix), position(path.frames[i].transform_matrix), near);
    }
    context.strokeStyle = "#e052c8";
    context.lineWidth = 2;
    context.stroke();
  }
  drawScaleBar(k);
}

// A bar of a round length (1, 2 or 5 times a power of ten) at the orbit distance, about 100 px long.
function drawScaleBar(k) {
  const pixelsPerUnit = (k * view.camera.fl_x) / view.orbitDistance / (window.devicePixelRatio || 1);
  const target = 100 / pixelsPerUnit, power = 10 ** Math.floor(Math.log10(target));
  const length = [5, 2, 1].map((m) => m * power).find((l) => l <= target) || power;
  const bar = $("scale-bar");
  bar.hidden = !Number.isFinite(pixelsPerUnit);
  bar.style.width = `${Math.round(length * pixelsPerUnit)}px`;
  const unitText = view.units === "metres" ? "m" : "scene units";
  $("scale-label").textContent = `${+length.toPrecision(3)} ${unitText} at ${view.orbitDistance.toPrecision(3)} ${unitText}`;
}

// ------------------------------------------------------------------------------------------- moving

function setPose(pose) {
  view.pose = pose;
  viewChanged();
}

function orbitOrLook(dx, dy) {
  const pivot = view.moveMode === "orbit" ? add(position(view.pose), scale(forwardOf(view.pose), view.orbitDistance)) : position(view.pose);
  let pose = turn(view.pose, view.up, -dx * ROTATE_RAD_PER_PX, pivot);
  const pitched = turn(pose, unit(column(pose, 0)), -dy * ROTATE_RAD_PER_PX, pivot);
  if (Math.abs(dot(forwardOf(pitched), view.up)) < MAX_PITCH_COS) pose = pitched;
  setPose(pose);
}

function pan(dx, dy) {
  const perPixel = view.orbitDistance / view.camera.fl_x * (view.camera.width / $("stage").clientWidth);
  setPose(translate(view.pose, add(scale(column(view.pose, 0), -dx * perPixel), scale(column(view.pose, 1), dy * perPixel))));
}

function dolly(amount) {
  const step = view.orbitDistance * amount;
  if (view.moveMode === "orbit") view.orbitDistance = Math.max(1e-3 * view.extent, view.orbitDistance - step);
  setPose(translate(view.pose, scale(forwardOf(view.pose), step)));
}

const pointers = new Map();  // pointerId -> last [x, y]

function onPointerDown(event) {
  $("stage").setPointerCapture(event.pointerId);
  $("stage").classList.add("dragging");
  pointers.set(event.pointerId, [event.clientX, event.clientY, event.button === 2 || event.shiftKey]);
}

function onPointerMove(event) {
  const last = pointers.get(event.pointerId);
  if (!last) return;
  const dx = event.clientX - last[0], dy = event.clientY - last[1];
  if (pointers.size === 1) {
    if (last[2]) pan(dx, dy); else orbitOrLook(dx, dy);
  } else if (pointers.size === 2) {  // two fingers: pinch dollies, their midpoint pans
    const [other] = [...pointers.entries()].filter(([id]) => id !== event.pointerId).map(([, p]) => p);
    const before = Math.hypot(last[0] - other[0], last[1] - other[1]);
    const after = Math.hypot(event.clientX - other[0], event.clientY - other[1]);
    if (before > 0) dolly((after - before) / before);
    pan(dx / 2, dy / 2);
  }
  pointers.set(event.pointerId, [event.clientX, event.clientY, last[2]]);
}

function onPointerUp(event) {
  pointers.delete(event.pointerId);
  if (!pointers.size) $("stage").classList.remove("dragging");
}

const keysDown = new Set();
let flyFrame = 0, flyLast = 0;

function flyStep(now) {
  const seconds = Math.min(0.1, Math.max(0, now - flyLast) / 1000); // a frame's time may precede the key's
  flyLast = now;
  let move = [0, 0, 0];
  for (const code of keysDown) move = add(move, KEY_MOVES[code]);
  if (norm(move) > 0) {
    const step = FLY_SPEED * view.extent * seconds;
    const world = add(add(scale(column(view.pose, 0), move[0]), scale(view.up, move[1])), scale(column(view.pose, 2), move[2]));
    setPose(translate(view.pose, scale(unit(world), step)));
  }
  flyFrame = keysDown.size ? requestAnimationFrame(flyStep) : 0;
}

function onKey(event) {
  if (!(event.code in KEY_MOVES) || event.target.matches("input, select, textarea")) return;
  event.preventDefault();
  if (event.type === "keydown") keysDown.add(event.code); else keysDown.delete(event.code);
  if (keysDown.size && !flyFrame) {
    flyLast = performance.now();
    flyFrame = requestAnimationFrame(flyStep);
  }
}

// ------------------------------------------------------------------------------------------- cameras

// The stage takes the camera's aspect ratio, at most 78% of the window's height (the canvases fill it exactly,
// so the overlay's pixels line up with the render's).
function fitStage(width, height) {
  const stage = $("stage");
  stage.style.aspectRatio = `${width} / ${height}`;
  stage.style.maxWidth = `calc(78vh * ${width / height})`;
}

function snapTo(frame) {
  stopPlaying();
  view.camera = cameraOf(frame);
  view.snapped = frame;
  view.orbitDistance = Math.max(0.1 * view.extent, dot(sub(view.centre, position(frame.transform_matrix)), forwardOf(frame.transform_matrix)));
  fitStage(frame.width, frame.height);
  $("camera-select").value = String(frame.index);
  setPose(frame.transform_matrix);
  showGroundTruth(frame);
}

async function showGroundTruth(frame) {
  const evaluation = frame.splits.filter((s) => s !== "train");
  if (!evaluation.length) { hideGroundTruth(); return; }
  try {
    const url = await apiBlobUrl(frame.image_url);
    if (view.snapped !== frame) { URL.revokeObjectURL(url); return; }
    const image = $("gt-image");
    if (image.src) URL.revokeObjectURL(image.src);
    image.src = url;
    $("gt-caption").textContent = `ground truth · ${evaluation.join(", ")} · ${frame.name}`;
    $("gt-figure").hidden = false;
  } catch (err) {
    showMessage(`Ground truth of ${frame.name}: ${err.message}`);
  }
}

function hideGroundTruth() {
  view.snapped = null;
  $("gt-figure").hidden = true;
}

function cameraLabel(frame) {
  return `${frame.index}: ${frame.splits.join("+") || "no split"} · ${frame.name}`;
}

function stepCamera(delta) {
  const count = scene.frames.length, current = Number($("camera-select").value);
  snapTo(scene.frames[(current + delta + count) % count]);
}

// ------------------------------------------------------------------------------------------- keyframes

function renderKeyframes() {
  $("keyframes").replaceChildren(...path.keyframes.map((key, i) => {
    const item = document.createElement("li");
    const where = position(key.pose).map((v) => v.toFixed(2)).join(", ");
    item.append(`(${where})`);
    const go = Object.assign(document.createElement("button"), { type: "button", className: "secondary", textContent: "go" });
    go.addEventListener("click", () => { view.camera = key.camera; setPose(key.pose); });
    const remove = Object.assign(document.createElement("button"), { type: "button", className: "secondary", textContent: "✕" });
    remove.addEventListener("click", () => { path.keyframes.splice(i, 1); clearPath(); renderKeyframes(); });
    item.append(go, remove);
    return item;
  }));
  drawOverlay();
}

function clearPath() {
  path.frames = null;
  path.cameraPath = null;
}

// The video's camera: the view's, with even sizes (H.264 needs them).
function videoCamera() {
  const c = view.camera, width = c.width - (c.width % 2) || 2, height = c.height - (c.height % 2) || 2;
  return { ...c, width, height };
}

async function postPath(body) {
  const made = await (await api("/camera-paths", {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
  })).json();
  path.frames = made.frames;
  path.cameraPath = made.camera_path;
  path.size = [made.width, made.height];
  path.fps = made.fps;
  drawOverlay();
  return made;
}

async function makePath() {
  if (path.cameraPath) return path;
  if (path.keyframes.length < 2) throw new Error("add at least two keyframes first");
  const camera = videoCamera();
  await postPath({ keyframes: path.keyframes.map((key) => key.pose), frames: Number($("path-frames").value),
    fps: Number($("path-fps").value), ...camera });
  return path;
}

function stopPlaying() {
  cancelAnimationFrame(path.playing);
  path.playing = 0;
}

async function previewPath() {
  try {
    await makePath();
  } catch (err) {
    showMessage(`Path: ${err.message}`);
    return;
  }
  stopPlaying();
  const [width, height] = path.size;
  let started = null; // the first frame's timestamp: a frame's time may precede the click's performance.now()
  const step = (now) => {
    started ??= now;
    const i = Math.min(path.frames.length - 1, Math.floor(((now - started) / 1000) * path.fps));
    const frame = path.frames[i];
    view.camera = { fl_x: frame.fl_x, fl_y: frame.fl_y, cx: frame.cx, cy: frame.cy, width, height };
    setPose(frame.transform_matrix);
    path.playing = i < path.frames.length - 1 ? requestAnimationFrame(step) : 0;
  };
  path.playing = requestAnimationFrame(step);
}

async function startVideo() {
  try {
    await makePath();
    const output = await (await api(`/jobs/${jobId}/videos`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ camera_path: path.cameraPath }),
    })).json();
    showMessage(`Video queued (output ${output.id.slice(0, 8)}, ${path.frames.length} frames).`, "info");
    followVideo(output);
  } catch (err) {
    showMessage(`Video refused: ${err.message}`);
  }
}

async function followVideo(output) {
  const item = document.createElement("li");
  item.dataset.outputId = output.id;
  $("videos").prepend(item);
  for (;;) {
    item.textContent = `video ${output.id.slice(0, 8)}: ${output.state} ${Math.round(100 * (output.progress || 0))}%`;
    item.dataset.state = output.state;
    if (!["queued", "running"].includes(output.state)) break;
    await new Promise((resolve) => setTimeout(resolve, 1000));
    try {
      output = await (await api(`/outputs/${output.id}`)).json();
    } catch (err) {
      item.textContent = `video ${output.id.slice(0, 8)}: ${err.message}`;
      return;
    }
  }
  if (output.state === "succeeded") {
    const video = Object.assign(document.createElement("video"), { controls: true, muted: true, loop: true });
    video.src = await apiBlobUrl(output.file_url);
    item.append(video);
  }
}

async function exportPath() {
  try {
    await makePath();
  } catch (err) {
    showMessage(`Export: ${err.message}`);
    return;
  }
  const keys = path.keyframes.map((key) => ({ camera_to_world: key.pose.flat(), ...key.camera }));
  const json = JSON.stringify({ ...path.cameraPath, voxnerf_keyframes: keys }, null, 1);
  const link = Object.assign(document.createElement("a"), {
    href: URL.createObjectURL(new Blob([json], { type: "application/json" })), download: `camera_path-${jobId.slice(0, 8)}.json`,
  });
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10_000);
}

async function importPath(file) {
  try {
    const data = JSON.parse(await file.text());
    const keys = Array.isArray(data.voxnerf_keyframes) ? data.voxnerf_keyframes : [];
    const { voxnerf_keyframes: _ignored, ...cameraPath } = data;
    await postPath({ camera_path: cameraPath });
    path.keyframes = keys.map((key) => ({
      pose: [0, 1, 2, 3].map((r) => key.camera_to_world.slice(4 * r, 4 * r + 4)), camera: cameraOf(key),
    }));
    renderKeyframes();
    showMessage(`Imported a path of ${path.frames.length} frames from ${file.name}.`, "info");
  } catch (err) {
    showMessage(`Import of ${file.name}: ${err.message}`);
  }
}

// ------------------------------------------------------------------------------------------- start

function sceneGeometry() {
  const positions = scene.frames.map((f) => position(f.transform_matrix));
  const points = [...positions];
  if (scene.prior) for (let i = 0; i < scene.prior.points.length; i += 3) points.push(scene.prior.points.slice(i, i + 3));
  const low = [0, 1, 2].map((a) => Math.min(...points.map((p) => p[a])));
  const high = [0, 1, 2].map((a) => Math.max(...points.map((p) => p[a])));
  view.extent = Math.max(1e-6, norm(sub(high, low)));
  const mean = (list) => scale(list.reduce(add, [0, 0, 0]), 1 / list.length);
  view.centre = scene.prior ? mean(points.slice(positions.length)) : mean(positions);
  view.up = unit(scene.frames.map((f) => column(f.transform_matrix, 1)).reduce(add, [0, 0, 0]));
}

function bindControls() {
  const stage = $("stage");
  stage.addEventListener("pointerdown", onPointerDown);
  stage.addEventListener("pointermove", onPointerMove);
  stage.addEventListener("pointerup", onPointerUp);
  stage.addEventListener("pointercancel", onPointerUp);
  stage.addEventListener("contextmenu", (event) => event.preventDefault());
  stage.addEventListener("wheel", (event) => { event.preventDefault(); dolly(-Math.sign(event.deltaY) * 0.1); }, { passive: false });
  document.addEventListener("keydown", onKey);
  document.addEventListener("keyup", onKey);
  window.addEventListener("resize", drawOverlay);
  for (const radio of document.querySelectorAll('input[name="output"]')) {
    radio.addEventListener("change", () => { view.mode = radio.value; viewChanged(); });
  }
  $("move-mode").addEventListener("change", (event) => { view.moveMode = event.target.value; });
  $("show-frusta").addEventListener("change", drawOverlay);
  $("show-prior").addEventListener("change", drawOverlay);
  $("reset-view").addEventListener("click", () => snapTo(scene.frames[0]));
  $("camera-snap").addEventListener("click", () => snapTo(scene.frames[Number($("camera-select").value)]));
  $("camera-prev").addEventListener("click", () => stepCamera(-1));
  $("camera-next").addEventListener("click", () => stepCamera(1));
  $("key-add").addEventListener("click", () => {
    path.keyframes.push({ pose: view.pose, camera: view.camera });
    clearPath();
    renderKeyframes();
  });
  $("key-clear").addEventListener("click", () => { path.keyframes = []; clearPath(); stopPlaying(); renderKeyframes(); });
  for (const id of ["path-frames", "path-fps"]) $(id).addEventListener("change", clearPath);
  $("path-preview").addEventListener("click", previewPath);
  $("path-video").addEventListener("click", startVideo);
  $("path-export").addEventListener("click", exportPath);
  $("path-import").addEventListener("change", (event) => { if (event.target.files[0]) importPath(event.target.files[0]); event.target.value = ""; });
  $("token-form").addEventListener("submit", (event) => {
    event.preventDefault();
    saveToken($("token").value.trim());
    showMessage("");
    start();
  });
}

async function start() {
  if (!/^[0-9a-f]{32}$/.test(jobId)) {
    showMessage("No job to view: open the viewer from a job's row on the dashboard (viewer.html?job=<job id>).");
    return;
  }
  $("job-label").textContent = `job ${jobId.slice(0, 8)}`;
  try {
    const cameras = await (await api(`/jobs/${jobId}/cameras`)).json();
    scene.frames = cameras.frames;
    view.units = cameras.units;
    view.depthUnitScale = cameras.depth_unit_scale;
    const response = await api(`/jobs/${jobId}/prior-preview`).catch(() => null);  // a scene may have no prior
    scene.prior = response ? await response.json() : null;
  } catch (err) {
    showMessage(err.message);
    return;
  }
  sceneGeometry();
  $("units").textContent = view.units === "metres"
    ? "Scene units are metres (the scan has sensor depth)."
    : "Scene units: the poses' own (no sensor depth says they are metres).";
  $("camera-select").replaceChildren(...scene.frames.map((f) => new Option(cameraLabel(f), String(f.index))));
  $("render").classList.add("empty");
  snapTo(scene.frames[0]);
  watchJob();
}

$("token").value = savedToken();
bindControls();
start();
