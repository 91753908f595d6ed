"use strict";
const SVGNS = "http://www.w3.org/2000/svg";
const W = 150, H = 44, MIN_SCALE = 0.9;
const MODE = document.body.getAttribute("data-mode");
const ACTIVE = ["RUNNING", "PAUSE_REQUESTED", "PAUSED", "STOPPING"];
let runs = [], current = null, view = null, selected = null, pinned = false;
let busy = false, dirty = false, timer = null, runsTimer = null, robot = null;
let connected = false, cam = null, fitted = null, token = "";
let rec = null, playing = false, playTimer = null, displays = [];
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
function short(s, n) { return s.length > n ? s.slice(0, n - 1) + "\u2026" : s; }
function show(v) { return typeof v === "string" ? v : JSON.stringify(v); }
function pad(n, k) { return String(n).padStart(k, "0"); }
function clock(ms) {
  const d = new Date(ms);
  return pad(d.getHours(), 2) + ":" + pad(d.getMinutes(), 2) + ":" + pad(d.getSeconds(), 2)
    + "." + pad(d.getMilliseconds(), 3);
}
function secs(s) { return s < 10 ? s.toFixed(2) + " s" : s < 100 ? s.toFixed(1) + " s"
  : Math.round(s) + " s"; }
// a tick's time with as many decimals as its step needs (no "0.00 s" twice on a short run)
function tickText(s, step) {
  if (step >= 0.1) return secs(s);
  const d = Math.min(6, Math.ceil(-Math.log10(step)) + (step * 10 ** Math.ceil(-Math.log10(step))
    < 2 ? 1 : 0));
  return s < 1 ? (s * 1000).toFixed(Math.max(0, d - 3)) + " ms" : s.toFixed(d) + " s";
}
function num(v, d) { return typeof v === "number" ? v.toFixed(d) : "\u2013"; }
async function getJSON(url) {
  const r = await fetch(url, {cache: "no-store"});
  if (!r.ok) throw new Error(url + ": HTTP " + r.status);
  return r.json();
}
function active(state) { return ACTIVE.includes(state) || state === "RUNNING"; }

// ---------------------------------------------------------------- runs and the selected run

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
  if (next !== current) { current = next; view = null; selected = null; cam = null; }
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
    const li = el("li", {title: r.name, "data-run": r.name});
    li.append(el("span", {class: "name"}, r.name));
    li.append(el("span", {class: "badge", "data-state": r.state}, r.result || r.state));
    if (r.name === current) li.classList.add("current");
    li.addEventListener("click", () => {
      pinned = true; current = r.name; view = null; selected = null; cam = null;
      history.replaceState(null, "", "#" + encodeURIComponent(r.name));
      renderRuns(); refresh();
    });
    ul.append(li);
  }
}

function refresh() {
  if (MODE !== "live") return;
  if (!timer) timer = setTimeout(() => { timer = null; loadView(); }, 80);
}
async function loadView() {
  if (busy) { dirty = true; return; }
  busy = true;
  let fetched = true;
  try {
    do {
      dirty = false;
      if (!current) { view = null; break; }
      const name = current;
      const data = await getJSON("/api/graphs/" + encodeURIComponent(name));
      if (name === current) view = data;
    } while (dirty);
  } catch (e) {
    // keep the page as it is (the events may have moved it past the last snapshot): the
    // server may be gone (the header says so)
    fetched = false;
  } finally {
    busy = false;
  }
  if (fetched) renderAll();
}
function renderAll() { renderHead(); renderGraph(); renderTimeline(); renderDetails();
  renderControls(); }

function renderHead() {
  $("runname").textContent = view ? view.name : (current || "no graph selected");
  $("runname").setAttribute("title", view ? view.name : "");
  const badge = $("runstate");
  badge.textContent = view ? (view.result ? view.state + " \u00b7 " + view.result : view.state)
    : "";
  badge.setAttribute("data-state", view ? view.state : "");
  $("rundesc").textContent = view ? view.description : "";
  const errs = clear($("errors"));
  if (view) for (const e of view.errors) errs.append(el("li", {}, e));
}

// ---------------------------------------------------------------- the graph: fit, pan, zoom

function applyCam() {
  const svg = $("svg");
  const box = cam || fitted;
  if (box) svg.setAttribute("viewBox", [box.x, box.y, box.w, box.h].join(" "));
}
function fitBox() {
  const pad = 30, gw = view.width + 2 * pad, gh = view.height + 2 * pad;
  const c = $("canvas"), cw = Math.max(c.clientWidth, 50), ch = Math.max(c.clientHeight, 50);
  // fill the panel, but never enlarge more than 1.6 times (a 3-node graph stays readable) nor
  // shrink below MIN_SCALE (the text stays readable: a wide graph starts at its entry, and
  // the rest is a drag away)
  const scale = Math.max(MIN_SCALE, Math.min(1.6, cw / gw, ch / gh));
  const w = cw / scale, h = ch / scale;
  return {x: w >= gw ? -pad - (w - gw) / 2 : -pad, y: h >= gh ? -pad - (h - gh) / 2 : -pad,
    w: w, h: h};
}
function zoomAt(factor, px, py) {
  const box = Object.assign({}, cam || fitted);
  const c = $("canvas");
  const fx = px / c.clientWidth, fy = py / c.clientHeight;
  const w = Math.min(Math.max(box.w * factor, 80), 20000), h = box.h * (w / box.w);
  cam = {x: box.x + (box.w - w) * fx, y: box.y + (box.h - h) * fy, w: w, h: h};
  applyCam();
}
function setupPanZoom() {
  const c = $("canvas");
  let drag = null;
  c.addEventListener("wheel", (ev) => {
    if (!view) return;
    ev.preventDefault();
    const r = c.getBoundingClientRect();
    zoomAt(ev.deltaY > 0 ? 1.15 : 1 / 1.15, ev.clientX - r.left, ev.clientY - r.top);
  }, {passive: false});
  c.addEventListener("pointerdown", (ev) => {
    if (!view || ev.target.closest(".node") || ev.target.closest("#zoom")) return;
    drag = {x: ev.clientX, y: ev.clientY, box: Object.assign({}, cam || fitted)};
    c.classList.add("panning");
  });
  window.addEventListener("pointermove", (ev) => {
    if (!drag) return;
    const k = drag.box.w / c.clientWidth;
    cam = {x: drag.box.x - (ev.clientX - drag.x) * k, y: drag.box.y - (ev.clientY - drag.y) * k,
      w: drag.box.w, h: drag.box.h};
    applyCam();
  });
  window.addEventListener("pointerup", () => { drag = null; c.classList.remove("panning"); });
  $("zoomin").addEventListener("click", () => zoomAt(1 / 1.25, c.clientWidth / 2,
    c.clientHeight / 2));
  $("zoomout").addEventListener("click", () => zoomAt(1.25, c.clientWidth / 2,
    c.clientHeight / 2));
  $("zoomfit").addEventListener("click", () => { cam = null; applyCam(); });
}

