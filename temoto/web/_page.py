"""The live view's page: one HTML document with inline CSS and JavaScript, no external assets.

The script builds every element with ``textContent`` and ``setAttribute`` (never ``innerHTML``),
so graph names, parameters and log lines cannot inject markup. The server sends a Content
Security Policy that allows exactly this script and this style (by hash) and requests to the
same origin. Node colours come from CSS rules on each node's ``data-state`` attribute, so a state
change is one attribute write.
"""

from __future__ import annotations

__all__ = ["CSS", "JS", "STATES", "page"]

#: Node states in legend order, with their fill and text colours.
STATES: tuple[tuple[str, str, str], ...] = (
    ("UNINITIALIZED", "#d9dde3", "#1f2937"),
    ("INITIALIZED", "#bfd3f2", "#1f2937"),
    ("RUNNING", "#2f7de1", "#ffffff"),
    ("PAUSE_REQUESTED", "#fde68a", "#1f2937"),
    ("PAUSED", "#f2b705", "#1f2937"),
    ("STOPPING", "#f59e57", "#1f2937"),
    ("FINISHED", "#2fa84f", "#ffffff"),
    ("BYPASSED", "#b9a6e8", "#1f2937"),
    ("ERROR", "#d63b3b", "#ffffff"),
)

_STATE_RULES = "\n".join(
    f'.node[data-state="{s}"] rect {{ fill: {fill}; }}\n'
    f'.node[data-state="{s}"] text {{ fill: {ink}; }}\n'
    f'.swatch[data-state="{s}"], .badge[data-state="{s}"] {{ background: {fill}; color: {ink}; }}'
    for s, fill, ink in STATES
)

CSS = (
    """
* { box-sizing: border-box; }
body { margin: 0; font: 14px/1.4 system-ui, sans-serif; color: #1f2937; background: #f4f6f9; }
header { display: flex; align-items: center; gap: 12px; padding: 8px 16px;
  background: #1f2937; color: #f9fafb; }
header h1 { font-size: 16px; margin: 0; font-weight: 600; }
#conn { font-size: 12px; padding: 2px 8px; border-radius: 10px; background: #6b7280; }
#conn.live { background: #2fa84f; }
#actor { opacity: .7; font-size: 12px; }
main { display: grid; grid-template-columns: 190px 1fr 300px; gap: 12px; padding: 12px;
  height: calc(100vh - 42px); }
section { background: #fff; border-radius: 6px; box-shadow: 0 1px 2px #0002; overflow: auto;
  padding: 10px 12px; min-height: 0; }
h2 { font-size: 13px; text-transform: uppercase; letter-spacing: .04em; color: #6b7280;
  margin: 4px 0 8px; }
h3 { font-size: 13px; margin: 12px 0 4px; color: #374151; }
#runs { list-style: none; margin: 0; padding: 0; }
#runs li { padding: 6px 8px; border-radius: 4px; cursor: pointer; display: flex;
  justify-content: space-between; gap: 6px; align-items: center; word-break: break-all; }
#runs li:hover { background: #eef2f7; }
#runs li.current { background: #dbe7fb; font-weight: 600; }
.badge { font-size: 11px; padding: 1px 6px; border-radius: 8px; background: #e5e7eb;
  white-space: nowrap; font-weight: 500; }
.badge[data-state="HALTED"], .badge[data-state="STOPPED"] { background: #f59e57; }
#graph { display: flex; flex-direction: column; }
#runhead { display: flex; gap: 10px; align-items: baseline; flex-wrap: wrap; }
#runname { font-size: 16px; font-weight: 600; word-break: break-all; }
#rundesc { color: #6b7280; font-size: 12px; }
#errors { color: #b91c1c; font-size: 12px; margin: 4px 0; padding-left: 18px; }
#canvas { flex: 1; min-height: 0; overflow: auto; border: 1px solid #e5e7eb; border-radius: 4px;
  background: #fbfcfd; display: flex; }
#canvas svg { display: block; margin: auto; }
.node { cursor: pointer; }
.node rect { stroke: #374151; stroke-width: 1; transition: fill .25s; }
.node.selected rect { stroke: #111827; stroke-width: 3; }
.node text { font-size: 12px; pointer-events: none; }
.node .state { font-size: 9px; letter-spacing: .04em; }
.node[data-state="RUNNING"] rect { animation: pulse 1.2s ease-in-out infinite; }
@keyframes pulse { 50% { stroke-width: 4; stroke: #93c5fd; } }
.term circle { fill: #374151; }
.term text { font-size: 11px; fill: #374151; }
.edge { fill: none; stroke: #6b7280; stroke-width: 1.4; }
.edge.optional { stroke-dasharray: 5 4; }
.edge.back { stroke: #9333ea; }
#legend { display: flex; flex-wrap: wrap; gap: 6px; margin-top: 8px; font-size: 11px; }
.swatch { padding: 2px 8px; border-radius: 8px; border: 1px solid #0002; }
table { border-collapse: collapse; width: 100%; font-size: 12px; }
td { border-top: 1px solid #eef0f3; padding: 3px 4px; vertical-align: top;
  word-break: break-all; }
td:first-child { color: #6b7280; white-space: nowrap; word-break: normal; }
#log { list-style: none; margin: 0; padding: 0; font: 12px/1.35 ui-monospace, monospace; }
#log li { padding: 2px 0; border-top: 1px solid #eef0f3; white-space: pre-wrap;
  word-break: break-word; }
#log time { color: #6b7280; margin-right: 6px; }
#resources { list-style: none; margin: 0; padding: 0; font-size: 12px; }
#resources li { padding: 4px 0; border-top: 1px solid #eef0f3; word-break: break-all; }
#resources code { font-size: 11px; }
.muted { color: #9ca3af; font-style: italic; }
"""
    + _STATE_RULES
    + "\n"
)

