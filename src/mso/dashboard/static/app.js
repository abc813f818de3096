// The mso dashboard page: draws each view pushed by the server (Server-Sent Events on /events)
// and sends relocation and remap requests (POST /api/relocate, /api/remap). Hand-written, no
// library, nothing loaded from elsewhere. Names from the overlay are only ever set as text.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const W = 800, PAD = 60;
let H = 420;  // the drawing's height in the width's units: the panel's own shape (drawTopology)
let view = null;

function el(tag, attrs, ...children) {
  const e = tag.startsWith("svg:") ? document.createElementNS(SVG, tag.slice(4)) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === "text") e.textContent = v; else if (k === "cls") e.setAttribute("class", v);
    else if (k === "fontSize") e.style.fontSize = v;  // (a style attribute: refused by the page's CSP)
    else e.setAttribute(k, v);
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

// robots closer than their labels need are pushed apart (a few rounds of pairwise repulsion,
// deterministic): close robots keep their arrangement and never overlap
const MIN_GAP = 130;
function spread(pos) {
  const ids = Object.keys(pos).sort();
  for (let round = 0; round < 60; round++) {
    let moved = false;
    for (let i = 0; i < ids.length; i++) for (let j = i + 1; j < ids.length; j++) {
      const a = pos[ids[i]], b = pos[ids[j]];
      let dx = b[0] - a[0], dy = b[1] - a[1];
      let d = Math.hypot(dx, dy);
      if (d >= MIN_GAP) continue;
      if (d < 1e-6) { dx = 1; dy = 0.3; d = Math.hypot(dx, dy); }
      const push = (MIN_GAP - d) / 2 + 0.5;
      a[0] -= (dx / d) * push; a[1] -= (dy / d) * push;
      b[0] += (dx / d) * push; b[1] += (dy / d) * push;
      moved = true;
    }
    if (!moved) break;
  }
  return pos;
}