function edgePath(a, b, e) {
  const half = (n) => (n.kind === "action" ? W / 2 : 12);
  if (e.back || b.x <= a.x) {
    const low = Math.max(a.y, b.y) + H / 2 + 26;
    return {d: `M${a.x},${a.y + H / 2} C${a.x},${low} ${b.x},${low} ${b.x},${b.y + H / 2 + 6}`,
      mx: (a.x + b.x) / 2, my: low - 4};
  }
  const x1 = a.x + half(a), x2 = b.x - half(b) - 2, mid = (x1 + x2) / 2;
  return {d: `M${x1},${a.y} C${mid},${a.y} ${mid},${b.y} ${x2},${b.y}`, mx: mid,
    my: (a.y + b.y) / 2 - 4};
}

function renderGraph() {
  const svg = clear($("svg"));
  if (!view) return;
  fitted = fitBox();
  applyCam();
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  const defs = sv("defs");
  for (const [id, color] of [["arrow", "#9ca3af"], ["arrow-taken", "#15803d"]]) {
    const marker = sv("marker", {id: id, viewBox: "0 0 10 10", refX: 9, refY: 5,
      markerWidth: 7, markerHeight: 7, orient: "auto-start-reverse"});
    marker.append(sv("path", {d: "M0,0 L10,5 L0,10 z", fill: color}));
    defs.append(marker);
  }
  svg.append(defs);
  const at = {}, labels = [];
  for (const n of view.nodes) at[n.id] = n;
  for (const e of view.edges) {
    const a = at[e.from], b = at[e.to];
    if (!a || !b) continue;
    const path = edgePath(a, b, e);
    const cls = "edge" + (e.required ? "" : " optional") + (e.back ? " back" : "");
    const p = sv("path", {d: path.d, class: cls, "data-status": e.status || "pending",
      "data-from": e.from, "data-to": e.to,
      "marker-end": e.status === "taken" ? "url(#arrow-taken)" : "url(#arrow)"});
    const why = a.result ? " (" + a.result + ")" : "";
    p.append(sv("title", {}, e.from + " \u2192 " + e.to + ": " + (e.status || "pending") + why
      + (e.conditions.length ? "\n" + e.conditions.join("\n") : "")));
    svg.append(p);
    if (e.status === "skipped" || (e.status === "taken" && a.result)) {
      labels.push(sv("text", {x: path.mx, y: path.my, "text-anchor": "middle", class: "elabel"},
        e.status === "skipped" ? "skipped" : a.result));
    }
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
    g.append(sv("title", {}, n.id + (n.actor ? " @" + n.actor : "") + "\n" + (n.state || "")
      + (n.result ? " \u00b7 " + n.result : "")));
    g.append(sv("rect", {x: n.x - W / 2, y: n.y - H / 2, width: W, height: H, rx: 7}));
    g.append(sv("text", {x: n.x, y: n.y - 3, "text-anchor": "middle"}, short(n.label, 19)));
    g.append(sv("text", {x: n.x, y: n.y + 13, "text-anchor": "middle", class: "state"},
      (n.state || "") + (n.result ? " \u00b7 " + n.result : "")));
    g.addEventListener("click", () => { selected = n.id; renderGraph(); renderDetails(); });
    svg.append(g);
  }
  for (const t of labels) svg.append(t);  // over the edges and the boxes, never under them
}

// ---------------------------------------------------------------- the timeline (Gantt chart)

function renderTimeline() {
  const box = clear($("gantt"));
  const line = view && view.timeline;
  if (!line || !line.spans.length) {
    box.append(el("p", {class: "muted"}, view ? "no action has run yet" : "no run selected"));
    $("tlsum").textContent = "";
    return;
  }
  const now = typeof view.now === "number" ? view.now : line.end;
  let t1 = Math.max(line.end !== null ? line.end : now, line.start + 0.001);
  for (const s of line.spans) if (s.end !== null) t1 = Math.max(t1, s.end);
  const t0 = line.start;
  const rows = [];
  for (const s of line.spans) if (!rows.includes(s.node)) rows.push(s.node);
  const labelW = 130, rowH = 20, width = Math.max(box.clientWidth - 4, 300);
  const plotW = width - labelW - 120, height = rows.length * rowH + 22;
  const X = (t) => labelW + ((t - t0) / (t1 - t0)) * plotW;
  const svg = sv("svg", {width: width, height: height, id: "ganttsvg"});
  const ticks = 6;
  for (let i = 0; i <= ticks; i++) {
    const t = t0 + ((t1 - t0) * i) / ticks, x = X(t);
    svg.append(sv("line", {x1: x, x2: x, y1: 0, y2: height - 16, class: "gaxis"}));
    svg.append(sv("text", {x: x, y: height - 4, "text-anchor": "middle", class: "gtime"},
      tickText(t - t0, (t1 - t0) / ticks)));
  }
  rows.forEach((node, i) => {
    const y = i * rowH + 3;
    svg.append(sv("text", {x: labelW - 6, y: y + 12, "text-anchor": "end", class: "glabel"},
      short(node, 19)));
  });
  for (const s of line.spans) {
    const i = rows.indexOf(s.node), y = i * rowH + 3;
    const end = s.end !== null ? s.end : now;
    const x = X(s.start), w = Math.max(X(end) - x, 2);
    const r = sv("rect", {x: x, y: y, width: w, height: rowH - 6, rx: 3, class: "bar",
      "data-state": s.state, "data-node": s.node, "data-open": s.end === null ? "1" : "0"});
    const dur = secs(end - s.start);
    r.append(sv("title", {}, s.node + ": " + s.state + (s.result ? " \u00b7 " + s.result : "")
      + ", " + dur + (s.end === null ? " so far" : "")));
    svg.append(r);
    svg.append(sv("text", {x: x + w + 4, y: y + 11, class: "gtime"},
      dur + (s.result ? " \u00b7 " + s.result : "")));
  }
  if (line.end === null) {
    svg.append(sv("line", {x1: X(now), x2: X(now), y1: 0, y2: height - 16, class: "gnow"}));
  }
  box.append(svg);
  $("tlsum").textContent = line.spans.length + " action runs \u00b7 " + secs(t1 - t0);
}

