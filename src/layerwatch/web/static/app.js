// layerwatch dashboard: vanilla JS, no network beyond this server (api.js loads first: $, csrf, api, esc, pct).
"use strict";
let jobId = null;
let jobCount = -1;
function img(el, path) {
  if (path) { el.src = "/api/image/" + path.split("/").map(encodeURIComponent).join("/"); el.style.visibility = "visible"; }
  else { el.removeAttribute("src"); el.style.visibility = "hidden"; }
}

async function loadJobs() {
  const jobs = await api("/api/jobs");
  const sel = $("job-select");
  if (jobs.length !== jobCount) {
    jobCount = jobs.length;
    const keep = jobId;
    sel.innerHTML = jobs.map((j) => `<option value="${j.id}">#${j.id} ${esc(j.part || "job")} · ${esc(j.printer)}${j.outcome ? " · " + esc(j.outcome) : " · live"}</option>`).join("");
    jobId = keep != null && jobs.some((j) => j.id === keep) ? keep : (jobs.length ? jobs[0].id : null);
    if (jobId != null) { sel.value = String(jobId); }
  }
  $("jobs").innerHTML = "<tr><th>job</th><th>part</th><th>layers</th><th>max a%</th><th>outcome</th></tr>" + jobs.map((j) =>
    `<tr class="${j.id === jobId ? "sel" : ""}" data-job="${j.id}"><td>#${j.id}</td><td>${esc(j.part || "")}</td><td>${j.n_layers}</td><td>${pct(j.max_anomaly_ratio)}</td><td>${esc(j.outcome || "live")}</td></tr>`).join("");
  return jobs.find((j) => j.id === jobId);
}

function drawCurve(rows, threshold) {
  const svg = $("curve"), W = Math.max(200, svg.clientWidth), H = Math.max(120, svg.clientHeight), L = 40, R = 10, T = 10, B = 26;
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const n = rows.length;
  const maxA = Math.max(threshold || 0, ...rows.map((r) => r.anomaly_ratio || 0), 0.05) * 1.1;
  const maxL = Math.max(1, ...rows.map((r) => r.layer));
  const x = (l) => L + (W - L - R) * l / maxL;
  const y = (a) => T + (H - T - B) * (1 - a / maxA);
  let s = "";
  for (let i = 0; i <= 4; i++) {
    const a = maxA * i / 4;
    s += `<line x1="${L}" x2="${W - R}" y1="${y(a)}" y2="${y(a)}" stroke="#e5e7eb"/><text x="${L - 4}" y="${y(a) + 4}" font-size="11" text-anchor="end" fill="#6b7280">${(100 * a).toFixed(0)}%</text>`;
  }
  s += `<text x="${(L + W) / 2}" y="${H - 4}" font-size="11" text-anchor="middle" fill="#6b7280">layer (0–${maxL})</text>`;
  if (threshold != null) {
    s += `<line id="threshold-line" x1="${L}" x2="${W - R}" y1="${y(threshold)}" y2="${y(threshold)}" stroke="#dc2626" stroke-dasharray="6 4" stroke-width="1.5"/>`;
  }
  if (n) {
    const pts = rows.filter((r) => r.anomaly_ratio != null).map((r) => `${x(r.layer).toFixed(1)},${y(r.anomaly_ratio).toFixed(1)}`).join(" ");
    s += `<polyline points="${pts}" fill="none" stroke="#2563eb" stroke-width="2"/>`;
    for (const r of rows) {
      if (r.anomaly_ratio != null && threshold != null && r.anomaly_ratio > threshold) {
        s += `<circle cx="${x(r.layer)}" cy="${y(r.anomaly_ratio)}" r="3" fill="#dc2626"/>`;
      }
    }
  }
  svg.innerHTML = s;
}

function fetchJob(id) {
  return Promise.all([api(`/api/jobs/${id}/layers`), api(`/api/jobs/${id}/latest`), api(`/api/jobs/${id}/events`)]);
}