// vertex names under a robot, as many as the panel's height gives room for (at least 4); the
// rest as "+N more" (all in its title)
let MAX_LABELS = 4;

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
  // the panel's shape decides the drawing's: a line of robots in a tall panel gets its chains
  // spread apart and every vertex named, not a thin strip above an empty box
  const box = svg.getBoundingClientRect();
  const aspect = box.width > 0 && box.height > 0 ? Math.min(1.2, Math.max(0.25, box.height / box.width)) : 0.4;
  H = W * aspect;
  MAX_LABELS = Math.max(4, Math.floor((H / 2 - 60) / 13));
  const pos = spread(layout(v.nodes, v.links));
  // robots, names and bundles drawn u times their least size: as large as the panel's height
  // allows, never so large that the names of neighbouring robots run into each other
  const ps = Object.values(pos);
  let dmin = Infinity;
  for (let i = 0; i < ps.length; i++) for (let j = i + 1; j < ps.length; j++) dmin = Math.min(dmin, Math.hypot(ps[i][0] - ps[j][0], ps[i][1] - ps[j][1]));
  const xspan = ps.length ? Math.max(...ps.map((p) => p[0])) - Math.min(...ps.map((p) => p[0])) : 0;
  const yspan = ps.length ? Math.max(...ps.map((p) => p[1])) - Math.min(...ps.map((p) => p[1])) : 0;
  const labels = Math.min(MAX_LABELS, Math.max(0, ...v.nodes.map((n) => (n.vertices || []).length)));
  const u = Math.max(1, Math.min(2, dmin / MIN_GAP, (0.85 * aspect * (xspan + 140) - yspan) / (100 + 13 * labels)));
  const flat = xspan >= yspan;  // bundles spread across the line the robots make
  const moved = new Set(v.apps.flatMap((app) => Object.keys(app.moved || {})));
  for (const [a, b] of v.links) {
    if (!pos[a] || !pos[b]) continue;
    svg.append(el("svg:line", { x1: pos[a][0], y1: pos[a][1], x2: pos[b][0], y2: pos[b][1], stroke: "#c3c8d0", "stroke-width": 2, "data-link": `${a}-${b}` }));
  }
  const vertexColour = {};
  const all = v.apps.reduce((n, app) => n + app.chains.length, 0);
  let k = 0;
  for (const app of v.apps) for (const c of app.chains) {
    const hosts = [];
    for (const n of c.nodes) if (n && pos[n] && hosts[hosts.length - 1] !== n) hosts.push(n);
    const hops = hosts.length ? [hosts[0]] : [];
    for (let i = 1; i < hosts.length; i++) hops.push(...route(v.routes, hosts[i - 1], hosts[i], pos).slice(1));
    // the chains side by side across the line, centred on the links, 4-10 (times u) apart as
    // the height allows: apart enough to tell one from another, the bundle within the robots'
    // circles (clear of the names above and below them)
    const gap = Math.min(u * Math.max(4, Math.min(10, (H * 0.3) / Math.max(all, 1))), Math.min(20 * u, 60) / Math.max((all - 1) / 2, 1));
    const off = (k++ - (all - 1) / 2) * gap;
    const [ox, oy] = flat ? [0, off] : [off, 0];
    if (hops.length > 1) {
      const pts = hops.map((n) => `${pos[n][0] + ox},${pos[n][1] + oy}`).join(" ");
      svg.append(el("svg:polyline", { points: pts, fill: "none", stroke: c.colour, "stroke-width": 3, "stroke-opacity": 0.8, "stroke-linejoin": "round", "data-chain": `${app.name}/${c.index}` }, el("svg:title", { text: `${app.name} [${c.index}] ${c.name}: ${hops.join(" → ")}` })));
    }
    for (const vx of c.vertices) if (!(vx in vertexColour)) vertexColour[vx] = c.colour;
  }
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const n of v.nodes) {
    const p = pos[n.id];
    if (!p) continue;
    const g = el("svg:g", { "data-node": n.id, cls: "node" + (n.answered ? "" : " gone") });
    const stroke = n.failed ? "#c62828" : n.unreachable ? "#6b7280" : n.parked ? "#b26a00" : "#374151";
    g.append(el("svg:circle", { cls: "robot", cx: p[0], cy: p[1], r: 24 * u, fill: n.answered ? batteryColour(n.battery) : "#e5e7eb", stroke, "stroke-width": n.failed ? 4 : 2, "stroke-dasharray": n.answered && !n.unreachable ? null : "4 3" }));
    if (n.failed) {  // a cross through a failed robot: never mistaken for a live one
      g.append(el("svg:line", { x1: p[0] - 14 * u, y1: p[1] - 14 * u, x2: p[0] + 14 * u, y2: p[1] + 14 * u, stroke: "#c62828", "stroke-width": 3 }));
    }
    g.append(el("svg:text", { x: p[0], y: p[1] + 5 * u, "text-anchor": "middle", cls: "node-label", fontSize: `${14 * u}px`, text: n.id }));
    const last = n.last_battery === null || n.last_battery === undefined ? "" : ` · last ${Math.round(n.last_battery * 100)}%`;
    const sub = !n.answered ? (n.failed ? "failed" : n.unreachable ? "unreachable" : "silent") + last
      : `${n.battery === null ? "wall" : Math.round(n.battery * 100) + "%"} · ${fmt(n.drain_w, 2)} W`;
    g.append(el("svg:text", { x: p[0], y: p[1] - 32 * u, "text-anchor": "middle", cls: "node-sub", fontSize: `${11 * u}px`, text: sub }));
    const names = n.vertices || [];
    const shown = names.length > MAX_LABELS ? names.slice(0, MAX_LABELS - 1) : names;
    shown.forEach((vx, i) => {
      const hot = moved.has(vx);
      g.append(el("svg:text", { x: p[0], y: p[1] + (44 + i * 13) * u, "text-anchor": "middle", cls: "vertex-label" + (hot ? " moved" : ""), fontSize: `${11 * u}px`, fill: hot ? null : vertexColour[vx] || "#374151", "data-vertex": vx, text: hot ? `${vx} ←` : vx }));
    });
    if (shown.length < names.length) {
      const more = names.slice(shown.length);
      const hot = more.some((vx) => moved.has(vx));
      g.append(el("svg:text", { x: p[0], y: p[1] + (44 + shown.length * 13) * u, "text-anchor": "middle", cls: "vertex-label more" + (hot ? " moved" : ""), fontSize: `${11 * u}px`, text: `+${more.length} more` }, el("svg:title", { text: more.join(", ") })));
    }
    if (names.some((vx) => moved.has(vx))) {  // a vertex just moved here: a ring for a few s
      g.append(el("svg:circle", { cx: p[0], cy: p[1], r: 31 * u, fill: "none", cls: "moved-ring" }));
    }
    g.append(el("svg:title", { text: `${n.id}: ${names.join(", ") || "no vertex"}` }));
    svg.append(g);
    x0 = Math.min(x0, p[0] - 70 * u); x1 = Math.max(x1, p[0] + 70 * u);
    y0 = Math.min(y0, p[1] - 48 * u); y1 = Math.max(y1, p[1] + (52 + Math.min(names.length, MAX_LABELS) * 13) * u);
  }
  // the drawing's own extent, in the panel's shape (a line of robots is centred in it)
  if (x1 > x0) {
    const bw = x1 - x0, bh = Math.max(y1 - y0, bw * aspect, 160);
    svg.setAttribute("viewBox", `${x0} ${(y0 + y1 - bh) / 2} ${bw} ${bh}`);
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
    // a robot that does not answer keeps its last battery, greyed: never a full green bar
    const b = n.answered ? n.battery : n.last_battery;
    const known = b !== null && b !== undefined;
    const bar = el("span", { cls: "bar" + (!n.answered ? " gone" : known && b < 0.1 ? " empty" : known && b < 0.3 ? " low" : "") });
    const fill = el("span"); fill.style.width = `${known ? Math.round(b * 100) : n.answered ? 100 : 0}%`;
    bar.append(fill);
    const level = known ? `${(b * 100).toFixed(1)}%` + (n.answered ? "" : " (last)") : n.answered ? "wall" : "-";
    const t = n.traffic || {};
    return el("tr", { "data-node": n.id },
      el("td", { text: n.id }), el("td", { cls, text: state }),
      el("td", {}, bar, level),
      el("td", { cls: "num", text: fmt(n.drain_w, 2) }), el("td", { cls: "num", text: life(n.lifetime_s) }),
      el("td", { cls: "num", text: n.answered ? `${Math.round((n.load || 0) * 100)}%` : "-" }),
      el("td", { cls: "num", text: n.answered ? `${((n.cpu || 0) * 100).toFixed(1)}%` : "-" }),
      el("td", { cls: "num", text: fmt(t.bytes_in, 0) }), el("td", { cls: "num", text: fmt(t.bytes_out, 0) }),
      el("td", { cls: "num", text: fmt(t.bytes_forwarded, 0) }),
      el("td", { cls: "wrap", text: (n.vertices || []).join(", ") }));
  });
  document.querySelector("#nodes tbody").replaceChildren(...rows);
}