// ---------------------------------------------------------------- the robot

function mapBounds(pts) {
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const [x, y] of pts) { x0 = Math.min(x0, x); x1 = Math.max(x1, x);
    y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  const span = Math.max(x1 - x0, y1 - y0, 2) + 1;
  return {cx: cx, cy: cy, span: span};
}
function renderMap(r) {
  const svg = clear($("map"));
  const pw = svg.clientWidth || 330, ph = svg.clientHeight || 220;
  svg.setAttribute("viewBox", `0 0 ${pw} ${ph}`);
  const pts = [[0, 0], ...(r.trail || [])];
  if (r.pose) pts.push([r.pose.x, r.pose.y]);
  if (r.goal) pts.push([r.goal.x, r.goal.y]);
  const b = mapBounds(pts);
  const k = Math.min(pw, ph) / b.span;
  const X = (x) => pw / 2 + (x - b.cx) * k, Y = (y) => ph / 2 - (y - b.cy) * k;
  const step = b.span > 12 ? 5 : b.span > 5 ? 1 : 0.5;
  const gx0 = Math.floor((b.cx - pw / 2 / k) / step) * step;
  const gy0 = Math.floor((b.cy - ph / 2 / k) / step) * step;
  for (let x = gx0; X(x) <= pw; x += step) {
    svg.append(sv("line", {x1: X(x), x2: X(x), y1: 0, y2: ph,
      class: Math.abs(x) < 1e-9 ? "axis" : "grid"}));
  }
  for (let y = gy0; Y(y) >= 0; y += step) {
    svg.append(sv("line", {x1: 0, x2: pw, y1: Y(y), y2: Y(y),
      class: Math.abs(y) < 1e-9 ? "axis" : "grid"}));
  }
  svg.append(sv("text", {x: 4, y: ph - 4, class: "maplabel"}, "grid " + step + " m \u00b7 odom"));
  if (r.trail && r.trail.length > 1) {
    svg.append(sv("polyline", {class: "trail",
      points: r.trail.map(([x, y]) => X(x).toFixed(1) + "," + Y(y).toFixed(1)).join(" ")}));
  }
  if (r.goal) {
    const gx = X(r.goal.x), gy = Y(r.goal.y);
    if (r.pose) svg.append(sv("line", {x1: X(r.pose.x), y1: Y(r.pose.y), x2: gx, y2: gy,
      class: "goalline"}));
    svg.append(sv("circle", {cx: gx, cy: gy, r: 7, class: "goal", id: "goal"}));
    svg.append(sv("path", {d: `M${gx - 4},${gy} h8 M${gx},${gy - 4} v8`, class: "goal"}));
  }
  for (const d of displays) {  // a map display in the odometry frame: drawn over the map
    const m = d.panel === "map" && d.messages.length ? d.messages[d.messages.length - 1] : null;
    const p = m && typeof m.latitude !== "number" ? displayPoint(m) : null;
    if (p && m.poses) {
      svg.append(sv("polyline", {class: d.field === "plan" ? "overlay-path overlay-plan"
        : "overlay-path", "data-display": d.name,
        points: trackOf(d).map(([x, y]) => X(x).toFixed(1) + "," + Y(y).toFixed(1)).join(" ")}));
    }
    if (p) svg.append(sv("circle", {class: "overlay", cx: X(p[0]), cy: Y(p[1]), r: 6,
      "data-display": d.name}));
  }
  if (r.pose) {
    const deg = -r.pose.yaw * 180 / Math.PI;
    const g = sv("g", {id: "rover", transform: `translate(${X(r.pose.x)},${Y(r.pose.y)}) `
      + `rotate(${deg})`, "data-x": r.pose.x, "data-y": r.pose.y});
    g.append(sv("path", {d: "M11,0 L-7,-7 L-3,0 L-7,7 z", class: "rover"}));
    svg.append(g);
  }
}
function renderRobot() {
  const box = $("robotbody");
  const r = robot;
  $("robotname").textContent = r ? "Robot \u00b7 " + r.name + (r.loaded ? "" : " (released)")
    : "Robot";
  $("mapbox").hidden = !(r && r.pose);
  $("jointsbox").hidden = !(r && r.joints);
  $("vehiclebox").hidden = !(r && r.vehicle);
  $("healthbox").hidden = !r;
  $("norobot").hidden = !!r;
  if (MODE === "replay") $("norobot").textContent = "No robot readings in this recording.";
  if (!r) return;
  if (r.pose) {
    renderMap(r);
    let text = `x ${num(r.pose.x, 2)} m  y ${num(r.pose.y, 2)} m  yaw `
      + `${num(r.pose.yaw * 180 / Math.PI, 0)}\u00b0`;
    if (r.goal) {
      const left = Math.hypot(r.goal.x - r.pose.x, r.goal.y - r.pose.y);
      text += `\ngoal (${num(r.goal.x, 2)}, ${num(r.goal.y, 2)}) \u00b7 ${num(left, 2)} m left`;
    } else text += "\nno goal";
    $("pose").textContent = text;
  }
  if (r.joints) {
    const jb = clear($("joints"));
    for (const j of r.joints) {
      const row = el("div", {class: "joint", "data-joint": j.name});
      row.append(el("span", {class: "jname", title: j.name}, j.name));
      const bar = el("div", {class: "jbar",
        title: j.min !== null ? `limits ${j.min} .. ${j.max} rad` : "no limits declared"});
      const lo = j.min !== null ? j.min : -Math.PI, hi = j.max !== null ? j.max : Math.PI;
      const f = (v) => Math.min(1, Math.max(0, (v - lo) / (hi - lo))) * 100;
      if (lo < 0 && hi > 0) { const z = el("span", {class: "jzero"}); z.style.left = f(0) + "%";
        bar.append(z); }
      if (typeof j.position === "number") {
        const m = el("span", {class: "jpos"});
        m.style.left = f(j.position) + "%";
        if (j.min !== null && (j.position - lo < 0.05 * (hi - lo) || hi - j.position
          < 0.05 * (hi - lo))) m.classList.add("near");
        bar.append(m);
      }
      row.append(bar, el("span", {class: "jval"}, num(j.position, 2) + " rad"));
      jb.append(row);
    }
  }
  if (r.vehicle) {
    const v = r.vehicle, t = clear($("vehicle"));
    row(t, "position", `${num(v.lat, 6)}, ${num(v.lon, 6)}`);
    row(t, "altitude", num(v.alt, 1) + " m");
    row(t, "mode", v.mode);
    row(t, "armed", v.armed ? "ARMED" : "disarmed");
    row(t, "battery", (v.battery_remaining >= 0 ? v.battery_remaining + " % \u00b7 " : "")
      + num(v.battery_voltage, 1) + " V");
    if (v.status && v.status.length) row(t, "status", v.status[v.status.length - 1]);
  }
  const hl = clear($("health"));
  for (const h of r.health) {
    const li = el("li", {"data-device": h.device});
    li.append(el("span", {class: "dot" + (h.ok ? (h.state === "ACTIVE" ? "" : " warn") : " bad")}));
    li.append(el("strong", {}, h.device), el("span", {class: "badge"}, h.state));
    if (h.message) li.append(el("span", {class: "msg", title: h.message}, h.message));
    hl.append(li);
  }
}
async function pollRobot() {
  if (MODE === "live") {
    try {
      const [r, d] = await Promise.all([getJSON("/api/robot"), getJSON("/api/displays")]);
      robot = r.robot; displays = d.displays;
      renderRobot(); renderDisplays();
    } catch (e) { /* kept */ }
  }
  setTimeout(pollRobot, connected ? 250 : 1000);
}