async function loadJob(job, early) {
  if (jobId == null) { $("job-title").textContent = "No jobs yet"; return; }
  const [rows, latest, events] = await (early && early.id === jobId ? early.data : fetchJob(jobId));
  const pause = settings ? settings.policy.pause_ratio : null;
  const first = rows.find((r) => pause != null && r.anomaly_ratio != null && r.anomaly_ratio > pause);
  $("job-title").textContent = `Job #${jobId}: ${job && job.part ? job.part : ""}`;
  $("job-meta").innerHTML = latest
    ? `layer <b>${latest.layer}</b> · z ${latest.z.toFixed(2)} mm · a% <b class="${first ? "fail" : ""}">${pct(latest.anomaly_ratio)}</b> · ${esc(latest.metric)} T<sub>S</sub>=${latest.threshold} · ${rows.length} layers` +
      (first ? ` · <span class="fail">first failing layer ${first.layer}</span>` : "") + (job && job.outcome ? ` · ${esc(job.outcome)}` : " · live")
    : "no layers yet";
  const im = (latest && latest.images) || {};
  img($("img-top"), im.top || im.photo); img($("img-reference"), im.reference); img($("img-overlay"), im.overlay);
  img($("img-stack"), im.stack); $("stack-none").style.display = im.stack ? "none" : "block";
  $("ack-job").hidden = !(job && job.outcome == null);
  drawCurve(rows, pause);
  $("curve-legend").innerHTML = `<span class="key-curve">━</span> a% per layer &nbsp; <span class="key-threshold">╌</span> pause threshold ${pct(pause)}`;
  $("events").innerHTML = events.slice(-50).reverse().map((e) =>
    `<li><span class="meta">${new Date(e.time * 1000).toLocaleTimeString()}</span> <span class="kind">${esc(e.kind)}</span> ${esc(e.message)}</li>`).join("");
}

async function loadPrinters() {
  const ps = await api("/api/printers");
  if (!ps.length) { $("printer-list").textContent = "no printers connected"; return; }
  $("printer-list").innerHTML = ps.map((p) => {
    const st = p.state || (p.status && (p.status.state || p.status.error)) || "unknown";
    return `<div class="printer" data-printer="${esc(p.name)}"><span class="name">${esc(p.name)} · <span class="state ${esc(st)}" data-testid="state">${esc(st)}</span></span>` +
      ["acknowledge", "pause", "resume", "cancel"].map((a) => `<button class="${a}" data-action="${a}">${a}</button>`).join("") + "</div>";
  }).join("");
}

document.addEventListener("click", async (ev) => {
  const b = ev.target.closest("button[data-action]");
  if (!b) { return; }
  const name = b.closest(".printer").dataset.printer, action = b.dataset.action;
  if (action === "cancel" && !confirm("Cancel the print?")) { return; }
  b.disabled = true;
  try {
    await api(`/api/printers/${encodeURIComponent(name)}/${action}` + (jobId != null ? `?job_id=${jobId}` : ""), { method: "POST" });
  } catch (e) { alert(e.message); }
  b.disabled = false;
  await refresh();
});

$("ack-job").addEventListener("click", async () => {
  if (jobId == null) { return; }
  $("ack-job").disabled = true;
  try {
    await api(`/api/jobs/${jobId}/acknowledge`, { method: "POST" });
    $("ack-msg").textContent = "acknowledged";
  } catch (e) { $("ack-msg").textContent = e.message; }
  $("ack-job").disabled = false;
  await refresh();
});

async function loadAudit() {
  const rows = await api("/api/audit?limit=30");
  $("audit").innerHTML = rows.map((a) =>
    `<li><span class="meta">${new Date(a.time * 1000).toLocaleString()}</span> <span class="kind">${esc(a.action)}</span>` +
    `${a.target ? " " + esc(a.target) : ""} <span class="meta">by ${esc(a.actor)} from ${esc(a.client)}</span></li>`).join("") ||
    "<li class=\"meta\">nothing changed from the dashboard yet</li>";
}

