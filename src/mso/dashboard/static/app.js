// The mso dashboard page: draws each view pushed by the server (Server-Sent Events on /events)
// and sends relocation and remap requests (POST /api/relocate, /api/remap). Hand-written, no
// library, nothing loaded from elsewhere. Names from the overlay are only ever set as text.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const W = 800, H = 420, PAD = 60;
let view = null;

function el(tag, attrs, ...children) {
  const e = tag.startsWith("svg:") ? document.createElementNS(SVG, tag.slice(4)) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === "text") e.textContent = v; else if (k === "cls") e.setAttribute("class", v); else e.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

function fmt(x, digits) { return x === null || x === undefined ? "-" : Number(x).toFixed(digits); }
function life(s) {
  if (s === null || s === undefined) return "-";
  if (s >= 3600) return (s / 3600).toFixed(1) + " h";
  if (s >= 60) return (s / 60).toFixed(0) + " min";
  return s.toFixed(0) + " s";
}
function batteryColour(f) {
  if (f === null || f === undefined) return "#9ca3af";
  const hue = Math.round(120 * Math.max(0, Math.min(1, f)));
  return `hsl(${hue}, 60%, 55%)`;
}

function layout(nodes, links) {
  const pos = {};
  const placed = nodes.filter((n) => n.pos);
  if (placed.length === nodes.length && nodes.length > 0) {
    const xs = placed.map((n) => n.pos[0]), ys = placed.map((n) => n.pos[1]);
    const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
    const s = Math.min((W - 2 * PAD) / Math.max(x1 - x0, 1e-9), (H - 2 * PAD) / Math.max(y1 - y0, 1e-9));
    const ox = (W - s * (x1 - x0)) / 2, oy = (H - s * (y1 - y0)) / 2;
    for (const n of nodes) pos[n.id] = [ox + s * (n.pos[0] - x0), oy + s * (n.pos[1] - y0)];
    return pos;
  }
  // no positions: breadth-first from the first node, one column per hop
  const adj = {};
  for (const n of nodes) adj[n.id] = [];
  for (const [a, b] of links) { if (adj[a] && adj[b]) { adj[a].push(b); adj[b].push(a); } }
  const depth = {}, columns = [];
  for (const start of nodes.map((n) => n.id)) {
    if (start in depth) continue;
    const base = columns.length;
    depth[start] = base;
    const queue = [start];
    while (queue.length) {
      const u = queue.shift();
      (columns[depth[u]] = columns[depth[u]] || []).push(u);
      for (const v of adj[u].sort()) if (!(v in depth)) { depth[v] = depth[u] + 1; queue.push(v); }
    }
  }
  const dx = columns.length > 1 ? (W - 2 * PAD) / (columns.length - 1) : 0;
  columns.forEach((col, i) => col.forEach((id, j) => {
    pos[id] = [columns.length > 1 ? PAD + i * dx : W / 2, (H / (col.length + 1)) * (j + 1)];
  }));
  return pos;
}

// the path events take from node a to node b: a's next hop toward b, then that node's, ...
// (the relays a chain's events cross); a straight line when the routes do not say
function route(routes, a, b, pos) {
  const path = [a];
  let at = a;
  while (at !== b && path.length <= Object.keys(pos).length) {
    const next = ((routes || {})[at] || {})[b];
    if (!next || !pos[next[0]] || path.includes(next[0])) return [a, b];
    at = next[0];
    path.push(at);
  }
  return at === b ? path : [a, b];
}