// ---------------------------------------------------------------- the loaded displays

const LOG_LEVELS = ["", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"];
const COLORS = ["#2f7de1", "#d63b3b", "#2fa84f", "#f59e0b", "#9333ea", "#0891b2", "#64748b"];
// a display message's point on a map: [x, y] (odometry metres, or longitude/latitude)
function displayPoint(m) {
  if (m.poses) return m.poses.length ? displayPoint({pose: m.poses[m.poses.length - 1]}) : null;
  if (m.pose && m.pose.position) return [m.pose.position.x, m.pose.position.y];
  if (m.translation) return [m.translation.x, m.translation.y];
  if (typeof m.latitude === "number") return [m.longitude, m.latitude];
  return null;
}
function numbersIn(text) {
  return (String(text).match(/-?\d+(?:\.\d+)?(?:e-?\d+)?/gi) || []).map(Number);
}
// a small line chart: one polyline per series, the y range from the data
function plot(names, rows) {
  const W0 = 320, H0 = 120;
  const svg = sv("svg", {viewBox: `0 0 ${W0} ${H0}`, preserveAspectRatio: "none",
    class: "plot"});
  let lo = Infinity, hi = -Infinity;
  for (const r of rows) for (const v of r) if (typeof v === "number") {
    lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (!isFinite(lo)) return svg;
  if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
  const X = (i) => rows.length < 2 ? W0 : (i / (rows.length - 1)) * W0;
  const Y = (v) => H0 - 6 - ((v - lo) / (hi - lo)) * (H0 - 12);
  names.forEach((name, k) => {
    const pts = [];
    rows.forEach((r, i) => { if (typeof r[k] === "number") pts.push(X(i).toFixed(1) + ","
      + Y(r[k]).toFixed(1)); });
    svg.append(sv("polyline", {class: "series", "data-series": name, points: pts.join(" "),
      stroke: COLORS[k % COLORS.length]}));
  });
  return svg;
}
function legendOf(names, last) {
  const box = el("div", {class: "legend"});
  names.forEach((name, k) => {
    const s = el("span", {"data-series": name}, name + " " + num(last[k], 2));
    s.style.setProperty("--c", COLORS[k % COLORS.length]);
    box.append(s);
  });
  return box;
}
// a map display's track: a path's poses, else the point of each message kept
function trackOf(d) {
  const last = d.messages.length ? d.messages[d.messages.length - 1] : null;
  if (last && last.poses) return last.poses.map((p) => displayPoint({pose: p})).filter(Boolean);
  return d.messages.map(displayPoint).filter(Boolean);
}
function mapPanel(d) {
  const pts = trackOf(d);
  const svg = sv("svg", {viewBox: "0 0 320 120", class: "track-map"});
  if (!pts.length) return svg;
  const b = mapBounds(pts), k = Math.min(320, 120) / b.span;
  const X = (x) => 160 + (x - b.cx) * k, Y = (y) => 60 - (y - b.cy) * k;
  svg.append(sv("polyline", {class: d.field === "plan" ? "track plan" : "track",
    points: pts.map(([x, y]) => X(x).toFixed(1) + "," + Y(y).toFixed(1)).join(" ")}));
  const [x, y] = pts[pts.length - 1];
  svg.append(sv("circle", {class: "dmark", cx: X(x), cy: Y(y), r: 5, "data-x": x,
    "data-y": y}));
  return svg;
}
// a scene (the world model's items) from above: a square per item with a cube, every name
function scenePanel(last) {
  const svg = sv("svg", {viewBox: "0 0 320 160", class: "scene"});
  const items = (last.entities || []).map((e) => {
    const prim = (e.cubes && e.cubes[0]) || (e.texts && e.texts[0]);
    const p = prim && prim.pose ? prim.pose.position : null;
    return p ? {id: e.id, x: p.x, y: p.y, cube: !!(e.cubes && e.cubes.length)} : null;
  }).filter(Boolean);
  if (!items.length) return svg;
  const b = mapBounds(items.map((i) => [i.x, i.y])), k = Math.min(320, 160) / b.span;
  const X = (x) => 160 + (x - b.cx) * k, Y = (y) => 80 - (y - b.cy) * k;
  for (const i of items) {
    const g = sv("g", {class: "entity", "data-entity": i.id, "data-x": i.x, "data-y": i.y});
    if (i.cube) g.append(sv("rect", {x: X(i.x) - 4, y: Y(i.y) - 4, width: 8, height: 8}));
    g.append(sv("text", {x: X(i.x) + 6, y: Y(i.y) - 6}, i.id));
    svg.append(g);
  }
  return svg;
}
// a laser scan around its sensor: a dot per range, the sensor at the centre
function scanPanel(m) {
  const svg = sv("svg", {viewBox: "-160 -80 320 160", class: "scan"});
  const n = m.ranges.length, far = Math.max(0.5, ...m.ranges.filter((r) => r < 1e6));
  const k = 75 / far;
  svg.append(sv("circle", {cx: 0, cy: 0, r: 3, class: "sensor"}));
  m.ranges.forEach((r, i) => {
    if (!(r < 1e6)) return;  // no return
    const a = m.start_angle + (n > 1 ? (i * (m.end_angle - m.start_angle)) / (n - 1) : 0);
    svg.append(sv("circle", {cx: (r * Math.cos(a) * k).toFixed(1),
      cy: (-r * Math.sin(a) * k).toFixed(1), r: 2.5, class: "ray", "data-range": r}));
  });
  return svg;
}
// bytes from a message's base64 ``data`` (the Foxglove JSON encoding of ``bytes``)
function bytesOf(b64) {
  const s = atob(b64 || ""), a = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) a[i] = s.charCodeAt(i);
  return a;
}
// Foxglove's NumericType (PackedElementField.type): the DataView getter and its bytes
const NUMERIC = {1: ["getUint8", 1], 2: ["getInt8", 1], 3: ["getUint16", 2], 4: ["getInt16", 2],
  5: ["getUint32", 4], 6: ["getInt32", 4], 7: ["getFloat32", 4], 8: ["getFloat64", 8]};
// a packed field's reader: the value of the element starting at byte ``at`` (little endian)
function fieldReader(view, f) {
  const t = f ? NUMERIC[f.type] : null;
  if (!t) return null;
  return (at) => at + f.offset + t[1] <= view.byteLength ? view[t[0]](at + f.offset, true) : NaN;
}
// a heat colour from 0 (low: blue) through amber to 1 (high: red)
const HEAT = [[47, 125, 225], [245, 158, 11], [214, 59, 59]];
function heat(t) {
  const u = Math.max(0, Math.min(1, t)) * 2, i = Math.min(1, Math.floor(u)), f = u - i;
  return HEAT[i].map((c, k) => Math.round(c + (HEAT[i + 1][k] - c) * f));
}
function rangeOf(values) {
  let lo = Infinity, hi = -Infinity;
  for (const v of values) if (Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  return [lo, hi];
}
// a point cloud seen from above (x right, y up): a dot per point coloured by its height,
// the cloud's origin marked; at most MAX_CLOUD points drawn (evenly picked)
const MAX_CLOUD = 2000;
function cloudPanel(m) {
  const svg = sv("svg", {viewBox: "0 0 320 160", class: "cloud"});
  const data = bytesOf(m.data), view = new DataView(data.buffer);
  const by = Object.fromEntries((m.fields || []).map((f) => [f.name, f]));
  const rx = fieldReader(view, by.x), ry = fieldReader(view, by.y), rz = fieldReader(view, by.z);
  const stride = m.point_stride, n = stride > 0 ? Math.floor(data.length / stride) : 0;
  if (!rx || !ry || !n) return [svg, 0];
  const every = Math.max(1, Math.ceil(n / MAX_CLOUD)), pts = [];
  for (let i = 0; i < n; i += every) {
    const at = i * stride, p = [rx(at), ry(at), rz ? rz(at) : 0];
    if (Number.isFinite(p[0]) && Number.isFinite(p[1])) pts.push(p);
  }
  const b = mapBounds([[0, 0], ...pts]), k = Math.min(320, 160) / b.span;
  const X = (x) => 160 + (x - b.cx) * k, Y = (y) => 80 - (y - b.cy) * k;
  const [lo, hi] = rangeOf(pts.map((p) => p[2]));
  svg.append(sv("circle", {cx: X(0), cy: Y(0), r: 3, class: "sensor"}));
  for (const [x, y, z] of pts) {
    const c = heat(hi > lo ? (z - lo) / (hi - lo) : 0.5);
    svg.append(sv("circle", {cx: X(x).toFixed(1), cy: Y(y).toFixed(1), r: 2.5, class: "pt",
      fill: `rgb(${c.join(",")})`, "data-x": x, "data-y": y, "data-z": z}));
  }
  return [svg, n];
}
// a raw image drawn to a canvas, a pixel per pixel (mono8/16, rgb8, bgr8, rgba8, bgra8, 32FC1)
const RAW_CHANNELS = {mono8: 1, "8UC1": 1, rgb8: 3, "8UC3": 3, bgr8: 3, rgba8: 4, bgra8: 4,
  mono16: 2, "16UC1": 2, "32FC1": 4};
function rawPanel(m) {
  const w = m.width, h = m.height, enc = m.encoding, bpp = RAW_CHANNELS[enc];
  if (!bpp || !(w > 0 && h > 0) || w * h > 4096 * 4096) {
    return el("p", {class: "muted"}, "not drawn here: " + enc + " " + w + "\u00d7" + h);
  }
  const data = bytesOf(m.data), view = new DataView(data.buffer);
  const canvas = el("canvas", {class: "draw", width: w, height: h, "data-encoding": enc});
  const ctx = canvas.getContext("2d"), img = ctx.createImageData(w, h), out = img.data;
  let lo = 0, hi = 255;
  if (enc === "32FC1") {
    const vals = [];
    for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
      const at = y * m.step + 4 * x;
      if (at + 4 <= data.length) vals.push(view.getFloat32(at, true));
    }
    [lo, hi] = rangeOf(vals);
  }
  for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
    const at = y * m.step + bpp * x, o = 4 * (y * w + x);
    if (at + bpp > data.length) continue;  // short: left transparent
    let r, g, b, a = 255;
    if (bpp === 1) { r = g = b = data[at]; }
    else if (enc === "mono16" || enc === "16UC1") { r = g = b = view.getUint16(at, true) >> 8; }
    else if (enc === "32FC1") {
      const v = view.getFloat32(at, true);
      r = g = b = Number.isFinite(v) && hi > lo ? Math.round(255 * (v - lo) / (hi - lo)) : 0;
    } else if (enc === "bgr8" || enc === "bgra8") {
      [b, g, r] = [data[at], data[at + 1], data[at + 2]];
      if (bpp === 4) a = data[at + 3];
    } else {
      [r, g, b] = [data[at], data[at + 1], data[at + 2]];
      if (bpp === 4) a = data[at + 3];
    }
    out[o] = r; out[o + 1] = g; out[o + 2] = b; out[o + 3] = a;
  }
  ctx.putImageData(img, 0, 0);
  return canvas;
}
// a grid as a heat map seen from above: a pixel per cell, its first field's value from the
// lowest (blue) to the highest (red), row 0 (the grid's corner) at the bottom; NaN: grey
function gridPanel(m) {
  const data = bytesOf(m.data), view = new DataView(data.buffer);
  const cols = m.column_count, rows = m.row_stride > 0 ? Math.floor(data.length / m.row_stride) : 0;
  const f = (m.fields || []).find((x) => x.name === "value") || (m.fields || [])[0];
  const read = fieldReader(view, f);
  if (!read || !(cols > 0) || !rows || cols * rows > 4096 * 4096) {
    return [el("p", {class: "muted"}, "no cells"), [NaN, NaN]];
  }
  const vals = [];
  for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) {
    vals.push(Number(read(r * m.row_stride + c * m.cell_stride)));
  }
  const [lo, hi] = rangeOf(vals);
  const canvas = el("canvas", {class: "draw", width: cols, height: rows, "data-field": f.name,
    "data-min": lo, "data-max": hi});
  const ctx = canvas.getContext("2d"), img = ctx.createImageData(cols, rows), out = img.data;
  vals.forEach((v, i) => {
    const r = Math.floor(i / cols), c = i % cols, o = 4 * ((rows - 1 - r) * cols + c);
    const rgb = Number.isFinite(v) ? heat(hi > lo ? (v - lo) / (hi - lo) : 0.5) : [229, 231, 235];
    out[o] = rgb[0]; out[o + 1] = rgb[1]; out[o + 2] = rgb[2]; out[o + 3] = 255;
  });
  ctx.putImageData(img, 0, 0);
  return [canvas, [lo, hi]];
}
function panelBody(d) {
  const msgs = d.messages, last = msgs.length ? msgs[msgs.length - 1] : null;
  const out = [];
  if (!last) { out.push(el("p", {class: "muted"}, "no message yet")); return out; }
  if (d.panel === "plot") {
    const names = last.name || [];
    out.push(plot(names, msgs.map((m) => m.position || [])), legendOf(names, last.position));
  } else if (d.panel === "map" && d.field === "plan") {  // the segment from the base to its goal
    const ps = (last.poses || []).map((q) => displayPoint({pose: q}));
    out.push(mapPanel(d), el("pre", {class: "dplan"}, ps.length > 1
      ? `to x ${num(ps[ps.length - 1][0], 2)} m  y ${num(ps[ps.length - 1][1], 2)} m  \u00b7 `
        + num(Math.hypot(ps[ps.length - 1][0] - ps[0][0], ps[ps.length - 1][1] - ps[0][1]), 2)
        + " m to go  (" + last.frame_id + ")" : "no goal"));
  } else if (d.panel === "map") {
    const p = displayPoint(last);
    out.push(mapPanel(d), el("pre", {}, p ? (typeof last.latitude === "number"
      ? `lat ${num(p[1], 6)}  lon ${num(p[0], 6)}` : `x ${num(p[0], 2)} m  y ${num(p[1], 2)} m`)
      + "  (" + (last.frame_id || last.parent_frame_id || "") + ")" : ""));
  } else if (d.panel === "scan") {
    out.push(scanPanel(last), el("pre", {}, last.ranges.length + " ranges \u00b7 "
      + num(last.start_angle * 180 / Math.PI, 0) + "\u00b0 to "
      + num(last.end_angle * 180 / Math.PI, 0) + "\u00b0 \u00b7 frame " + last.frame_id));
  } else if (d.panel === "image") {
    const fmt = last.format === "jpeg" ? "jpeg" : "png";
    out.push(el("img", {class: "dimage", alt: d.name, src: `data:image/${fmt};base64,${last.data}`}),
      el("pre", {}, fmt + " \u00b7 frame " + last.frame_id));
  } else if (d.panel === "cloud") {
    const [svg, n] = cloudPanel(last);
    out.push(svg, el("pre", {}, n + " points \u00b7 frame " + last.frame_id));
  } else if (d.panel === "rawimage") {
    out.push(rawPanel(last), el("pre", {}, last.encoding + " " + last.width + "\u00d7"
      + last.height + " \u00b7 frame " + last.frame_id));
  } else if (d.panel === "grid") {
    const [canvas, [lo, hi]] = gridPanel(last), size = last.cell_size || {};
    out.push(canvas, el("pre", {}, last.column_count + " columns \u00b7 "
      + num(size.x, 2) + " m cells \u00b7 " + num(lo, 2) + " to " + num(hi, 2)
      + " \u00b7 frame " + last.frame_id));
  } else if (d.panel === "scene") {
    out.push(scenePanel(last), el("pre", {}, (last.entities || []).length + " items"));
  } else if (d.panel === "log") {
    const ul = el("ul", {class: "dlog"});
    for (const m of msgs.slice(-30).reverse()) {
      ul.append(el("li", {}, (LOG_LEVELS[m.level] || m.level) + " " + m.name + ": "
        + m.message));
    }
    out.push(ul);
  } else if (d.panel === "text") {
    const series = msgs.map((m) => numbersIn(m.data !== undefined ? m.data : show(m))[0]);
    if (series.filter((v) => typeof v === "number").length > 1) {
      out.push(plot(["value"], series.map((v) => [v])));
    }
    const head = last.component ? last.component + (last.robot ? " @" + last.robot : "")
      + " \u00b7 " + last.size + " bytes\n" : "";
    out.push(el("pre", {class: "ddata"}, head + (last.data !== undefined ? last.data
      : show(last))));
  } else {
    const t = el("table");
    for (const [k, v] of Object.entries(last)) if (k !== "timestamp") row(t, k, show(v));
    out.push(t);
  }
  return out;
}
function renderDisplays() {
  const box = $("displaylist");
  $("displays").hidden = !displays.length;
  const names = new Set(displays.map((d) => d.name));
  for (const p of [...box.children]) {
    if (!names.has(p.getAttribute("data-display"))) p.remove();  // released: its panel goes
  }
  for (const d of displays) {
    let p = [...box.children].find((c) => c.getAttribute("data-display") === d.name);
    if (!p) {
      p = el("div", {class: "display", "data-display": d.name});
      box.append(p);
    }
    p.setAttribute("data-panel", d.panel);
    p.setAttribute("data-kind", d.kind);
    clear(p);
    const h = el("h3", {title: d.topic}, d.name);
    h.append(el("span", {class: "dkind"}, d.kind + " \u00b7 " + d.count + " messages"));
    p.append(h, ...panelBody(d));
  }
}