JS = """
"use strict";
const SVGNS = "http://www.w3.org/2000/svg";
const W = 150, H = 44;
let runs = [], current = null, view = null, selected = null, pinned = false;
let busy = false, dirty = false, timer = null, runsTimer = null;
const $ = (id) => document.getElementById(id);

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
}
function sv(tag, attrs, text) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, String(v));
  if (text !== undefined) e.textContent = text;
  return e;
}
function clear(e) { while (e.firstChild) e.removeChild(e.firstChild); return e; }
function short(s, n) { return s.length > n ? s.slice(0, n - 1) + "\\u2026" : s; }
function show(v) { return typeof v === "string" ? v : JSON.stringify(v); }
async function getJSON(url) {
  const r = await fetch(url, {cache: "no-store"});
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return r.json();
}

function active(state) { return ["RUNNING", "PAUSED", "STOPPING"].includes(state); }
function chooseRun() {
  const names = runs.map((r) => r.name);
  const wanted = decodeURIComponent(location.hash.slice(1));
  if (pinned && names.includes(current)) return current;
  if (wanted && names.includes(wanted)) { pinned = true; return wanted; }
  const here = runs.find((r) => r.name === current);
  if (here && active(here.state)) return current;
  const live = runs.filter((r) => active(r.state));
  if (live.length) return live[live.length - 1].name;
  return names.length ? (names.includes(current) ? current : names[names.length - 1]) : null;
}

async function loadRuns() {
  try {
    const data = await getJSON("/api/graphs");
    runs = data.graphs;
    $("actor").textContent = data.actor ? "actor " + data.actor : "";
  } catch (e) { return; }
  const next = chooseRun();
  if (next !== current) { current = next; view = null; selected = null; }
  renderRuns();
  refresh();
}
function refreshRuns() {
  if (!runsTimer) runsTimer = setTimeout(() => { runsTimer = null; loadRuns(); }, 100);
}

function renderRuns() {
  const ul = clear($("runs"));
  if (!runs.length) ul.append(el("li", {class: "muted"}, "no graph runs yet"));
  for (const r of runs.slice().reverse()) {
    const li = el("li", {title: r.name}, "");
    li.append(el("span", {}, r.name));
    li.append(el("span", {class: "badge", "data-state": r.state}, r.result || r.state));
    if (r.name === current) li.classList.add("current");
    li.addEventListener("click", () => {
      pinned = true; current = r.name; view = null; selected = null;
      history.replaceState(null, "", "#" + encodeURIComponent(r.name));
      renderRuns(); refresh();
    });
    ul.append(li);
  }
}

function refresh() {
  if (!timer) timer = setTimeout(() => { timer = null; loadView(); }, 80);
}
async function loadView() {
  if (busy) { dirty = true; return; }
  busy = true;
  try {
    do {
      dirty = false;
      if (!current) { view = null; break; }
      const name = current;
      const data = await getJSON("/api/graphs/" + encodeURIComponent(name));
      if (name === current) view = data;
    } while (dirty);
  } catch (e) {
    view = null;
  } finally {
    busy = false;
  }
  renderView();
}

function renderView() {
  const svg = clear($("svg"));
  $("runname").textContent = view ? view.name : (current || "no graph selected");
  const badge = $("runstate");
  badge.textContent = view ? (view.result ? view.state + " \\u00b7 " + view.result : view.state)
    : "";
  badge.setAttribute("data-state", view ? view.state : "");
  $("rundesc").textContent = view ? view.description : "";
  const errs = clear($("errors"));
  if (view) for (const e of view.errors) errs.append(el("li", {}, e));
  if (!view) { renderDetails(); return; }
  const pad = 30, vw = view.width + 2 * pad, vh = view.height + 2 * pad;
  // shrink a large graph to fit (down to 40 %, then scroll); never enlarge a small one
  const box = $("canvas");
  const scale = Math.max(0.4, Math.min(1, (box.clientWidth - 4) / vw, (box.clientHeight - 4) / vh));
  svg.setAttribute("width", Math.floor(vw * scale));
  svg.setAttribute("height", Math.floor(vh * scale));
  svg.setAttribute("viewBox", [-pad, -pad, vw, vh].join(" "));
  const defs = sv("defs");
  const marker = sv("marker", {id: "arrow", viewBox: "0 0 10 10", refX: 9, refY: 5,
    markerWidth: 7, markerHeight: 7, orient: "auto-start-reverse"});
  marker.append(sv("path", {d: "M0,0 L10,5 L0,10 z", fill: "#6b7280"}));
  defs.append(marker);
  svg.append(defs);
  const at = {};
  for (const n of view.nodes) at[n.id] = n;
  const half = (n) => (n.kind === "action" ? W / 2 : 12);
  for (const e of view.edges) {
    const a = at[e.from], b = at[e.to];
    if (!a || !b) continue;
    let d;
    if (e.back || b.x <= a.x) {
      const low = Math.max(a.y, b.y) + H / 2 + 26;
      d = `M${a.x},${a.y + H / 2} C${a.x},${low} ${b.x},${low} ${b.x},${b.y + H / 2 + 6}`;
    } else {
      const x1 = a.x + half(a), x2 = b.x - half(b) - 2, mid = (x1 + x2) / 2;
      d = `M${x1},${a.y} C${mid},${a.y} ${mid},${b.y} ${x2},${b.y}`;
    }
    const cls = "edge" + (e.required ? "" : " optional") + (e.back ? " back" : "");
    const p = sv("path", {d: d, class: cls, "marker-end": "url(#arrow)"});
    p.append(sv("title", {}, e.from + " \\u2192 " + e.to +
      (e.conditions.length ? "\\n" + e.conditions.join("\\n") : "")));
    svg.append(p);
  }
  for (const n of view.nodes) {
    if (n.kind !== "action") {
      const g = sv("g", {class: "term", "data-kind": n.kind});
      g.append(sv("circle", {cx: n.x, cy: n.y, r: 10}));
      g.append(sv("text", {x: n.x, y: n.y + 26, "text-anchor": "middle"}, n.label));
      svg.append(g);
      continue;
    }
    const g = sv("g", {class: "node", "data-node": n.id, "data-state": n.state || ""});
    if (n.id === selected) g.classList.add("selected");
    g.append(sv("title", {}, n.id + (n.actor ? " @" + n.actor : "")));
    g.append(sv("rect", {x: n.x - W / 2, y: n.y - H / 2, width: W, height: H, rx: 7}));
    g.append(sv("text", {x: n.x, y: n.y - 3, "text-anchor": "middle"}, short(n.label, 21)));
    g.append(sv("text", {x: n.x, y: n.y + 13, "text-anchor": "middle", class: "state"},
      n.state || ""));
    g.addEventListener("click", () => { selected = n.id; renderView(); });
    svg.append(g);
  }
  renderDetails();
}

function row(table, key, value) {
  const tr = el("tr");
  tr.append(el("td", {}, key), el("td", {}, value));
  table.append(tr);
}
function renderDetails() {
  const box = clear($("details"));
  const node = view && view.nodes.find((n) => n.id === selected && n.kind === "action");
  $("nodename").textContent = node ? node.id : "Action";
  if (!node) {
    box.append(el("p", {class: "muted"}, "Click an action to see its parameters, the resources "
      + "it holds and its log."));
    return;
  }
  const t = el("table");
  row(t, "state", node.state || "");
  row(t, "type", node.type);
  if (node.actor) row(t, "actor", node.actor);
  if (node.description) row(t, "description", node.description);
  for (const [k, v] of Object.entries(node.inputs)) {
    row(t, k, v.value === undefined ? "(" + v.type + ", not set)" : show(v.value));
  }
  box.append(t);
  box.append(el("h3", {}, "Resources held (" + node.resources.length + ")"));
  const res = el("ul", {id: "resources"});
  if (!node.resources.length) res.append(el("li", {class: "muted"}, "none"));
  for (const r of node.resources) {
    const li = el("li", {"data-resource": r.resource});
    li.append(el("strong", {}, r.server), document.createTextNode(" "));
    li.append(el("code", {}, show(r.request)));
    const flags = [r.exclusive ? "exclusive" : "", r.suspended ? "suspended" : "",
      r.failed ? "FAILED" : ""].filter(Boolean).join(", ");
    li.append(el("div", {class: "muted"}, "resource " + r.resource + (flags ? " \\u00b7 "
      + flags : "")));
    res.append(li);
  }
  box.append(res);
  box.append(el("h3", {}, "Log (" + node.logs.length + ", newest first)"));
  const log = el("ul", {id: "log"});
  if (!node.logs.length) log.append(el("li", {class: "muted"}, "empty"));
  for (const m of node.logs) {
    const li = el("li");
    const when = typeof m.t === "number" ? new Date(m.t) : null;
    if (when) li.append(el("time", {}, when.toLocaleTimeString() + "."
      + String(when.getMilliseconds()).padStart(3, "0")));
    li.append(document.createTextNode(m.message));
    log.append(li);
  }
  box.append(log);
}

function onEvent(ev) {
  if (ev.kind === "hello" || ev.kind === "resync") { loadRuns(); return; }
  if (ev.kind === "graph") { refreshRuns(); }
  if (ev.graph !== current) return;
  if (ev.kind === "node") {
    for (const g of document.querySelectorAll("#svg .node")) {
      if (g.getAttribute("data-node") !== ev.node) continue;
      g.setAttribute("data-state", ev.state);
      const s = g.querySelector(".state");
      if (s) s.textContent = ev.state;
    }
  }
  refresh();
}

function connect() {
  const source = new EventSource("/api/events");
  source.onopen = () => { $("conn").textContent = "live"; $("conn").className = "live"; };
  source.onerror = () => {
    $("conn").textContent = "reconnecting\\u2026";
    $("conn").className = "";
  };
  source.onmessage = (m) => { try { onEvent(JSON.parse(m.data)); } catch (e) { /* ignore */ } };
}

function legend() {
  const box = $("legend");
  for (const s of document.body.getAttribute("data-states").split(" ")) {
    box.append(el("span", {class: "swatch", "data-state": s}, s));
  }
}

legend();
window.addEventListener("resize", () => { if (view) renderView(); });
renderView();
loadRuns();
connect();
"""

_BODY = """<header><h1>TeMoto live view</h1><span id="actor"></span>
<span id="conn">connecting</span></header>
<main>
<section><h2>Graph runs</h2><ul id="runs"></ul></section>
<section id="graph">
<div id="runhead"><span id="runname"></span><span class="badge" id="runstate"></span>
<span id="rundesc"></span></div>
<ul id="errors"></ul>
<div id="canvas"><svg id="svg" xmlns="http://www.w3.org/2000/svg"></svg></div>
<div id="legend"></div>
</section>
<section><h2 id="nodename">Action</h2><div id="details"></div></section>
</main>
"""


def page() -> str:
    """The whole HTML document.

    Returns:
        The page (static: the data comes from the JSON API).

    Raises:
        Nothing.
    """
    states = " ".join(s for s, _, _ in STATES)
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        '<link rel="icon" href="data:,">\n'
        "<title>TeMoto live view</title>\n"
        f"<style>{CSS}</style></head>\n"
        f'<body data-states="{states}">\n{_BODY}<script>{JS}</script>\n</body></html>\n'
    )