function drawTopology(v) {
  const svg = document.getElementById("topology");
  svg.replaceChildren();
  const pos = layout(v.nodes, v.links);
  for (const [a, b] of v.links) {
    if (!pos[a] || !pos[b]) continue;
    svg.append(el("svg:line", { x1: pos[a][0], y1: pos[a][1], x2: pos[b][0], y2: pos[b][1], stroke: "#c3c8d0", "stroke-width": 2, "data-link": `${a}-${b}` }));
  }
  const vertexColour = {};
  let k = 0;
  for (const app of v.apps) for (const c of app.chains) {
    const hosts = [];
    for (const n of c.nodes) if (n && pos[n] && hosts[hosts.length - 1] !== n) hosts.push(n);
    const hops = hosts.length ? [hosts[0]] : [];
    for (let i = 1; i < hosts.length; i++) hops.push(...route(v.routes, hosts[i - 1], hosts[i], pos).slice(1));
    const off = ((k++ % 5) - 2) * 3;
    if (hops.length > 1) {
      const pts = hops.map((n) => `${pos[n][0] + off},${pos[n][1] + off}`).join(" ");
      svg.append(el("svg:polyline", { points: pts, fill: "none", stroke: c.colour, "stroke-width": 3, "stroke-opacity": 0.75, "data-chain": `${app.name}/${c.index}` }));
    }
    for (const vx of c.vertices) if (!(vx in vertexColour)) vertexColour[vx] = c.colour;
  }
  for (const n of v.nodes) {
    const p = pos[n.id];
    if (!p) continue;
    const g = el("svg:g", { "data-node": n.id, cls: "node" });
    const stroke = n.failed ? "#c62828" : n.unreachable ? "#6b7280" : n.parked ? "#b26a00" : "#374151";
    g.append(el("svg:circle", { cx: p[0], cy: p[1], r: 24, fill: n.answered ? batteryColour(n.battery) : "#e5e7eb", stroke, "stroke-width": n.failed ? 4 : 2, "stroke-dasharray": n.answered && !n.unreachable ? null : "4 3" }));
    g.append(el("svg:text", { x: p[0], y: p[1] + 5, "text-anchor": "middle", cls: "node-label", text: n.id }));
    const sub = !n.answered ? (n.failed ? "failed" : n.unreachable ? "unreachable" : "silent")
      : `${n.battery === null ? "wall" : Math.round(n.battery * 100) + "%"} · ${fmt(n.drain_w, 2)} W`;
    g.append(el("svg:text", { x: p[0], y: p[1] - 32, "text-anchor": "middle", cls: "node-sub", text: sub }));
    (n.vertices || []).forEach((vx, i) => {
      g.append(el("svg:text", { x: p[0], y: p[1] + 44 + i * 13, "text-anchor": "middle", cls: "vertex-label", fill: vertexColour[vx] || "#374151", "data-vertex": vx, text: vx }));
    });
    svg.append(g);
  }
  const legend = document.getElementById("legend");
  legend.replaceChildren(...v.apps.flatMap((app) => app.chains.map((c) => {
    const sw = el("span", { cls: "swatch" }); sw.style.background = c.colour;
    return el("span", {}, sw, ` ${app.name} [${c.index}] ${c.name}`);
  })));
}

function drawNodes(v) {
  const rows = v.nodes.map((n) => {
    let state = "up", cls = "";
    if (n.failed) { state = "failed"; cls = "state-failed"; }
    else if (n.unreachable) { state = "unreachable (presumed running)"; cls = "state-silent"; }
    else if (!n.answered) { state = "silent"; cls = "state-silent"; }
    else if (n.parked) { state = "parked chain"; cls = "state-parked"; }
    if (n.rejoined) { state += ` (rejoined, incarnation ${n.rejoined})`; cls = cls || "state-rejoined"; }
    const bar = el("span", { cls: "bar" + (n.battery !== null && n.battery < 0.1 ? " empty" : n.battery !== null && n.battery < 0.3 ? " low" : "") });
    const fill = el("span"); fill.style.width = `${n.battery === null || n.battery === undefined ? 100 : Math.round(n.battery * 100)}%`;
    bar.append(fill);
    const t = n.traffic || {};
    return el("tr", { "data-node": n.id },
      el("td", { text: n.id }), el("td", { cls, text: state }),
      el("td", {}, bar, n.battery === null || n.battery === undefined ? "wall" : `${(n.battery * 100).toFixed(1)}%`),
      el("td", { cls: "num", text: fmt(n.drain_w, 2) }), el("td", { cls: "num", text: life(n.lifetime_s) }),
      el("td", { cls: "num", text: n.answered ? `${Math.round((n.load || 0) * 100)}%` : "-" }),
      el("td", { cls: "num", text: n.answered ? `${((n.cpu || 0) * 100).toFixed(1)}%` : "-" }),
      el("td", { cls: "num", text: fmt(t.bytes_in, 0) }), el("td", { cls: "num", text: fmt(t.bytes_out, 0) }),
      el("td", { cls: "num", text: fmt(t.bytes_forwarded, 0) }),
      el("td", { cls: "wrap", text: (n.vertices || []).join(", ") }));
  });
  document.querySelector("#nodes tbody").replaceChildren(...rows);
}

function drawChains(v) {
  const rows = v.apps.flatMap((app) => app.chains.map((c) => {
    const sw = el("span", { cls: "swatch" }); sw.style.background = c.colour;
    const mapping = el("td", { cls: "mapping" });
    c.vertices.forEach((vx, i) => {
      if (i) mapping.append(" → ");
      mapping.append(el("span", { "data-vertex": vx, "data-node": c.nodes[i] || "", text: `${vx}@${c.nodes[i] || "?"}` }));
    });
    return el("tr", { "data-app": app.name, "data-chain": String(c.index) },
      el("td", {}, sw), el("td", { text: app.name }), el("td", { text: `[${c.index}] ${c.name}` }), mapping,
      el("td", { cls: "num", text: fmt(c.events_per_s, 1) }), el("td", { cls: "num", text: fmt(c.delay_ms, 2) }),
      el("td", { cls: c.parked ? "state-parked" : "", text: c.parked ? `parked: ${c.parked}` : "flowing" }));
  }));
  document.querySelector("#chains tbody").replaceChildren(...rows);
}