// ---------------------------------------------------------------- the selected action

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
  row(t, "state", (node.state || "") + (node.result ? " \u00b7 " + node.result : ""));
  row(t, "type", node.type);
  if (node.actor) row(t, "actor", node.actor);
  if (node.description) row(t, "description", node.description);
  for (const [k, v] of Object.entries(node.inputs || {})) {
    row(t, k, v.value === undefined || v.value === null ? "(" + v.type + ", not set)"
      : show(v.value));
  }
  box.append(t);
  const resources = node.resources || [], logs = node.logs || [];
  box.append(el("h3", {}, "Resources held (" + resources.length + ")"));
  const res = el("ul", {id: "resources"});
  if (!resources.length) res.append(el("li", {class: "muted"}, "none"));
  for (const r of resources) {
    const li = el("li", {"data-resource": r.resource});
    li.append(el("strong", {}, r.server), document.createTextNode(" "));
    li.append(el("code", {}, show(r.request)));
    const flags = [r.exclusive ? "exclusive" : "", r.suspended ? "suspended" : "",
      r.failed ? "FAILED" : ""].filter(Boolean).join(", ");
    li.append(el("div", {class: "muted"}, "resource " + r.resource + (flags ? " \u00b7 "
      + flags : "")));
    res.append(li);
  }
  box.append(res);
  box.append(el("h3", {}, "Log (" + logs.length + ", newest first)"));
  const log = el("ul", {id: "log"});
  if (!logs.length) log.append(el("li", {class: "muted"}, "empty"));
  for (const m of logs) {
    const li = el("li");
    if (typeof m.t === "number") li.append(el("time", {}, clock(m.t)));
    li.append(document.createTextNode(m.message));
    log.append(li);
  }
  box.append(log);
}

