"""The live pages: ``/`` lists the jobs, ``/jobs/{id}/view`` follows one. Plain HTML, SVG
and a small inline script: no build step, nothing fetched from the internet. The script
reads the event stream with ``fetch`` (so it can send the bearer token, which EventSource
cannot) and reconnects with ``Last-Event-ID``. A token is taken from ``#token=...`` in the
address once and kept in the tab's sessionStorage."""

_COMMON = r"""
<meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<style>
 body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;max-width:1100px}
 h1{font-size:1.3em;margin:0 0 .5em} table{border-collapse:collapse} td,th{padding:.25em .7em;border-bottom:1px solid #ddd;text-align:left}
 .grid{display:grid;grid-template-columns:1fr 1fr;gap:1em} .card{border:1px solid #ddd;border-radius:6px;padding:.6em}
 .card h2{font-size:1em;margin:0 0 .3em} .kv span{display:inline-block;margin-right:1.4em} .kv b{font-variant-numeric:tabular-nums}
 svg{width:100%;height:220px} .axis{stroke:#999;stroke-width:1} .lbl{font-size:10px;fill:#555}
 .status-running{color:#b60} .status-finished{color:#070} .status-failed{color:#b00} .status-cancelled{color:#777}
</style>
<script>
const TOKEN_KEY = "abcns-token";
(function(){ const m = location.hash.match(/token=([^&]+)/); if (m) { sessionStorage.setItem(TOKEN_KEY, decodeURIComponent(m[1])); history.replaceState(null, "", location.pathname); } })();
function headers(extra) { const h = Object.assign({}, extra || {}); const t = sessionStorage.getItem(TOKEN_KEY); if (t) h["Authorization"] = "Bearer " + t; return h; }
async function getJSON(url) { const r = await fetch(url, {headers: headers()}); if (!r.ok) throw new Error(url + ": " + r.status); return r.json(); }
function fmt(x, d) { if (x === null || x === undefined) return "-"; if (typeof x !== "number") return String(x); const a = Math.abs(x); return (a !== 0 && (a < 1e-3 || a >= 1e5)) ? x.toExponential(d || 3) : x.toPrecision(d || 4); }
</script>
"""

INDEX = r"""<!doctype html><html><head><title>abcns jobs</title>""" + _COMMON + r"""</head><body>
<h1>abcns jobs</h1>
<table><thead><tr><th>job</th><th>name</th><th>status</th><th>population</th><th>epsilon</th><th>simulations</th></tr></thead>
<tbody id="jobs"></tbody></table>
<p id="error"></p>
<script>
async function refresh() {
  try {
    const jobs = await getJSON("/jobs");
    document.getElementById("jobs").innerHTML = jobs.reverse().map(j => `<tr>
      <td><a href="/jobs/${j.id}/view">${j.id.slice(0, 8)}</a></td><td>${j.name || ""}</td>
      <td class="status-${j.status}">${j.status}</td><td>${j.progress ? j.progress.population : "-"}</td>
      <td>${j.progress ? fmt(j.progress.epsilon) : "-"}</td><td>${j.progress ? j.progress.simulations : "-"}</td></tr>`).join("");
    document.getElementById("error").textContent = "";
  } catch (e) { document.getElementById("error").textContent = String(e); }
}
refresh(); setInterval(refresh, 2000);
</script></body></html>"""