function drawTimeline(v) {
  const rows = v.timeline.map((e) => el("tr", { cls: e.ok ? e.kind : `${e.kind} failed`, "data-kind": e.kind },
    el("td", { cls: "num", text: fmt(e.t, 1) }), el("td", { text: `${e.kind}: ${e.what}` }), el("td", { cls: "wrap", text: e.why }),
    el("td", { cls: "num", text: fmt(e.took_ms, 2) }),
    el("td", { cls: "num", text: e.lost === null || e.lost === undefined ? "-" : e.lost === 0 ? "none" : String(e.lost) })));
  document.querySelector("#timeline tbody").replaceChildren(...rows);
}

function setOptions(select, options) {
  const key = JSON.stringify(options);
  if (select.dataset.key === key) return;
  const keep = select.value;
  select.replaceChildren(...options.map(([value, label]) => el("option", { value, text: label })));
  select.dataset.key = key;
  if (options.some(([value]) => value === keep)) select.value = keep;
}

function drawControls(v) {
  const appSel = document.getElementById("app");
  setOptions(appSel, v.apps.map((a) => [a.name, a.name]));
  const app = v.apps.find((a) => a.name === appSel.value) || v.apps[0];
  if (!app) return;
  setOptions(document.getElementById("relocate-vertex"), Object.keys(app.vertices).sort().map((vx) => [vx, vx]));
  const targets = [["upstream", "upstream"], ["downstream", "downstream"]];
  for (const n of v.nodes) if (n.answered && !n.failed) targets.push([`node:${n.id}`, n.id]);
  setOptions(document.getElementById("relocate-target"), targets);
  setOptions(document.getElementById("remap-chain"), app.chains.map((c) => [String(c.index), `[${c.index}] ${c.name}`]));
  // the current node of the chosen vertex, beside the choice
  const vx = document.getElementById("relocate-vertex").value;
  const capable = (app.capable || {})[vx];
  const by = capable ? ` (placed by capability; capable, best first: ${capable.join(", ")})` : "";
  document.getElementById("relocate-vertex").title = vx ? `now on ${app.placement[vx]}${by}` : "";
}

function render(v) {
  view = v;
  document.getElementById("overlay").textContent = v.overlay ? `· ${v.overlay}` : "";
  document.getElementById("clock").textContent = `t = ${fmt(v.t, 0)} s · via ${v.via} · every ${v.interval} s`;
  document.getElementById("error").textContent = v.error ? `status: ${v.error}` : "";
  if (!v.nodes) return;
  drawTopology(v); drawNodes(v); drawChains(v); drawTimeline(v); drawControls(v);
  document.body.dataset.updated = String(v.t);
}

async function post(path, body) {
  const out = document.getElementById("control-result");
  out.textContent = "…"; out.className = "";
  try {
    const r = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    const a = await r.json();
    if (!a.ok) { out.textContent = `refused: ${a.error}`; out.className = "bad"; return; }
    out.textContent = a.node !== undefined ? `${a.vertex} now runs on ${a.node} (${a.elapsed_ms.toFixed(2)} ms)`
      : `remapped in ${a.elapsed_ms.toFixed(1)} ms; moved: ${Object.entries(a.moved).map(([k, n]) => `${k}→${n}`).join(", ") || "nothing"}`;
  } catch (e) { out.textContent = `failed: ${e}`; out.className = "bad"; }
}

document.getElementById("app").addEventListener("change", () => view && drawControls(view));
document.getElementById("relocate-vertex").addEventListener("change", () => view && drawControls(view));
document.getElementById("relocate-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const target = document.getElementById("relocate-target").value;
  const body = { app: document.getElementById("app").value, vertex: document.getElementById("relocate-vertex").value };
  if (target.startsWith("node:")) body.target = target.slice(5); else body.direction = target;
  post("/api/relocate", body);
});
document.getElementById("remap-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  post("/api/remap", { app: document.getElementById("app").value, chains: [Number(document.getElementById("remap-chain").value)] });
});
document.getElementById("remap-all").addEventListener("click", () => post("/api/remap", { app: document.getElementById("app").value, all: true }));

const conn = document.getElementById("conn");
const source = new EventSource("/events");
source.onopen = () => { conn.textContent = "live"; conn.className = "conn up"; };
source.onerror = () => { conn.textContent = "reconnecting…"; conn.className = "conn down"; };
source.onmessage = (ev) => render(JSON.parse(ev.data));