// ---------------------------------------------------------------- controls (live mode)

function renderControls() {
  const state = view ? view.state : null;
  const can = !!token && connected;
  $("pause").disabled = !(can && state === "RUNNING");
  $("resume").disabled = !(can && (state === "PAUSED" || state === "PAUSE_REQUESTED" || state === "HALTED"));
  $("stop").disabled = !(can && active(state));
  $("start").disabled = !(can && $("indexed").value);
  $("indexed").disabled = !can;
}
async function post(path, body) {
  const r = await fetch(path, {method: "POST", cache: "no-store",
    headers: {"Content-Type": "application/json", "X-TeMoto-Token": token},
    body: JSON.stringify(body || {})});
  let answer = {};
  try { answer = await r.json(); } catch (e) { /* empty */ }
  if (!r.ok) throw new Error(answer.error || "HTTP " + r.status);
  return answer;
}
async function control(verb) {
  if (!current) return;
  $("notice").textContent = "";
  try {
    await post("/api/graphs/" + encodeURIComponent(current) + "/" + verb);
    $("notice").textContent = verb + " " + current;
  } catch (e) { $("notice").textContent = verb + ": " + e.message; }
  refreshRuns();
}
async function startGraph() {
  const name = $("indexed").value;
  if (!name) return;
  try {
    const answer = await post("/api/start", {graph: name});
    pinned = false; current = answer.run; view = null; cam = null;
    history.replaceState(null, "", location.pathname);
    $("notice").textContent = "started " + answer.run;
  } catch (e) { $("notice").textContent = "start: " + e.message; }
  refreshRuns();
}
async function loadIndexed() {
  try {
    const names = (await getJSON("/api/indexed")).graphs;
    const sel = clear($("indexed"));
    sel.append(el("option", {value: ""}, names.length ? "graph to start\u2026"
      : "no indexed graphs"));
    for (const n of names) sel.append(el("option", {value: n}, n));
  } catch (e) { /* offline */ }
  renderControls();
}
function takeToken() {
  const params = new URLSearchParams(location.search);
  const given = params.get("token");
  if (given) {
    sessionStorage.setItem("temoto-token", given);
    history.replaceState(null, "", location.pathname + location.hash);  // not in the address
  }
  token = sessionStorage.getItem("temoto-token") || "";
  $("lock").textContent = token ? "" : "read-only (open the address printed with its token)";
}

