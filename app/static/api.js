// VoxNeRF pages' shared REST access (a classic script: load it before the page's own script). Every request
// carries the API token saved in localStorage (if any) as "Authorization: Bearer <token>"; the dashboard's
// header form saves it. Files behind the token (renders, images, downloads) become blob: URLs, since an
// <img>, <video> or link cannot send the header. A job's live events (followJobEvents) are read the same way:
// EventSource cannot send the header either. Also the pages' one DOM helper, `el`.
"use strict";

const TOKEN_KEY = "voxnerf.token";

function savedToken() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

// Save the token ("" forgets it).
function saveToken(token) {
  if (token) localStorage.setItem(TOKEN_KEY, token); else localStorage.removeItem(TOKEN_KEY);
}

// FastAPI's error body as one line: its detail string, or each validation error's field and message.
function detailText(body, status) {
  const detail = body && body.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => `${(d.loc || []).slice(1).join(".") || "body"}: ${d.msg}`).join("; ");
  }
  return `HTTP ${status}`;
}

// fetch(path) with the token; the response when it is ok, else an Error with the server's one-line detail.
// A 401 to a request sent before the token was saved (a poll in flight while the user pressed Save) is sent
// again once with the saved token. On 401 the page's token field (id "token"), when it has one, takes the focus.
async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const token = savedToken();
  if (token) headers.set("Authorization", `Bearer ${token}`);
  const response = await fetch(path, { ...options, headers });
  if (response.ok) return response;
  if (response.status === 401 && savedToken() !== token && !options.resentForToken) {
    return api(path, { ...options, resentForToken: true });
  }
  let body = null;
  try {
    body = await response.json();
  } catch (_) {
    body = null;
  }
  if (response.status === 401) {
    const field = document.getElementById("token");
    if (field) {
      field.focus();
      throw new Error("This server needs an API token: enter it above and press Save.");
    }
    throw new Error("This server needs an API token: enter it on the dashboard (/) and press Save.");
  }
  throw new Error(detailText(body, response.status));
}

// A blob: URL of what GET path answers (downloaded with the token); the caller revokes it when done.
async function apiBlobUrl(path) {
  const blob = await (await api(path)).blob();
  return URL.createObjectURL(blob);
}

// Whether the viewer can render `job` (a JobOut), as POST /render decides (app.core.outputs.render_source): a
// succeeded job, or a running, cancelled or failed one that has written a checkpoint (its latest or last one).
function viewable(job) {
  return job.state === "succeeded"
    || (["running", "cancelled", "failed"].includes(job.state) && job.checkpoint_iteration !== null
      && job.checkpoint_iteration !== undefined);
}

// An element with properties (dataset entries under `data`) and children (strings become text).
function el(tag, props = {}, ...children) {
  const { data, ...rest } = props;
  const node = Object.assign(document.createElement(tag), rest);
  for (const [key, value] of Object.entries(data || {})) node.dataset[key] = value;
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

// ------------------------------------------------------------------------------------------- live events

const FINAL_STATES = ["succeeded", "failed", "cancelled"];
const EVENTS_RECONNECT_MS = 3000;  // wait before reconnecting after a dropped stream or a refusal

// Parse a text/event-stream body (a ReadableStream of bytes) as the Server-Sent Events format says: "field: value"
// lines, an event dispatched at each blank line, ":" lines are comments (keep-alives). Calls onEvent({ id, type,
// data }) with data as the text of its data lines (joined by newlines) for each event; resolves when the body ends.
async function readEventStream(body, onEvent) {
  const reader = body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  let event = { id: null, type: "message", data: [] };
  const line = (text) => {
    if (text === "") {
      if (event.data.length) onEvent({ id: event.id, type: event.type, data: event.data.join("\n") });
      event = { id: null, type: "message", data: [] };
      return;
    }
    if (text.startsWith(":")) return;
    const colon = text.indexOf(":");
    const field = colon < 0 ? text : text.slice(0, colon);
    const value = colon < 0 ? "" : text.slice(colon + 1).replace(/^ /, "");
    if (field === "data") event.data.push(value);
    else if (field === "event") event.type = value;
    else if (field === "id") event.id = value;
  };
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += value;
    const lines = buffer.split(/\r\n|\r|\n/);
    buffer = lines.pop();
    lines.forEach(line);
  }
}

// Follow job jobId's live events (GET /jobs/{id}/events) with the saved token: onEvent(type, data, id) for each
// (type "progress" or "state": data is the job, as GET /jobs/{id} returns it; "stage": the stage record;
// "evaluation": the history point). A dropped stream is reopened with Last-Event-ID, so no event comes twice; it
// ends after the job's final state event, on a 404 (the job is gone), or when the returned object's stop() is
// called. onError(message), when given, hears why a stream was refused or dropped before it is reopened.
function followJobEvents(jobId, onEvent, onError = () => {}) {
  let lastId = null;
  let stopped = false;
  let controller = null;
  const run = async () => {
    while (!stopped) {
      controller = new AbortController();
      const headers = new Headers({ Accept: "text/event-stream" });
      const token = savedToken();
      if (token) headers.set("Authorization", `Bearer ${token}`);
      if (lastId !== null) headers.set("Last-Event-ID", lastId);
      let ended = false;
      try {
        const response = await fetch(`/jobs/${jobId}/events`, { headers, signal: controller.signal, cache: "no-store" });
        if (response.status === 204 || response.status === 404) return;
        if (!response.ok) {
          let body = null;
          try { body = await response.json(); } catch (_) { body = null; }
          throw new Error(detailText(body, response.status));
        }
        await readEventStream(response.body, (event) => {
          if (event.id !== null) lastId = event.id;
          const data = JSON.parse(event.data);
          if (event.type === "state" && FINAL_STATES.includes(data.state)) ended = true;
          onEvent(event.type, data, event.id);
        });
      } catch (err) {
        if (stopped) return;
        onError(err.message);
      }
      if (ended || stopped) return;
      await new Promise((resolve) => setTimeout(resolve, EVENTS_RECONNECT_MS));
    }
  };
  run();
  return { stop() { stopped = true; if (controller) controller.abort(); } };
}
