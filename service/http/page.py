"""The pages: ``/`` lists the jobs, ``/jobs/{id}/view`` follows one, ``/docs`` is Swagger UI.

Plain HTML, SVG and a small inline script: no build step, nothing fetched from the
internet. The script reads the event stream with ``fetch`` (so it can send the bearer
token, which EventSource cannot) and reconnects with ``Last-Event-ID``. A token is taken
from ``#token=...`` in the address once and kept in the tab's sessionStorage.

Everything that comes from a job (its name, its models' names, numbers) is put in the page
as text (``textContent``, DOM nodes), never as HTML; and the pages are served with a
Content-Security-Policy (:data:`CSP`) that runs only this module's own scripts (by hash)
and connects only to the service, so a name that holds markup can neither run nor send
the token anywhere.
"""

import base64
import hashlib
import json

from service.report.colours import MODEL_COLOURS


def _hash(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


STYLE = r"""
 body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;max-width:1100px}
 h1{font-size:1.3em;margin:0 0 .5em} table{border-collapse:collapse} td,th{padding:.25em .7em;border-bottom:1px solid #ddd;text-align:left}
 .grid{display:grid;grid-template-columns:1fr 1fr;gap:1em} .card{border:1px solid #ddd;border-radius:6px;padding:.6em}
 .card h2{font-size:1em;margin:0 0 .3em} .kv span{display:inline-block;margin-right:1.4em} .kv b{font-variant-numeric:tabular-nums}
 svg{width:100%;height:230px} .axis{stroke:#777;stroke-width:1} .grid{stroke:#e4e4e4;stroke-width:1} .lbl{font-size:11px;fill:#333}
 .axis-title{font-size:12px;fill:#111} .hist{display:inline-block;margin:0 1.4em .8em 0} .hist svg{width:240px;height:112px}
 .gap{margin-top:1em} .mark{stroke:#000;stroke-width:1.2} .mark-label{font-size:11px;fill:#000}
 svg text{stroke:none}
 .status-running{color:#b60} .status-finished{color:#070} .status-failed{color:#b00} .status-cancelled{color:#777}
#warnings{color:#a40;margin:.5em 0;padding-left:1.2em}
"""

COMMON_JS = r"""
const TOKEN_KEY = "abcns-token";
(function(){ const m = location.hash.match(/token=([^&]+)/); if (m) { sessionStorage.setItem(TOKEN_KEY, decodeURIComponent(m[1])); history.replaceState(null, "", location.pathname); } })();
function headers(extra) { const h = Object.assign({}, extra || {}); const t = sessionStorage.getItem(TOKEN_KEY); if (t) h["Authorization"] = "Bearer " + t; return h; }
async function getJSON(url) { const r = await fetch(url, {headers: headers()}); if (!r.ok) throw new Error(url + ": " + r.status); return r.json(); }
function fmt(x, d) { if (x === null || x === undefined) return "-"; if (typeof x !== "number") return String(x); const a = Math.abs(x); return (a !== 0 && (a < 1e-3 || a >= 1e5)) ? x.toExponential(d || 3) : x.toPrecision(d || 4); }
// elements, never markup: every string becomes a text node
// (a child that is a node stays a node: an SVG <rect> in an <svg> is drawn, its text would not be)
function nodes(children) { return children.map(c => (c instanceof Node) ? c : String(c)); }
function el(tag, attrs, ...children) { const e = document.createElement(tag); for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, String(v)); e.append(...nodes(children)); return e; }
const SVG_NS = "http://www.w3.org/2000/svg";
function sv(tag, attrs, ...children) { const e = document.createElementNS(SVG_NS, tag); for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, String(v)); e.append(...nodes(children)); return e; }
function text(id, value) { document.getElementById(id).textContent = value; }
"""

INDEX_JS = r"""
async function refresh() {
  try {
    const jobs = await getJSON("/jobs");
    const rows = jobs.reverse().map(j => el("tr", {},
      el("td", {}, el("a", {href: "/jobs/" + encodeURIComponent(j.id) + "/view"}, j.id.slice(0, 8))), el("td", {}, j.name || ""),
      el("td", {class: "status-" + j.status}, j.status), el("td", {}, j.progress ? j.progress.population : "-"),
      el("td", {}, j.progress ? fmt(j.progress.epsilon) : "-"), el("td", {}, j.progress ? j.progress.simulations : "-")));
    document.getElementById("jobs").replaceChildren(...rows);
    text("error", "");
  } catch (e) { text("error", String(e)); }
}
refresh(); setInterval(refresh, 2000);
"""

VIEW_JS = r"""
const jobId = location.pathname.split("/")[2];
text("job", jobId.slice(0, 8));
const pops = [];  // population events
const COLORS = __MODEL_COLOURS__;  // a model's colour, as in abcns plot (service/report/colours.py)
const EPS_COLOR = COLORS[0], ACC_COLOR = "#2ca02c";  // as abcns plot's tolerance figure
const HIST_PARTICLES = 50000, PAGE = 10000;  // the marginals use at most this many particles of a population
let modelNames = [], lastId = 0, ended = false, histBusy = false, histShown = 0, legendKey = null;
let unit = " %";  // the tolerance's unit: % for the NMSE (the default distance), none for a summary distance

// a job's model probabilities in the order of its models (a list, or name -> value)
function probsOf(p, names) {
  const v = p.model_probabilities || [];
  return Array.isArray(v) ? v : (names.length ? names : Object.keys(v)).map(n => v[n]);
}

// "nice" tick values in [lo, hi]: steps of 1, 2 or 5 x 10^k, about n of them (whole numbers if integer)
function ticks(lo, hi, n, integer) {
  const raw = (hi - lo) / Math.max(1, n - 1);
  let step = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 5, 10]) { if (m * step >= raw * (1 - 1e-9)) { step *= m; break; } }
  if (integer) step = Math.max(1, Math.round(step));
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) out.push(Number(v.toPrecision(12)));
  return out;
}

// ticks of a log axis (positions in log10): at 1 x 10^k, else 1, 2, 5 x 10^k, else every digit, the first with 3 or more
function logTicks(y0, y1) {
  let out = [];
  for (const digits of [[1], [1, 2, 5], [1, 2, 3, 4, 5, 6, 7, 8, 9]]) {
    out = [];
    for (let k = Math.floor(y0); k <= Math.ceil(y1); k++) {
      for (const d of digits) { const v = k + Math.log10(d); if (v >= y0 - 1e-9 && v <= y1 + 1e-9) out.push(v); }
    }
    if (out.length >= 3) break;
  }
  return out;
}

function tickText(x, digits) {
  const a = Math.abs(x), d = digits || 3;
  return (a === 0 || (a >= 1e-3 && a < 1e5)) ? String(Number(x.toPrecision(d))) : x.toExponential(d - 2);
}

// the labels of distinct tick values, with as many digits as tell them apart (a narrow marginal: 1.4903 1.4911 1.4919)
function tickTexts(values) {
  for (let d = 3; d < 15; d++) { const t = values.map(v => tickText(v, d)); if (new Set(t).size === values.length) return t; }
  return values.map(v => tickText(v, 15));
}

// a line chart of the populations: ticks and their values along both axes, and the axes' titles
function line(svg, series, opts) {
  const W = 500, H = 230, L = 58, R = 12, T = 10, B = 40;  // the plot area: x in [L, W - R], y in [T, H - B]
  svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
  // marks: dashed lines across the plot at {x} or {y}, each with its label (the floor, the decision)
  const marks = opts.marks || [];
  const xs = series.flatMap(s => s.points.map(p => p[0])),
        ys = series.flatMap(s => s.points.map(p => p[1])).concat(marks.filter(m => m.y !== undefined).map(m => m.y));
  const titles = [sv("text", {class: "axis-title", x: L + (W - L - R) / 2, y: H - 4, "text-anchor": "middle"}, "population"),
    sv("text", {class: "axis-title", x: 0, y: 0, "text-anchor": "middle",
                transform: `translate(13,${T + (H - B - T) / 2}) rotate(-90)`}, opts.ylabel)];
  if (!xs.length) { svg.replaceChildren(...titles); return; }
  let x0 = Math.min(...xs), x1 = Math.max(...xs); if (x1 === x0) x1 = x0 + 1;
  let y0 = opts.y0 !== undefined ? opts.y0 : Math.min(...ys), y1 = opts.y1 !== undefined ? opts.y1 : Math.max(...ys);
  if (y1 === y0) { y0 -= 0.5; y1 += 0.5; }
  const X = x => L + (x - x0) / (x1 - x0) * (W - L - R), Y = y => T + (1 - (y - y0) / (y1 - y0)) * (H - B - T);
  const out = [sv("line", {class: "axis", x1: L, y1: H - B, x2: W - R, y2: H - B}),
               sv("line", {class: "axis", x1: L, y1: T, x2: L, y2: H - B}), ...titles];
  for (const v of ticks(x0, x1, 6, true)) {
    out.push(sv("line", {class: "axis", x1: X(v), y1: H - B, x2: X(v), y2: H - B + 4}),
             sv("text", {class: "lbl", x: X(v), y: H - B + 15, "text-anchor": "middle"}, v));
  }
  for (const v of (opts.yticks ? opts.yticks(y0, y1) : ticks(y0, y1, 5, !!opts.integer))) {
    out.push(sv("line", {class: "grid", x1: L, y1: Y(v), x2: W - R, y2: Y(v)}),
             sv("text", {class: "lbl", x: L - 5, y: Y(v) + 3, "text-anchor": "end"}, opts.fmt(v)));
  }
  for (const s of series) {
    const d = s.points.map((p, i) => (i ? "L" : "M") + X(p[0]).toFixed(1) + "," + Y(p[1]).toFixed(1)).join("");
    out.push(sv("path", {d: d, fill: "none", stroke: s.color, "stroke-width": 1.6}));
  }
  for (const m of marks) {
    const at = m.x !== undefined ? {x1: X(m.x), y1: T, x2: X(m.x), y2: H - B} : {x1: L, y1: Y(m.y), x2: W - R, y2: Y(m.y)};
    const left = m.x !== undefined && X(m.x) > L + (W - L - R) / 2;  // a label beside its line, inside the plot
    // a horizontal mark's label above its line, or below it (m.below: the lower of two close marks, so they never overlap)
    const where = m.x !== undefined ? {x: X(m.x) + (left ? -3 : 3), y: T + 10, "text-anchor": left ? "end" : "start"}
                                    : {x: W - R - 2, y: Y(m.y) + (m.below ? 11 : -3), "text-anchor": "end"};
    out.push(sv("line", Object.assign({class: "mark", "stroke-dasharray": m.dash || "5,3"}, at)),
             sv("text", Object.assign({class: "mark-label"}, where), m.label));
  }
  svg.replaceChildren(...out);
}

// the histogram of one parameter: 20 bars; the parameter's values along the x axis
function hist(values, label, color) {
  const W = 240, H = 112, T = 4, B = 30, n = 20;  // the bars in [T, H - B]
  let lo = Math.min(...values), hi = Math.max(...values); if (hi === lo) { hi = lo + 1; }
  const counts = new Array(n).fill(0); for (const v of values) counts[Math.min(n - 1, Math.floor((v - lo) / (hi - lo) * n))]++;
  const m = Math.max(...counts), bw = W / n, h = H - B - T;
  const bars = counts.map((c, i) => sv("rect", {x: (i * bw).toFixed(1), y: (T + h - c / m * h).toFixed(1),
    width: (bw - 1).toFixed(1), height: (c / m * h).toFixed(1), fill: color}));
  const axis = [sv("line", {class: "axis", x1: 0, y1: H - B, x2: W, y2: H - B})];
  const labels = tickTexts([lo, (lo + hi) / 2, hi]);
  [[lo, 1, "start"], [(lo + hi) / 2, W / 2, "middle"], [hi, W - 1, "end"]].forEach(([v, x, anchor], i) => axis.push(
    sv("line", {class: "axis", x1: x, y1: H - B, x2: x, y2: H - B + 4}),
    sv("text", {class: "lbl", x: x, y: H - B + 14, "text-anchor": anchor}, labels[i])));
  axis.push(sv("text", {class: "axis-title", x: W / 2, y: H - 2, "text-anchor": "middle"}, label));
  return el("div", {class: "hist"}, sv("svg", {viewBox: `0 0 ${W} ${H}`}, ...bars, ...axis));
}

function leader(probs) { let k = 0; probs.forEach((p, i) => { if (p > probs[k]) k = i; }); return k; }

// the population the answer is read at: the lowest tolerance at or above the decision
// tolerance as the last population estimates it (abcns.result.Result.decision_population);
// the last population while the run knows no noise floor
function decisionPop() {
  const p = pops[pops.length - 1];
  if (!p || p.decision_tolerance === null || p.decision_tolerance === undefined) return p;
  const above = pops.filter(q => q.epsilon >= p.decision_tolerance);
  return above.length ? above.reduce((a, b) => (b.epsilon <= a.epsilon ? b : a)) : pops[0];
}

function render() {
  const p = pops[pops.length - 1];
  if (p) {
    text("population", p.population); text("epsilon", fmt(p.epsilon)); text("eps-unit", unit);
    text("acceptance", p.acceptance_rate.toFixed(3)); text("simulations", p.simulations); text("elapsed", p.elapsed_s.toFixed(1));
    // the workers' share of time on the run's simulations over the last population (in-process: none)
    text("efficiency", p.efficiency === null || p.efficiency === undefined ? "-" : p.efficiency.toFixed(2));
  }
  const d = decisionPop(), known = p && p.decision_tolerance !== null && p.decision_tolerance !== undefined;
  if (d) {  // the leading model where the answer is read, and which tolerance that is
    const probs = probsOf(d, modelNames), k = leader(probs);
    text("leader", (modelNames[k] || "model " + (k + 1)) + " (" + probs[k].toFixed(2) + ")");
    text("answer-at", known ? `population ${d.population}, \u03b5 ${fmt(d.epsilon)}${unit} (decision tolerance ${fmt(p.decision_tolerance)}${unit}, noise floor ${fmt(p.noise_floor)}${unit})`
                            : `population ${d.population} (the last: no noise floor yet)`);
  }
  const epsMarks = known ? [{y: Math.log10(p.decision_tolerance), label: "decision " + fmt(p.decision_tolerance) + unit},
                            {y: Math.log10(p.noise_floor), label: "noise floor " + fmt(p.noise_floor) + unit, dash: "2,3", below: true}] : [];
  line(document.getElementById("eps"), [{color: EPS_COLOR, points: pops.map(q => [q.population, Math.log10(q.epsilon)])}],
       {ylabel: "tolerance \u03b5" + (unit ? " (" + unit.trim() + ")" : ""), fmt: v => tickText(Math.pow(10, v)),
        yticks: logTicks, marks: epsMarks});  // a log axis labelled with the tolerance itself
  line(document.getElementById("acc"), [{color: ACC_COLOR, points: pops.map(q => [q.population, q.acceptance_rate])}],
       {y0: 0, y1: 1, ylabel: "acceptance rate", fmt: tickText});
  // the cluster's worker threads during each population (none for one evaluated in the runner's process)
  const counted = pops.filter(q => q.workers !== null && q.workers !== undefined);
  line(document.getElementById("workers-chart"), [{color: "#555", points: counted.map(q => [q.population, q.workers])}],
       {y0: 0, y1: Math.max(1, ...counted.map(q => q.workers)), ylabel: "workers", fmt: tickText, integer: true});
  const n = pops.length ? probsOf(pops[0], modelNames).length : modelNames.length;
  line(document.getElementById("probs"), Array.from({length: n}, (_, i) => ({color: COLORS[i % COLORS.length],
       points: pops.map(q => [q.population, probsOf(q, modelNames)[i]])})),
       {y0: 0, y1: 1, ylabel: "model probability", fmt: tickText,
        marks: known ? [{x: d.population, label: "answer (population " + d.population + ")"}] : []});
  // the legend is made again only when the models it names change, not on every event:
  // its elements stay (a selection in it, a reader of them)
  const names = Array.from({length: n}, (_, i) => modelNames[i] || "model " + (i + 1)), key = JSON.stringify(names);
  if (key !== legendKey) {
    legendKey = key;
    document.getElementById("legend").replaceChildren(...names.map((name, i) => {
      const s = el("span", {class: "model"}, "\u25A0 " + name + "  "); s.style.color = COLORS[i % COLORS.length]; return s; }));
  }
}

// the marginals of the leading model of the last population: one fetch at a time, and
// again as long as a newer population came meanwhile (so the panel never lags behind)
async function histograms() {
  if (histBusy) return;
  histBusy = true;
  try {
    while (pops.length && pops[pops.length - 1].population !== histShown) {
      const t = pops[pops.length - 1].population;
      let pop = await getJSON(`/jobs/${jobId}/populations/${t}?limit=${PAGE}`);
      const theta = pop.theta, models = pop.models;
      while (pop.offset + pop.distances.length < Math.min(pop.n_particles, HIST_PARTICLES) && pop.distances.length) {
        pop = await getJSON(`/jobs/${jobId}/populations/${t}?offset=${pop.offset + pop.distances.length}&limit=${PAGE}`);
        theta.push(...pop.theta); models.push(...pop.models);
      }
      const lead = leader(probsOf(pop, pop.model_names));
      const rows = theta.filter((_, i) => models[i] === lead);
      const part = models.length < pop.n_particles ? ` (first ${models.length} of ${pop.n_particles} particles)` : "";
      document.getElementById("hists").replaceChildren(el("div", {class: "lbl", id: "hist-title"},
        `${pop.model_names[lead]}, population ${t}: ${rows.length} particles${part}`),
        ...pop.parameter_names[lead].map((nm, j) => hist(rows.map(r => r[j]), nm, COLORS[lead % COLORS.length])));
      histShown = t;
    }
  } catch (e) { /* the next population retries */ } finally { histBusy = false; }
}

// once the job has ended: the summary's answer (read by the likelihood over every population
// where the run knows its noise; provisional when it stopped above its decision tolerance)
// and its warnings (an undecided run, a provisional answer, ...)
async function showWarnings() {
  try {
    const s = await getJSON(`/jobs/${jobId}/result`), dec = s.decision;
    if (dec && s.model_probabilities && Object.keys(s.model_probabilities).length) {
      const names = Object.keys(s.model_probabilities), probs = names.map(k => s.model_probabilities[k]), k = leader(probs);
      text("leader", names[k] + " (" + probs[k].toFixed(2) + ")" + (dec.provisional ? " provisional" : ""));
      const how = dec.reading === "likelihood" ? `populations 1-${dec.population} weighted by the likelihood` : `population ${dec.population}`;
      text("answer-at", (dec.provisional ? `PROVISIONAL (stopped: ${dec.rule}, above the decision tolerance): ` : "") +
           `${how}, \u03b5 ${fmt(dec.epsilon)}${unit}`);
    }
    document.getElementById("warnings").replaceChildren(...(s.warnings || []).map(w => el("li", {}, "warning: " + w)));
  } catch (e) { text("error", String(e)); }
}

async function workers() {  // the cluster's workers now (the service counts them every 2 s)
  try {
    const h = await getJSON("/health"); text("workers", h.workers);
    text("utilization", h.utilization == null ? "-" : `${Math.round(100 * h.utilization)} %`);
  } catch (e) { text("workers", "-"); text("utilization", "-"); }
}

function setStatus(s) { const e = document.getElementById("status"); e.textContent = s; e.className = "status-" + s; }

function handle(ev) {
  if (ev.id) lastId = parseInt(ev.id, 10);
  let data = {}; try { data = JSON.parse(ev.data || "{}"); } catch (e) {}
  if (ev.event === "population") { pops.push(data); render(); histograms(); setStatus("running"); }
  else if (ev.event === "started") setStatus("running");
  else if (ev.event === "placed") {  // where the job's loop runs: whole on a worker, or spread from it
    const pl = data.placement || {};
    text("placement", pl.worker ? `${pl.mode === "spread" ? "spread from" : "whole on"} ${pl.worker}` : "-");
  }
  else if (ev.event === "queued") {
    if (data.models) modelNames = data.models;
    if (data.distance) unit = data.distance === "nmse" ? " %" : "";
    setStatus("queued"); render();
  }
  else if (ev.event === "requeued") setStatus("queued");  // the scheduler went away; resumed when it is back
  else if (["finished", "failed", "cancelled"].includes(ev.event)) { ended = true; text("placement", "-"); setStatus(ev.event); histograms(); showWarnings(); }
}

async function stream() {
  while (!ended) {
    try {
      const h = headers({"Accept": "text/event-stream"}); if (lastId) h["Last-Event-ID"] = String(lastId);
      const r = await fetch(`/jobs/${jobId}/events`, {headers: h});
      if (!r.ok) throw new Error("events: " + r.status);
      const reader = r.body.getReader(), dec = new TextDecoder(); let buf = "";
      for (;;) {
        const {value, done} = await reader.read(); if (done) break;
        buf += dec.decode(value, {stream: true});
        let k; while ((k = buf.indexOf("\n\n")) >= 0) {
          const block = buf.slice(0, k); buf = buf.slice(k + 2);
          const ev = {}; for (const ln of block.split("\n")) { const c = ln.indexOf(":"); if (c <= 0) continue;
            const f = ln.slice(0, c), v = ln.slice(c + 1).replace(/^ /, ""); ev[f] = ev[f] ? ev[f] + "\n" + v : v; }
          if (ev.event || ev.data) handle(ev);
        }
      }
      text("error", "");
    } catch (e) { text("error", String(e)); }
    if (!ended) await new Promise(res => setTimeout(res, 1000));
  }
}

workers(); setInterval(workers, 2000);
getJSON(`/jobs/${jobId}`).then(j => { text("name", j.name || ""); modelNames = j.models || modelNames; setStatus(j.status); render(); })
  .catch(e => text("error", String(e))).finally(stream);
""".replace("__MODEL_COLOURS__", json.dumps(list(MODEL_COLOURS)))

_HEAD = '<meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">' \
        f"<style>{STYLE}</style><script>{COMMON_JS}</script>"

INDEX = ("<!doctype html><html><head><title>abcns jobs</title>" + _HEAD + "</head><body>\n<h1>abcns jobs</h1>\n"
         "<table><thead><tr><th>job</th><th>name</th><th>status</th><th>population</th><th>epsilon</th>"
         "<th>simulations</th></tr></thead>\n<tbody id=\"jobs\"></tbody></table>\n<p id=\"error\"></p>\n"
         f"<script>{INDEX_JS}</script></body></html>")

VIEW = ("<!doctype html><html><head><title>abcns job</title>" + _HEAD + r"""</head><body>
<h1>job <span id="job"></span> <small id="name"></small></h1>
<div class="kv card"><span>status <b id="status">-</b></span><span>population <b id="population">-</b></span>
<span>tolerance <b id="epsilon">-</b><b id="eps-unit"></b></span><span>acceptance <b id="acceptance">-</b></span>
<span>simulations <b id="simulations">-</b></span><span>elapsed <b id="elapsed">-</b> s</span>
<span>leading model <b id="leader">-</b></span><span>answer read at <b id="answer-at">-</b></span><span>runs <b id="placement">-</b></span><span>workers <b id="workers">-</b></span><span>cluster busy (last minute) <b id="utilization">-</b></span><span>efficiency <b id="efficiency">-</b></span></div>
<ul id="warnings"></ul>
<div class="grid gap">
 <div class="card"><h2>tolerance per population (log scale)</h2><svg id="eps"></svg></div>
 <div class="card"><h2>acceptance rate per population</h2><svg id="acc"></svg></div>
 <div class="card"><h2>model probabilities per population (dashed: where the answer is read)</h2><svg id="probs"></svg><div id="legend"></div></div>
 <div class="card"><h2>marginals of the leading model (last population; particles per bar)</h2><div id="hists"></div></div>
 <div class="card"><h2>cluster workers per population</h2><svg id="workers-chart"></svg></div>
</div>
<p id="error"></p>
""" + f"<script>{VIEW_JS}</script></body></html>")

#: the pages' icon (/favicon.ico): the tolerance falling, in the charts' colour
FAVICON = ('<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 16 16"><rect width="16" height="16" rx="3" fill="#fff"/>'
           '<path d="M2 3 L6 8 L10 11 L14 12" fill="none" stroke="' + MODEL_COLOURS[0] + '" stroke-width="2"/></svg>')

# only these scripts and this style run; fetch only to the service; no frames, forms or base
CSP = (f"default-src 'none'; script-src {_hash(COMMON_JS)} {_hash(INDEX_JS)} {_hash(VIEW_JS)}; style-src {_hash(STYLE)}; "
       "connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")

# Swagger UI from the swagger-ui-bundle-v2 wheel (served by the app under /docs/assets/);
# its own inline styles need style-src 'unsafe-inline', its scripts are ours and its bundle
DOCS_INIT = ('window.ui = SwaggerUIBundle({url: "/openapi.json", dom_id: "#swagger-ui", deepLinking: true, '
             'validatorUrl: null, presets: [SwaggerUIBundle.presets.apis], layout: "BaseLayout"});')
DOCS = ('<!doctype html><html><head><meta charset="utf-8"><title>abcns API</title>'
        '<link rel="stylesheet" href="/docs/assets/swagger-ui.css"><link rel="icon" href="/docs/assets/favicon-32x32.png">'
        '</head><body><div id="swagger-ui"></div><script src="/docs/assets/swagger-ui-bundle.js"></script>'
        f"<script>{DOCS_INIT}</script></body></html>")
DOCS_CSP = (f"default-src 'none'; script-src 'self' {_hash(DOCS_INIT)}; style-src 'self' 'unsafe-inline'; "
            "img-src 'self' data:; connect-src 'self'; font-src 'self' data:; base-uri 'none'; form-action 'none'; "
            "frame-ancestors 'none'")

# ---------------------------------------------------------------------------- a study (docs/studies.md)
STUDY_JS = r"""
const studyId = location.pathname.split("/")[2];
text("study", studyId.slice(0, 8));
const fixed = (x, d) => (x === null || x === undefined) ? "-" : x.toFixed(d);
function cell(c, r) { return el("td", {}, String(c) + " (" + fixed(r, 2) + ")"); }
async function refresh() {
  try {
    const s = await getJSON(`/studies/${studyId}`);
    text("progress", `${s.finished} of ${s.datasets} finished`);
    text("counts", Object.entries(s.counts).map(([k, v]) => `${k} ${v}`).join(", "));
    const c = s.confusion_matrix;
    document.getElementById("confusion-head").replaceChildren(el("tr", {}, el("th", {}, "true \\ chosen"), ...c.models.map(m => el("th", {}, m))));
    document.getElementById("confusion").replaceChildren(...c.models.map((m, i) => el("tr", {}, el("th", {}, m), ...c.counts[i].map((n, j) => cell(n, c.rates[i][j])))));
    const cal = s.calibration || {};
    text("ece", cal.ece === null || cal.ece === undefined ? "-" : fixed(cal.ece, 3) + (cal.ece_interval ? ` [${fixed(cal.ece_interval[0], 3)}, ${fixed(cal.ece_interval[1], 3)}]` : ""));
    const all = (s.coverage || {}).all || {};
    text("cover", all.n ? `50 %: ${fixed(all.cover50, 3)}, 95 %: ${fixed(all.cover95, 3)} of ${all.n} pairs` : "-");
    text("error", "");
    if (!s.done) setTimeout(refresh, 2000);
  } catch (e) { text("error", String(e)); setTimeout(refresh, 5000); }
}
refresh();
"""

STUDY = ("<!doctype html><html><head><title>abcns study</title>" + _HEAD + r"""</head><body>
<h1>study <span id="study"></span></h1>
<div class="kv card"><span>data sets <b id="progress">-</b></span><span>jobs <b id="counts">-</b></span>
<span>ECE <b id="ece">-</b></span><span>coverage <b id="cover">-</b></span></div>
<div class="card gap"><h2>confusion matrix: count (row rate)</h2><table><thead id="confusion-head"></thead><tbody id="confusion"></tbody></table></div>
<p id="error"></p>
""" + f"<script>{STUDY_JS}</script></body></html>")
STUDY_CSP = CSP.replace(_hash(VIEW_JS), _hash(STUDY_JS))
