// layerwatch pages' shared helpers: element lookup, the JSON API call with the session's CSRF token, escaping.
"use strict";
const $ = (id) => document.getElementById(id);
// the session's CSRF token: the server puts it in the page; every POST/PUT/PATCH/DELETE sends it back
let csrf = document.querySelector('meta[name="csrf-token"]').content;

async function api(path, opts, retried) {
  opts = Object.assign({ credentials: "same-origin" }, opts || {});
  if (opts.method && opts.method !== "GET") {
    opts.headers = Object.assign({}, opts.headers || {}, { "X-CSRF-Token": csrf });
  }
  const r = await fetch(path, opts);
  if (r.status === 403 && !retried) {  // the session expired or the server restarted: take a new one, once
    const s = await fetch("/api/session", { credentials: "same-origin" });
    if (s.ok) { csrf = (await s.json()).csrf; return api(path, opts, true); }
  }
  if (!r.ok) {
    const text = await r.text();
    let detail = text;
    try { const d = JSON.parse(text).detail; detail = typeof d === "string" ? d : JSON.stringify(d); } catch (e) { /* not JSON */ }
    throw new Error(detail || String(r.status));
  }
  return r.json();
}
// text for innerHTML (escaped) and a fraction as a percentage ("–" when unknown)
function esc(s) { const d = document.createElement("span"); d.textContent = String(s); return d.innerHTML; }
function pct(x) { return x == null ? "–" : (100 * x).toFixed(1) + " %"; }