// ---------------------------------------------------------------- events (live mode)

// a run's state once it has ended, from its result (the engine's _end_run)
function endedState(result) {
  return {on_stopped: "STOPPED", on_error: "ERROR", on_halted: "HALTED"}[result] || "FINISHED";
}
function onEvent(ev) {
  if (ev.kind === "hello" || ev.kind === "resync") { loadRuns(); loadIndexed(); return; }
  if (ev.kind === "graph") {
    // the events change the stored snapshots too, so that nothing older is drawn again when
    // the server is gone before the next fetch
    const state = ev.state === "ENDED" ? endedState(ev.result) : ev.state;
    const result = ev.state === "ENDED" ? ev.result : null;
    const r = runs.find((x) => x.name === ev.graph);
    if (r) { r.state = state; r.result = result; renderRuns(); }
    if (view && view.name === ev.graph && ev.state === "ENDED") {
      view.state = state; view.result = result; renderHead(); renderControls();
    }
    refreshRuns();
  }
  if (ev.graph !== current) return;
  if (ev.kind === "node" && view && view.name === ev.graph) {
    const n = view.nodes.find((x) => x.id === ev.node);
    if (n) { n.state = ev.state; if (ev.result) n.result = ev.result; }
  }
  if (ev.kind === "node") {
    for (const g of document.querySelectorAll("#svg .node")) {
      if (g.getAttribute("data-node") !== ev.node) continue;
      g.setAttribute("data-state", ev.state);
      const s = g.querySelector(".state");
      if (s) s.textContent = ev.state + (ev.result ? " \u00b7 " + ev.result : "");
    }
  }
  refresh();
}
function setConn(text, cls) { $("conn").textContent = text; $("conn").className = cls; }
function connect() {
  const source = new EventSource("/api/events");
  source.onopen = () => { connected = true; setConn("live", "live"); renderControls(); };
  source.onerror = () => {
    connected = false;
    setConn("disconnected", "down");  // the last state stays on the page
    renderControls();
  };
  source.onmessage = (m) => { try { onEvent(JSON.parse(m.data)); } catch (e) { /* ignore */ } };
}
function tick() {
  // a running run's timeline grows: fetch it now and then even without events
  if (connected && view && active(view.state)) refresh();
  setTimeout(tick, 1000);
}

