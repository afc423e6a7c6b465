// VoxNeRF pages' shared REST access (a classic script: load it before the page's own script). Every request
// carries the API token saved in localStorage (if any) as "Authorization: Bearer <token>"; the dashboard's
// header form saves it. Files behind the token (renders, images, downloads) become blob: URLs, since an
// <img>, <video> or link cannot send the header. Also the pages' one DOM helper, `el`.
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
// On 401 the page's token field (id "token"), when it has one, takes the focus.
async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const token = savedToken();
  if (token) headers.set("Authorization", `Bearer ${token}`);
  const response = await fetch(path, { ...options, headers });
  if (response.ok) return response;
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
