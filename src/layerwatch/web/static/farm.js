// layerwatch farm view (api.js loads first: $, csrf, api, esc, pct): one card per printer, live (SSE on history changes + a 2 s poll for states).
"use strict";
const thumbs = {};  // printer -> layer whose overlay is shown


function sparkline(values) {
  if (!values || values.length < 2) { return '<svg class="spark" viewBox="0 0 120 28"></svg>'; }
  const top = Math.max(0.05, ...values), n = values.length;
  const pts = values.map((v, i) => `${(120 * i / (n - 1)).toFixed(1)},${(26 - 24 * v / top).toFixed(1)}`).join(" ");
  return `<svg class="spark" viewBox="0 0 120 28" role="img" aria-label="a% of the last ${n} layers"><polyline points="${pts}"/></svg>`;
}

function card(p) {
  const alarm = p.alarm ? `<span class="badge ${esc(p.alarm.action)}" title="${esc(p.alarm.reason || "")}" data-testid="alarm">${esc(p.alarm.action)} · layer ${p.alarm.layer}</span>` : "";
  const job = p.job_id != null ? `<a href="/#job=${p.job_id}" data-testid="job">${esc(p.job || "job")} #${p.job_id}</a>` : esc(p.job || "no job");
  const layer = p.layer == null ? "–" : `${p.layer + 1}${p.layers ? " / " + p.layers : ""}`;
  const msg = p.message ? `<div class="msg" data-testid="message">${esc(p.message)}</div>` : "";
  const dropped = p.dropped ? ` · ${p.dropped} dropped` : "";
  return `<section class="card farm-card state-${esc(p.state)}" data-printer="${esc(p.name)}">` +
    `<div class="head"><b>${esc(p.name)}</b> <span class="state ${esc(p.state)}" data-testid="state">${esc(p.state)}</span> ${alarm}</div>` +
    `<img class="thumb" alt="overlay of ${esc(p.name)}" data-layer="">` +
    `<div class="meta">${job} · layer ${layer} · a% ${pct(p.ratio)}${dropped}</div>${sparkline(p.ratios)}${msg}` +
    `<div class="buttons">${["pause", "resume", "acknowledge"].map((a) => `<button class="${a}" data-action="${a}">${a}</button>`).join("")}</div>` +
    "</section>";
}

function paint(ps) {
  const grid = $("grid");
  const known = new Set(ps.map((p) => p.name));
  for (const el of grid.querySelectorAll(".farm-card")) { if (!known.has(el.dataset.printer)) { el.remove(); } }
  for (const p of ps) {
    const html = card(p);
    let el = grid.querySelector(`.farm-card[data-printer="${CSS.escape(p.name)}"]`);
    if (!el) { grid.insertAdjacentHTML("beforeend", html); el = grid.lastElementChild; }
    else if (el.dataset.html !== html) { const img = el.querySelector("img.thumb"); el.outerHTML = html; el = grid.querySelector(`.farm-card[data-printer="${CSS.escape(p.name)}"]`); if (img && img.src) { el.querySelector("img.thumb").replaceWith(img); } }
    el.dataset.html = html;
    if (p.thumb && thumbs[p.name] !== p.layer) {  // a new overlay: fetch it once per layer
      thumbs[p.name] = p.layer;
      el.querySelector("img.thumb").src = `/api/printers/${encodeURIComponent(p.name)}/thumb.png?layer=${p.layer}`;
    }
  }
  const count = (s) => ps.filter((p) => p.state === s).length;
  $("farm-counts").textContent = `${ps.length} printers · ${count("printing")} printing · ${count("paused")} paused · ${count("error")} error`;
}

let busy = false;
async function refresh() {
  if (busy) { return; }
  busy = true;
  try { paint(await api("/api/printers")); }
  catch (e) { $("live").textContent = "error"; }
  finally { busy = false; }
  document.body.dataset.ready = "1";
}

document.addEventListener("click", async (ev) => {
  const b = ev.target.closest("button[data-action]");
  if (!b) { return; }
  const name = b.closest(".farm-card").dataset.printer;
  b.disabled = true;
  try { await api(`/api/printers/${encodeURIComponent(name)}/${b.dataset.action}`, { method: "POST" }); }
  catch (e) { alert(e.message); }
  b.disabled = false;
  await refresh();
});

(async function main() {
  await refresh();
  const es = new EventSource("/api/stream");
  es.addEventListener("change", () => { $("live").textContent = "live"; $("live").classList.add("on"); refresh(); });
  es.onerror = () => { $("live").textContent = "reconnecting"; $("live").classList.remove("on"); };
  setInterval(refresh, 2000);  // states that are not history rows (paused by hand, host errors)
})();