// a chain's recent events/s (field 1) or delay (field 2) as a small line, its peak in the title
function spark(history, field, colour) {
  const pts = (history || []).filter((h) => h[field] !== null && h[field] !== undefined);
  const svg = el("svg:svg", { cls: "spark", viewBox: "0 0 90 18", width: 90, height: 18, "aria-hidden": "true" });
  if (pts.length < 2) return svg;
  const t0 = pts[0][0], t1 = pts[pts.length - 1][0], top = Math.max(...pts.map((h) => h[field]), 1e-9);
  const xy = pts.map((h) => `${(88 * (h[0] - t0) / Math.max(t1 - t0, 1e-9) + 1).toFixed(1)},${(17 - 16 * h[field] / top).toFixed(1)}`);
  svg.append(el("svg:polyline", { points: xy.join(" "), fill: "none", stroke: colour, "stroke-width": 1.5 }));
  svg.append(el("svg:title", { text: `last ${Math.round(t1 - t0)} s; peak ${top.toFixed(field === 1 ? 1 : 2)}` }));
  return svg;
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
      el("td", { cls: "num" }, fmt(c.events_per_s, 1), spark(c.history, 1, c.colour)),
      el("td", { cls: "num" }, fmt(c.delay_ms, 2), spark(c.history, 2, c.colour)),
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
  // only what a relocation can move (a chain's interior: never its pinned head or tail), and
  // for it only where it can go (upstream/downstream while a neighbour runs elsewhere; a live
  // node other than its own)
  const movable = app.movable || {};
  setOptions(document.getElementById("relocate-vertex"), Object.keys(movable).map((vx) => [vx, `${vx} (on ${app.placement[vx]})`]));
  const chosen = document.getElementById("relocate-vertex").value;
  const targets = (movable[chosen] || []).map((w) => [w, w]);
  for (const n of v.nodes) if (n.answered && !n.failed && !n.unreachable && n.id !== app.placement[chosen]) targets.push([`node:${n.id}`, n.id]);
  setOptions(document.getElementById("relocate-target"), targets);
  document.getElementById("relocate-go").disabled = !chosen || !targets.length || Boolean(v.ended);
  setOptions(document.getElementById("remap-chain"), app.chains.map((c) => [String(c.index), `[${c.index}] ${c.name}`]));
  // the current node of the chosen vertex, beside the choice
  const vx = document.getElementById("relocate-vertex").value;
  const capable = (app.capable || {})[vx];
  const by = capable ? ` (placed by capability; capable, best first: ${capable.join(", ")})` : "";
  document.getElementById("relocate-vertex").title = vx ? `now on ${app.placement[vx]}${by}` : "";
}

// vertices failing at a rate past the threshold: one red line each, with their last error
function drawAlarms(v) {
  const lines = v.apps.flatMap((app) => (app.alarms || []).map((a) => el("p", { "data-vertex": a.vertex,
    text: `${app.name}: vertex ${a.vertex} on ${a.node} fails ${a.per_s} times a second (${a.errors} errors in all): ${a.last_error || "no error text"}` })));
  document.getElementById("alarms").replaceChildren(...lines);
}

function render(v) {
  view = v;
  document.getElementById("overlay").textContent = v.overlay ? `· ${v.overlay}` : "";
  document.getElementById("clock").textContent = `t = ${fmt(v.t, 0)} s · via ${v.via} · every ${v.interval} s`;
  document.getElementById("error").textContent = v.error ? `status: ${v.error}` : "";
  if (v.ended) {  // the run is over: the last view stays, nothing reconnects
    source.close();
    conn.textContent = "ended"; conn.className = "conn ended";
    document.body.dataset.ended = "true";
    for (const b of document.querySelectorAll("#controls-panel button, #controls-panel select")) b.disabled = true;
  }
  if (!v.nodes) return;
  drawTopology(v); drawNodes(v); drawChains(v); drawTimeline(v); drawControls(v); drawAlarms(v);
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

window.addEventListener("resize", () => view && drawTopology(view));  // the drawing follows the panel's shape
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
source.onerror = () => { if (!document.body.dataset.ended) { conn.textContent = "reconnecting…"; conn.className = "conn down"; } };
source.onmessage = (ev) => render(JSON.parse(ev.data));