// ---------------------------------------------------------------- replay mode

function replayAt(T) {
  const states = {}, results = {}, open = {}, spans = [];
  for (const e of rec.events) {
    if (e.t > T) break;
    states[e.node] = e.state;
    if (e.result) results[e.node] = e.result;
    let s = open[e.node];
    if (e.state === "RUNNING" && !s) {
      s = {node: e.node, start: e.t, end: null, state: e.state, result: null};
      spans.push(s); open[e.node] = s;
    } else if (e.state === "BYPASSED") {
      spans.push({node: e.node, start: e.t, end: e.t, state: e.state, result: null});
    } else if (s) {
      s.state = e.state;
      if (e.state === "STOPPING") s.stopping = true;
      if (!ACTIVE.includes(e.state)) {
        s.end = e.t; delete open[e.node];
        s.result = e.result || (e.state === "ERROR" ? "on_error" : s.stopping ? "on_stopped"
          : null);
        if (s.result) results[e.node] = s.result;
      }
    }
  }
  const ended = rec.result !== null && T >= rec.end;
  const nodes = rec.graph.nodes.map((n) => Object.assign({}, n, n.kind === "action"
    ? {state: states[n.id] || "UNINITIALIZED", result: results[n.id] || null} : {}));
  const at = {};
  for (const n of nodes) at[n.id] = n;
  const edges = rec.graph.edges.map((e) => {
    const p = e.from === "graph_entry" ? "FINISHED" : (at[e.from] || {}).state;
    const c = e.to === "graph_exit" ? "RUNNING" : (at[e.to] || {}).state;
    let status = "pending";
    if (p === "FINISHED" || p === "ERROR") {
      if (c === "BYPASSED") status = "skipped";
      else if (c && !["UNINITIALIZED", "INITIALIZED"].includes(c)) status = "taken";
    }
    return Object.assign({}, e, {status: status});
  });
  view = {name: rec.name, description: rec.graph.description || "", errors: [],
    state: ended ? "FINISHED" : T <= rec.start ? "INITIALIZED" : "RUNNING",
    result: ended ? rec.result : null, nodes: nodes, edges: edges,
    width: rec.graph.width, height: rec.graph.height, now: T,
    timeline: {start: rec.start, end: ended ? rec.end : null, spans: spans}};
  let sample = null;
  const trail = [];
  for (const s of rec.robot) {
    if (s.t > T) break;
    sample = s;
    if (s.pose) trail.push([s.pose.x, s.pose.y]);
  }
  robot = sample ? Object.assign({}, sample, {trail: trail, loaded: true}) : null;
  $("clock").textContent = secs(T - rec.start) + " / " + secs(rec.end - rec.start);
  runs = [{name: rec.name, state: view.state, result: view.result}];
  current = rec.name;
  renderRuns(); renderAll(); renderRobot();
}
function sliderTime() {
  const f = Number($("slider").value) / Number($("slider").max);
  return rec.start + f * (rec.end - rec.start);
}
function play() {
  playing = !playing;
  $("play").textContent = playing ? "pause" : "play";
  if (playTimer) { clearInterval(playTimer); playTimer = null; }
  if (!playing) return;
  const s = $("slider");
  if (Number(s.value) >= Number(s.max)) s.value = "0";
  let last = performance.now();
  playTimer = setInterval(() => {
    const now = performance.now(), dt = (now - last) / 1000 * Number($("speed").value);
    last = now;
    const span = Math.max(rec.end - rec.start, 1e-3);
    const v = Math.min(Number(s.max), Number(s.value) + (dt / span) * Number(s.max));
    s.value = String(v);
    replayAt(sliderTime());
    if (v >= Number(s.max)) play();
  }, 100);
}
async function loadRecording() {
  try { rec = await getJSON("/api/recording"); } catch (e) { setConn("no recording", "down");
    return; }
  setConn("replay", "live");
  $("source").textContent = rec.source;
  $("source").setAttribute("title", rec.source + (rec.notes.length ? "\n" + rec.notes.join("\n")
    : ""));
  // what the reader wants a person to know (a file cut short, lines skipped), on the page
  $("notes").textContent = rec.notes.join(" \u00b7 ");
  $("notes").setAttribute("title", rec.notes.join("\n"));
  $("slider").addEventListener("input", () => replayAt(sliderTime()));
  $("play").addEventListener("click", play);
  $("slider").value = $("slider").max;
  replayAt(rec.end);
}

// ---------------------------------------------------------------- start

function legend() {
  const box = $("legend");
  for (const s of document.body.getAttribute("data-states").split(" ")) {
    box.append(el("span", {class: "swatch", "data-state": s}, s));
  }
  box.append(el("span", {class: "swatch edge-taken"}, "edge taken"));
  box.append(el("span", {class: "swatch edge-skipped"}, "edge skipped"));
}

legend();
setupPanZoom();
window.addEventListener("resize", () => { renderAll(); renderRobot(); });
renderAll();
renderRobot();
if (MODE === "replay") {
  loadRecording();
} else {
  takeToken();
  for (const verb of ["pause", "resume", "stop"]) {
    $(verb).addEventListener("click", () => control(verb));
  }
  $("start").addEventListener("click", startGraph);
  $("indexed").addEventListener("change", renderControls);
  loadRuns();
  connect();
  pollRobot();
  tick();
}