VIEW = r"""<!doctype html><html><head><title>abcns job</title>""" + _COMMON + r"""</head><body>
<h1>job <span id="job"></span> <small id="name"></small></h1>
<div class="kv card"><span>status <b id="status">-</b></span><span>population <b id="population">-</b></span>
<span>epsilon <b id="epsilon">-</b></span><span>acceptance <b id="acceptance">-</b></span>
<span>simulations <b id="simulations">-</b></span><span>elapsed <b id="elapsed">-</b> s</span>
<span>leading model <b id="leader">-</b></span></div>
<div class="grid" style="margin-top:1em">
 <div class="card"><h2>tolerance per population (log)</h2><svg id="eps"></svg></div>
 <div class="card"><h2>acceptance rate per population</h2><svg id="acc"></svg></div>
 <div class="card"><h2>model probabilities per population</h2><svg id="probs"></svg><div id="legend"></div></div>
 <div class="card"><h2>marginals of the leading model (last population)</h2><div id="hists"></div></div>
</div>
<p id="error"></p>
<script>
const jobId = location.pathname.split("/")[2];
document.getElementById("job").textContent = jobId.slice(0, 8);
const pops = [];  // population events
const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf"];
let lastId = 0, ended = false, histPending = false;

function line(svg, series, opts) {
  const W = 500, H = 200, L = 42, B = 18, T = 8;
  svg.setAttribute("viewBox", `0 0 ${W} ${H + B}`);
  const xs = series.flatMap(s => s.points.map(p => p[0])), ys = series.flatMap(s => s.points.map(p => p[1]));
  if (!xs.length) { svg.innerHTML = ""; return; }
  let x0 = Math.min(...xs), x1 = Math.max(...xs); if (x1 === x0) x1 = x0 + 1;
  let y0 = opts.y0 !== undefined ? opts.y0 : Math.min(...ys), y1 = opts.y1 !== undefined ? opts.y1 : Math.max(...ys); if (y1 === y0) y1 = y0 + 1;
  const X = x => L + (x - x0) / (x1 - x0) * (W - L - 5), Y = y => T + (1 - (y - y0) / (y1 - y0)) * (H - T);
  let out = `<line class="axis" x1="${L}" y1="${H}" x2="${W}" y2="${H}"/><line class="axis" x1="${L}" y1="${T}" x2="${L}" y2="${H}"/>`;
  out += `<text class="lbl" x="2" y="${T + 8}">${opts.fmt(y1)}</text><text class="lbl" x="2" y="${H}">${opts.fmt(y0)}</text>`;
  out += `<text class="lbl" x="${L}" y="${H + 14}">${x0}</text><text class="lbl" x="${W - 30}" y="${H + 14}">${x1}</text>`;
  for (const s of series) {
    const d = s.points.map((p, i) => (i ? "L" : "M") + X(p[0]).toFixed(1) + "," + Y(p[1]).toFixed(1)).join("");
    out += `<path d="${d}" fill="none" stroke="${s.color}" stroke-width="1.6"/>`;
  }
  svg.innerHTML = out;
}

function hist(values, label, truthless) {
  const W = 240, H = 90, n = 20;
  let lo = Math.min(...values), hi = Math.max(...values); if (hi === lo) { hi = lo + 1; }
  const counts = new Array(n).fill(0); for (const v of values) counts[Math.min(n - 1, Math.floor((v - lo) / (hi - lo) * n))]++;
  const m = Math.max(...counts), bw = W / n;
  const bars = counts.map((c, i) => `<rect x="${(i * bw).toFixed(1)}" y="${(H - c / m * H).toFixed(1)}" width="${(bw - 1).toFixed(1)}" height="${(c / m * H).toFixed(1)}" fill="#1f77b4"/>`).join("");
  return `<div style="display:inline-block;margin:0 .6em .6em 0"><div class="lbl">${label}: ${fmt(lo)} .. ${fmt(hi)}</div><svg viewBox="0 0 ${W} ${H}" style="width:240px;height:90px">${bars}</svg></div>`;
}

function render() {
  const p = pops[pops.length - 1];
  if (p) {
    document.getElementById("population").textContent = p.population;
    document.getElementById("epsilon").textContent = fmt(p.epsilon);
    document.getElementById("acceptance").textContent = p.acceptance_rate.toFixed(3);
    document.getElementById("simulations").textContent = p.simulations;
    document.getElementById("elapsed").textContent = p.elapsed_s.toFixed(1);
    const lead = Object.entries(p.model_probabilities).sort((a, b) => b[1] - a[1])[0];
    document.getElementById("leader").textContent = lead[0] + " (" + lead[1].toFixed(2) + ")";
  }
  line(document.getElementById("eps"), [{color: COLORS[0], points: pops.map(q => [q.population, Math.log10(q.epsilon)])}],
       {fmt: v => "1e" + v.toFixed(1)});
  line(document.getElementById("acc"), [{color: COLORS[2], points: pops.map(q => [q.population, q.acceptance_rate])}],
       {y0: 0, y1: 1, fmt: v => v.toFixed(1)});
  const names = pops.length ? Object.keys(pops[0].model_probabilities) : [];
  line(document.getElementById("probs"), names.map((nm, i) => ({color: COLORS[i % COLORS.length],
       points: pops.map(q => [q.population, q.model_probabilities[nm]])})), {y0: 0, y1: 1, fmt: v => v.toFixed(1)});
  document.getElementById("legend").innerHTML = names.map((nm, i) => `<span style="color:${COLORS[i % COLORS.length]}">&#9632; ${nm}</span>`).join(" &nbsp; ");
}

async function histograms() {
  if (histPending || !pops.length) return;
  histPending = true;
  try {
    const t = pops[pops.length - 1].population;
    const pop = await getJSON(`/jobs/${jobId}/populations/${t}`);
    const lead = pop.model_probabilities.indexOf(Math.max(...pop.model_probabilities));
    const rows = pop.theta.filter((_, i) => pop.models[i] === lead);
    const names = pop.parameter_names[lead];
    document.getElementById("hists").innerHTML = `<div class="lbl">${pop.model_names[lead]}, population ${t}</div>` +
      names.map((nm, j) => hist(rows.map(r => r[j]), nm)).join("");
  } catch (e) { /* the next population retries */ } finally { histPending = false; }
}

function setStatus(s) { const el = document.getElementById("status"); el.textContent = s; el.className = "status-" + s; }

function handle(ev) {
  if (ev.id) lastId = parseInt(ev.id, 10);
  let data = {}; try { data = JSON.parse(ev.data || "{}"); } catch (e) {}
  if (ev.event === "population") { pops.push(data); render(); histograms(); setStatus("running"); }
  else if (ev.event === "started") setStatus("running");
  else if (ev.event === "queued") setStatus("queued");
  else if (["finished", "failed", "cancelled"].includes(ev.event)) { ended = true; setStatus(ev.event); histograms(); }
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
      document.getElementById("error").textContent = "";
    } catch (e) { document.getElementById("error").textContent = String(e); }
    if (!ended) await new Promise(res => setTimeout(res, 1000));
  }
}

getJSON(`/jobs/${jobId}`).then(j => { document.getElementById("name").textContent = j.name || ""; setStatus(j.status); })
  .catch(e => { document.getElementById("error").textContent = String(e); });
stream();
</script></body></html>"""