function showPausing() {
  const on = settings.policy.action !== "notify" || settings.policy.strong_action !== "notify";
  $("pausing").checked = on;
  $("pausing-off").hidden = on;
}
$("pausing").addEventListener("change", async (ev) => {
  const enabled = ev.target.checked;
  if (!enabled && !confirm("Switch pausing off? Failures will only be notified, never pause the print.")) {
    ev.target.checked = true; return;
  }
  try {
    await api("/api/pausing", { method: "PUT", headers: { "content-type": "application/json" }, body: JSON.stringify({ enabled }) });
  } catch (e) { alert(e.message); }
  await loadSettings();
  await refresh();
});

let settings = null;
let settingsReady = null;
async function loadSettings() {
  const [st, metrics, ranges] = await Promise.all([api("/api/settings"), api("/api/metrics"), api("/api/settings/ranges")]);
  settings = st;
  for (const [id, key] of [["set-threshold", "analysis.threshold"], ["set-pause", "policy.pause_ratio"]]) {
    $(id).min = ranges[key].min; $(id).max = ranges[key].max;
  }
  showPausing();
  $("set-metric").innerHTML = metrics.map((m) => `<option>${m}</option>`).join("");
  $("set-metric").value = settings.analysis.metric;
  $("set-threshold").value = settings.analysis.threshold;
  $("set-pause").value = settings.policy.pause_ratio;
  // "notify" (never pause) is the pause switch's to set, not this list's
  const acts = settings.policy.action === "notify" ? ["notify", "pause", "cancel"] : ["pause", "cancel"];
  $("set-action").innerHTML = acts.map((a) => `<option>${a}</option>`).join("");
  $("set-action").value = settings.policy.action;
}
$("settings").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  const s = JSON.parse(JSON.stringify(settings));
  s.analysis.metric = $("set-metric").value;
  s.analysis.threshold = parseFloat($("set-threshold").value);
  s.policy.pause_ratio = parseFloat($("set-pause").value);
  s.policy.action = $("set-action").value;
  try {
    settings = await api("/api/settings", { method: "PUT", headers: { "content-type": "application/json" }, body: JSON.stringify(s) });
    $("settings-msg").textContent = "saved";
  } catch (e) { $("settings-msg").textContent = (e.message.startsWith("invalid") ? "" : "invalid: ") + e.message.slice(0, 160); }
  await refresh();
});
$("jobs").addEventListener("click", (ev) => {
  const tr = ev.target.closest("tr[data-job]");
  if (tr) { jobId = parseInt(tr.dataset.job, 10); $("job-select").value = String(jobId); refresh(); }
});
window.addEventListener("resize", () => refresh());
$("job-select").addEventListener("change", (ev) => { jobId = parseInt(ev.target.value, 10); refresh(); });

let busy = false;
async function refresh() {
  if (busy) { return; }
  busy = true;
  try {
    // the job's rows are fetched alongside the job list, not after it (one round trip less)
    const early = jobId != null ? { id: jobId, data: fetchJob(jobId) } : null;
    if (early) { early.data.catch(() => {}); }  // unused when the job vanished; loadJob fetches again
    await Promise.all([Promise.all([loadJobs(), settingsReady]).then(([job]) => loadJob(job, early)), loadPrinters(), loadAudit()]);
  }
  catch (e) { $("live").textContent = "error"; }
  finally { busy = false; }
  document.body.dataset.ready = "1";
}

(async function main() {
  const linked = /^#job=(\d+)$/.exec(location.hash);  // /#job=12 opens that job (links, bookmarks)
  if (linked) { jobId = parseInt(linked[1], 10); }
  else if (document.body.dataset.newest) { jobId = parseInt(document.body.dataset.newest, 10); }  // set by the server
  settingsReady = loadSettings();
  await refresh();
  const es = new EventSource("/api/stream");
  es.addEventListener("change", () => { $("live").textContent = "live"; $("live").classList.add("on"); refresh(); });
  es.onerror = () => { $("live").textContent = "reconnecting"; $("live").classList.remove("on"); };
})();
