"use strict";
// layerwatch dashboard: fetches the JSON API, draws the a% curve as inline SVG, follows /api/stream.
const $ = (id) => document.getElementById(id);
const state = { job: null, printer: null, pauseRatio: null };

async function api(path, opts) {
  const r = await fetch(path, Object.assign({ credentials: "same-origin" }, opts || {}));
  if (!r.ok) throw new Error(path + ": " + r.status);
  return r.json();
}

function svgEl(tag, attrs, text) {
  const e = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  if (text !== undefined) e.textContent = text;
  return e;
}

function drawCurve(rows, threshold) {
  const W = 600, H = 220, L = 40, B = 24, T = 10, R = 10;
  const svg = svgEl("svg", { viewBox: `0 0 ${W} ${H}`, role: "img", "aria-label": "a% per layer" });
  const pts = rows.filter((r) => r.anomaly_ratio !== null);
  const maxLayer = Math.max(1, ...rows.map((r) => r.layer));
  const maxY = Math.max(0.05, threshold || 0, ...pts.map((r) => r.anomaly_ratio)) * 1.1;
  const x = (l) => L + (W - L - R) * l / maxLayer;
  const y = (v) => H - B - (H - B - T) * v / maxY;
  svg.appendChild(svgEl("line", { x1: L, y1: H - B, x2: W - R, y2: H - B, stroke: "#555" }));
  svg.appendChild(svgEl("line", { x1: L, y1: T, x2: L, y2: H - B, stroke: "#555" }));
  for (const f of [0, 0.5, 1]) {
    svg.appendChild(svgEl("text", { x: 2, y: y(maxY * f / 1.1) + 4 }, (100 * maxY * f / 1.1).toFixed(1) + "%"));
  }
  svg.appendChild(svgEl("text", { x: W - R - 60, y: H - 6 }, "layer " + maxLayer));
  if (threshold != null) {
    svg.appendChild(svgEl("line", { class: "thr", x1: L, x2: W - R, y1: y(threshold), y2: y(threshold) }));
    svg.appendChild(svgEl("text", { x: L + 4, y: y(threshold) - 4 }, "pause at " + (100 * threshold).toFixed(1) + "%"));
  }
  if (pts.length) {
    svg.appendChild(svgEl("polyline", { class: "line", points: pts.map((r) => `${x(r.layer)},${y(r.anomaly_ratio)}`).join(" ") }));
  }
  $("curve").replaceChildren(svg);
}

function setImage(id, rel) {
  const img = $(id);
  if (rel) img.src = "/api/image/" + rel.split("/").map(encodeURIComponent).join("/"); else img.removeAttribute("src");
}

async function loadJobs() {
  const jobs = await api("/api/jobs");
  const body = $("jobs").querySelector("tbody");
  body.replaceChildren(...jobs.map((j) => {
    const tr = document.createElement("tr");
    const cells = [j.id, j.printer, j.part || "", j.n_layers, j.max_anomaly_ratio == null ? "" : (100 * j.max_anomaly_ratio).toFixed(1) + "%", j.outcome || "running"];
    for (const c of cells) { const td = document.createElement("td"); td.textContent = c; tr.appendChild(td); }
    tr.onclick = () => { state.job = j.id; refreshJob(); };
    return tr;
  }));
  if (state.job === null && jobs.length) state.job = jobs[0].id;
}

async function refreshJob() {
  if (state.job === null) return;
  const [job, rows, events, latest] = await Promise.all([
    api(`/api/jobs/${state.job}`), api(`/api/jobs/${state.job}/layers`),
    api(`/api/jobs/${state.job}/events`), api(`/api/jobs/${state.job}/latest`)]);
  $("job-title").textContent = `#${job.id} ${job.part || ""} on ${job.printer}` + (latest ? ` — layer ${latest.layer}` : "");
  drawCurve(rows, state.pauseRatio);
  const imgs = (latest && latest.images) || {};
  setImage("img-top", imgs.top); setImage("img-reference", imgs.reference); setImage("img-overlay", imgs.overlay);
  $("events").replaceChildren(...events.slice().reverse().map((e) => {
    const li = document.createElement("li");
    li.textContent = new Date(e.time * 1000).toLocaleTimeString() + "  " + e.kind + ": " + e.message;
    return li;
  }));
}

function describe(status) {
  if (status == null) return "unknown";
  if (typeof status === "string") return status;
  return status.state || status.status || JSON.stringify(status);
}

async function loadPrinters() {
  const list = await api("/api/printers");
  const sel = $("printer");
  if (sel.options.length !== list.length) {
    sel.replaceChildren(...list.map((p) => new Option(p.name, p.name)));
  }
  state.printer = sel.value || null;
  const p = list.find((q) => q.name === state.printer);
  const pill = $("printer-state");
  pill.textContent = p ? describe(p.status) : "no printer";
  pill.className = "pill" + (p && /paus/i.test(describe(p.status)) ? " paused" : " on");
}

async function action(name) {
  if (!state.printer) return;
  if (name === "cancel" && !confirm("Cancel the print?")) return;
  const q = state.job !== null ? `?job_id=${state.job}` : "";
  await api(`/api/printers/${encodeURIComponent(state.printer)}/${name}${q}`, { method: "POST" });
  await Promise.all([loadPrinters(), refreshJob()]);
}

async function loadSettings() {
  const s = await api("/api/settings");
  state.settings = s;
  state.pauseRatio = s.policy && typeof s.policy.pause_ratio === "number" ? s.policy.pause_ratio : null;
  const form = $("settings");
  for (const input of form.querySelectorAll("input[name]")) {
    const [sec, key] = input.name.split(".");
    input.value = s[sec] ? s[sec][key] : "";
  }
}

async function saveSettings(ev) {
  ev.preventDefault();
  const s = JSON.parse(JSON.stringify(state.settings));
  for (const input of $("settings").querySelectorAll("input[name]")) {
    const [sec, key] = input.name.split(".");
    s[sec][key] = input.type === "number" ? Number(input.value) : input.value;
  }
  const r = await fetch("/api/settings", { method: "PUT", headers: { "Content-Type": "application/json" }, body: JSON.stringify(s) });
  $("settings-msg").textContent = r.ok ? "saved" : "invalid: " + r.status;
  if (r.ok) await loadSettings();
}

function live() {
  const es = new EventSource("/api/stream");
  es.addEventListener("change", async () => {
    $("live").textContent = "live"; $("live").className = "pill on";
    await loadJobs(); await refreshJob(); await loadPrinters();
  });
  es.onerror = () => { $("live").textContent = "reconnecting"; $("live").className = "pill"; };
}

document.querySelectorAll("button[data-action]").forEach((b) => b.addEventListener("click", () => action(b.dataset.action)));
$("printer").addEventListener("change", loadPrinters);
$("settings").addEventListener("submit", saveSettings);
(async () => {
  await loadSettings(); await loadPrinters(); await loadJobs(); await refreshJob(); live();
})();
