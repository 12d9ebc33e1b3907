// clscatter relighting page: plain JavaScript, no build step, no outside resources.
//
// The page keeps at most one drag request in flight: while one is being rendered, newer
// drag positions wait here (only the newest is kept) and go out when its frame (or its
// cancellation) arrives. Typed values and the end of a drag are sent at once; the server
// then cancels whatever it is rendering for this page. So the server never queues work.
"use strict";

const $ = (id) => document.getElementById(id);
const canvas = $("frame");
const ctx = canvas.getContext("2d");
const handles = $("handles");

let ws = null;
let page = null;
let state = null;          // scene state from the server (camera, lights, medium, ...)
let reqId = 0;
let inflight = null;       // id of the drag request being rendered
let queued = null;         // {changes: Map(key -> "key=value"), mode}
let dragging = null;       // what the pointer is dragging, if anything
let frames = 0, finals = 0;
let finalCurrent = false;  // the shown image is the full render of the current settings
let lightIndex = 0;
let wheelTimer = null;
let keyframes = [];        // each frame's key=value changes (clscatter serve --keyframes)

// ---- small vector helpers -------------------------------------------------------------
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const len = (a) => Math.sqrt(dot(a, a));
const norm = (a) => mul(a, 1 / len(a));
const finite = (v) => v.every(Number.isFinite);

function fmt(x) { return String(Number(Number(x).toPrecision(6))); }
function fmtVec(v) { return "[" + v.map(fmt).join(", ") + "]"; }
function fmtValue(v) { return Array.isArray(v) ? fmtVec(v) : fmt(v); }

// The renderer's pinhole camera (clscatter/scene/frame.py camera_struct, view_paths.cl):
// dir = forward + fx * right * tan_x + fy * up * tan_y, fx, fy in [-1, 1], y down the image.
function cameraBasis() {
  const c = state.camera;
  const fwd = norm(sub(c.target, c.origin));
  const right = norm(cross(fwd, c.up));
  const up = cross(right, fwd);
  const aspect = c.width / c.height;
  const half = Math.tan((c.fov * Math.PI) / 360);
  const [tx, ty] = c.fov_axis === "x" ? [half, half / aspect] : [half * aspect, half];
  return { o: c.origin, fwd, right, up, tx, ty };
}

function project(p) {          // world point -> [u, v] fractions of the image, or null
  const b = cameraBasis();
  const d = sub(p, b.o);
  const z = dot(d, b.fwd);
  if (z <= 1e-6) return null;
  const fx = dot(d, b.right) / (z * b.tx), fy = dot(d, b.up) / (z * b.ty);
  return [(fx + 1) / 2, (1 - fy) / 2];
}

function rayThrough(u, v) {     // [u, v] fractions -> {o, d}
  const b = cameraBasis();
  const fx = 2 * u - 1, fy = 1 - 2 * v;
  return { o: b.o, d: add(b.fwd, add(mul(b.right, fx * b.tx), mul(b.up, fy * b.ty))) };
}

function hitPlane(ray, point, normal) {
  const den = dot(ray.d, normal);
  if (Math.abs(den) < 1e-9) return null;
  const t = dot(sub(point, ray.o), normal) / den;
  if (!(t > 0)) return null;
  const p = add(ray.o, mul(ray.d, t));
  return finite(p) ? p : null;
}

function eventUV(ev) {
  const r = canvas.getBoundingClientRect();
  return [(ev.clientX - r.left) / r.width, (ev.clientY - r.top) / r.height];
}

// ---- talking to the server ------------------------------------------------------------
function keyOf(text) { return text.split("=")[0].trim().replace(/\[\s*(\d+)\s*\]/g, ".$1"); }

function mergeInto(map, changes) {
  for (const c of changes) { map.delete(keyOf(c)); map.set(keyOf(c), c); }
  return map;
}

function request(changes, mode) {
  if (mode === "preview" && inflight !== null) {        // wait for the frame in flight
    queued = { changes: mergeInto(queued ? queued.changes : new Map(), changes), mode };
    return;
  }
  if (queued) { changes = [...mergeInto(queued.changes, changes).values()]; queued = null; }
  const id = ++reqId;
  if (mode === "preview") inflight = id;
  finalCurrent = false;
  updateSave();
  send({ type: "set", id, changes, mode });
}

function refine(changes) { request(changes || [], "refine"); }

function release(id) {
  if (inflight !== null && id !== null && id >= inflight) {
    inflight = null;
    if (queued) { const q = queued; queued = null; request([...q.changes.values()], q.mode); }
  }
}

function send(msg) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg)); }

function connect() {
  ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.onmessage = (ev) => onMessage(JSON.parse(ev.data));
  ws.onclose = () => setBusy(false, "disconnected: reload the page");
}

function onMessage(m) {
  switch (m.type) {
    case "hello":
      page = m.page;
      showKeyframes(m.keyframes || []);
      applyState(m.state);
      setBusy(true, "rendering…");
      break;
    case "state":
      applyState(m.state);
      clearError();
      break;
    case "busy":
      setBusy(true, m.level === "preview" ? "preview…" : "refining…");
      break;
    case "frame":
      showFrame(m);
      release(m.id);
      break;
    case "cancelled":
      release(m.id);
      break;
    case "error":
      showError(m);
      release(m.id);
      break;
    case "idle":
      if (m.saveable !== undefined) finalCurrent = m.saveable;
      setBusy(false, "ready");
      break;
  }
}

// ---- keyframes: the slider sets a frame's keys (previews while it moves, full on release)
function showKeyframes(list) {
  keyframes = list;
  const slider = $("frame-slider");
  $("frame-box").classList.toggle("hidden", list.length === 0);
  slider.max = String(Math.max(list.length - 1, 0));
  slider.value = "0";
  $("frame-label").textContent = list.length ? `0 / ${list.length - 1}` : "";
}

$("frame-slider").addEventListener("input", () => {
  const k = Number($("frame-slider").value);
  $("frame-label").textContent = `${k} / ${keyframes.length - 1}`;
  if (keyframes[k]) request(keyframes[k], "preview");
});
$("frame-slider").addEventListener("change", () => {
  const k = Number($("frame-slider").value);
  if (keyframes[k]) request(keyframes[k], "refine");
});

function setBusy(on, text) {
  $("busy").className = on ? "busy" : "idle";
  $("stage").classList.toggle("busy", on);
  $("busy-text").textContent = text;
  document.body.dataset.busy = on ? "1" : "0";
  updateSave();
}

function showError(m) {
  $("error").textContent = m.message;
  if (m.change) {
    const key = keyOf(m.change);
    for (const inp of document.querySelectorAll("input[data-key]"))
      if (inp.dataset.key && keyOf(inp.dataset.key) === key) inp.classList.add("bad");
  }
}

function clearError() {
  $("error").textContent = "";
  for (const inp of document.querySelectorAll("input.bad")) inp.classList.remove("bad");
}

function showFrame(m) {
  const img = new Image();
  img.onload = () => {
    const W = state.camera.width, H = state.camera.height;
    if (canvas.width !== W || canvas.height !== H) { canvas.width = W; canvas.height = H; }
    ctx.imageSmoothingEnabled = true;
    ctx.drawImage(img, 0, 0, W, H);
    frames += 1;
    if (m.final) finals += 1;
    canvas.dataset.frames = String(frames);
    canvas.dataset.finals = String(finals);
    canvas.dataset.level = m.level;
    // a refine frame improves the full frame of the same settings: Save stays as it was
    if (m.level !== "refine") finalCurrent = m.final;
    showStats(m);
    showNotes(m.notes || []);
    placeHandles();
    updateSave();
  };
  img.src = "data:image/png;base64," + m.png;
}

function showStats(m) {
  const s = m.stats;
  $("stats-head").textContent =
    `${m.level} frame ${frames}: ${s.method || "none"} (asked: ${s.requested_method}) · ` +
    `${s.width}x${s.height}, ${s.spp} spp · ${fmt(s.seconds_total)} s`;
  // the plan's passes are named by method ("lsg") and their stages by method and step
  // ("lsg_gather"): a stage ran when its name or its method's prefix is in stages_run
  const ran = new Set(s.stages_run || []);
  const stageRan = (name) => ran.has(name) || [...ran].some((r) => name.startsWith(r + "_"));
  const body = $("stages").querySelector("tbody");
  body.innerHTML = "";
  for (const [name, sec] of Object.entries(s.stages || {})) {
    const tr = document.createElement("tr");
    if (stageRan(name)) tr.className = "ran";
    const a = document.createElement("td"), b = document.createElement("td");
    a.textContent = name; b.textContent = sec === null ? "-" : Number(sec).toFixed(3);
    tr.append(a, b); body.append(tr);
  }
  $("stats-run").textContent = "ran: " + ((s.stages_run || []).join(", ") || "nothing");
  $("stats-reused").textContent = "re-used: " + ((s.reused || []).join(", ") || "nothing");
}

// the plan's notes that leave light out of the image (the command line's
// "clscatter: note: ..." lines): shown above the image while they apply
function showNotes(notes) {
  const box = $("notes");
  box.innerHTML = "";
  for (const text of notes) {
    const li = document.createElement("li");
    li.textContent = "note: " + text;
    box.append(li);
  }
  box.classList.toggle("hidden", notes.length === 0);
  box.dataset.count = String(notes.length);
}

function updateSave() {
  const ok = page !== null && finalCurrent && document.body.dataset.busy !== "1";
  for (const [id, what] of [["save-png", "image.png"], ["save-exr", "image.exr"], ["save-toml", "scene.toml"]]) {
    const a = $(id);
    a.href = page ? `/save/${page}/${what}` : "#";
    a.classList.toggle("disabled", !ok);
  }
}

// ---- the controls ---------------------------------------------------------------------
function applyState(s) {
  state = s;
  $("source").textContent = s.source;
  const sel = $("method");
  sel.innerHTML = "";
  for (const name of s.methods) sel.add(new Option(name, name, false, name === s.method));
  if (!s.methods.includes(s.method)) sel.add(new Option(s.method, s.method, true, true));
  setInput("sigma_s", s.medium.sigma_s);
  setInput("sigma_a", s.medium.sigma_a);
  setInput("g", s.medium.g);
  const li = $("light-index");
  li.innerHTML = "";
  s.lights.forEach((l, i) => li.add(new Option(String(i), String(i), false, i === lightIndex)));
  if (lightIndex >= s.lights.length) lightIndex = 0;
  $("light-box").classList.toggle("hidden", s.lights.length === 0);
  showLight();
  const mats = Object.entries(s.materials).filter(([, m]) => m.type === "dielectric");
  $("material-box").classList.toggle("hidden", mats.length === 0);
  const ms = $("material"), keep = ms.value;
  ms.innerHTML = "";
  for (const [name] of mats) ms.add(new Option(name, name, false, name === keep));
  showMaterial();
  placeHandles();
}

function setInput(id, value, key) {
  const inp = $(id);
  if (key !== undefined) inp.dataset.key = key;
  // a field being typed in keeps its text, unless the server refused it: then the value
  // in use comes back, so a refused value is never shown as if it applied
  if (document.activeElement !== inp || inp.classList.contains("bad"))
    inp.value = value === undefined || value === null ? "" : fmtValue(value);
}

function showLight() {
  const l = state.lights[lightIndex];
  if (!l) return;
  const base = `lights[${lightIndex}]`;
  $("light-type").textContent = l.type;
  const power = l.type === "directional" ? "irradiance" : "intensity";
  $("power-label").textContent = power;
  setInput("light-power", l[power], `${base}.${power}`);
  for (const el of document.querySelectorAll("#light-box .pos")) el.classList.toggle("hidden", !l.position);
  for (const el of document.querySelectorAll("#light-box .tgt")) el.classList.toggle("hidden", l.type !== "spot");
  for (const el of document.querySelectorAll("#light-box .dir")) el.classList.toggle("hidden", l.type !== "directional");
  if (l.position) setInput("light-position", l.position, `${base}.position`);
  if (l.type === "spot") setInput("light-target", l.target, `${base}.target`);
  if (l.type === "directional") { setInput("light-direction", l.direction, `${base}.direction`); drawGizmo(l.direction); }
}

function showMaterial() {
  const name = $("material").value;
  const m = state.materials[name];
  if (m) setInput("ior", m.ior, `materials.${name}.ior`);
}

for (const inp of document.querySelectorAll("input[data-key]")) {
  inp.addEventListener("change", () => {
    if (!inp.dataset.key) return;
    inp.classList.remove("bad");
    request([`${inp.dataset.key}=${inp.value.trim()}`], "full");
  });
}
$("method").addEventListener("change", () => request([`render.method="${$("method").value}"`], "full"));
$("light-index").addEventListener("change", () => { lightIndex = Number($("light-index").value); showLight(); placeHandles(); });
$("material").addEventListener("change", showMaterial);

// handles on the image: the light's position and a spot light's target
function placeHandles() {
  if (!state || dragging) return;          // never pull a handle from under the pointer
  handles.innerHTML = "";
  state.lights.forEach((l, i) => {
    if (l.position) addHandle(i, "position", l.position);
    if (l.type === "spot" && l.target) addHandle(i, "target", l.target);
  });
  // the hint names the controls this scene has: handles for point and spot lights, the
  // direction disc in the side panel for directional ones
  const positioned = state.lights.some((l) => l.position);
  $("hint-light").innerHTML = positioned
    ? "Drag a <b>handle</b> to move a light (shift: along the floor plane)."
    : (state.lights.length
      ? "Turn the light with the <b>direction disc</b> in the side panel."
      : "This scene has no light.");
}

function addHandle(i, what, p) {
  const uv = project(p);
  if (!uv || uv[0] < -0.05 || uv[0] > 1.05 || uv[1] < -0.05 || uv[1] > 1.05) return;
  const h = document.createElement("div");
  h.className = "handle " + what;
  h.dataset.light = String(i);
  h.dataset.what = what;
  h.title = `lights[${i}].${what}: drag (shift: in the horizontal plane)`;
  h.style.left = (100 * uv[0]) + "%";
  h.style.top = (100 * uv[1]) + "%";
  h.addEventListener("pointerdown", (ev) => startHandleDrag(ev, h, i, what));
  handles.append(h);
}

function startHandleDrag(ev, h, i, what) {
  ev.preventDefault(); ev.stopPropagation();
  h.setPointerCapture(ev.pointerId);
  const l = state.lights[i];
  const start = l[what].slice();
  const normal = cameraBasis().fwd;
  dragging = { kind: "light", h, i, what, start, last: null };
  const move = (e) => {
    const ray = rayThrough(...eventUV(e));
    const p = e.shiftKey ? hitPlane(ray, dragging.last || start, [0, 1, 0]) : hitPlane(ray, start, normal);
    if (!p) return;
    dragging.last = p;
    l[what] = p;
    const uv = project(p);
    if (uv) { h.style.left = (100 * uv[0]) + "%"; h.style.top = (100 * uv[1]) + "%"; }
    request([`lights[${i}].${what}=${fmtVec(p)}`], "preview");
  };
  const up = () => {
    h.removeEventListener("pointermove", move);
    h.removeEventListener("pointerup", up);
    const last = dragging && dragging.last;
    dragging = null;
    refine(last ? [`lights[${i}].${what}=${fmtVec(last)}`] : []);
  };
  h.addEventListener("pointermove", move);
  h.addEventListener("pointerup", up);
}

// orbit (drag the image) and dolly (wheel) around the camera's target
$("stage").addEventListener("pointerdown", (ev) => {
  if (ev.target !== canvas || !state) return;
  ev.preventDefault();
  canvas.setPointerCapture(ev.pointerId);
  const c = state.camera;
  dragging = { kind: "orbit", x: ev.clientX, y: ev.clientY, origin: c.origin.slice(), last: null };
});
canvas.addEventListener("pointermove", (ev) => {
  if (!dragging || dragging.kind !== "orbit") return;
  const c = state.camera;
  const up = norm(c.up);
  let off = sub(dragging.origin, c.target);
  off = rotate(off, up, -(ev.clientX - dragging.x) * 0.01);
  const right = norm(cross(off, up));
  const turned = rotate(off, right, (ev.clientY - dragging.y) * 0.01);
  const cosUp = dot(norm(turned), up);
  if (Math.abs(cosUp) < 0.985) off = turned;          // never over the pole
  const o = add(c.target, off);
  if (!finite(o)) return;
  dragging.last = o;
  c.origin = o;
  placeHandles();
  request([`camera.origin=${fmtVec(o)}`], "preview");
});
canvas.addEventListener("pointerup", () => {
  if (!dragging || dragging.kind !== "orbit") return;
  const last = dragging.last;
  dragging = null;
  if (last) refine([`camera.origin=${fmtVec(last)}`]);
});
canvas.addEventListener("wheel", (ev) => {
  if (!state) return;
  ev.preventDefault();
  const c = state.camera;
  const o = add(c.target, mul(sub(c.origin, c.target), Math.exp(Math.sign(ev.deltaY) * 0.1)));
  if (!finite(o)) return;
  c.origin = o;
  placeHandles();
  request([`camera.origin=${fmtVec(o)}`], "preview");
  clearTimeout(wheelTimer);
  wheelTimer = setTimeout(() => refine([`camera.origin=${fmtVec(c.origin)}`]), 300);
}, { passive: false });

function rotate(v, axis, a) {   // Rodrigues
  const c = Math.cos(a), s = Math.sin(a);
  return add(add(mul(v, c), mul(cross(axis, v), s)), mul(axis, dot(axis, v) * (1 - c)));
}

// the directional light's gizmo: the disk is the sky seen from above (x right, z down);
// the dot is where the light travels towards, projected on the ground plane
const gizmo = $("gizmo"), gctx = gizmo.getContext("2d");
function drawGizmo(d) {
  const R = gizmo.width / 2 - 6, cx = gizmo.width / 2, cy = gizmo.height / 2;
  gctx.clearRect(0, 0, gizmo.width, gizmo.height);
  gctx.strokeStyle = "#556"; gctx.beginPath(); gctx.arc(cx, cy, R, 0, 2 * Math.PI); gctx.stroke();
  gctx.beginPath(); gctx.moveTo(cx - R, cy); gctx.lineTo(cx + R, cy); gctx.moveTo(cx, cy - R); gctx.lineTo(cx, cy + R); gctx.stroke();
  const n = norm(d);
  gctx.fillStyle = n[1] <= 0 ? "#fc4" : "#f66";
  gctx.beginPath(); gctx.arc(cx + n[0] * R, cy + n[2] * R, 6, 0, 2 * Math.PI); gctx.fill();
}
gizmo.addEventListener("pointerdown", (ev) => {
  ev.preventDefault();
  gizmo.setPointerCapture(ev.pointerId);
  dragging = { kind: "gizmo", last: null };
  gizmoMove(ev);
});
function gizmoMove(ev) {
  if (!dragging || dragging.kind !== "gizmo") return;
  const l = state.lights[lightIndex];
  if (!l || l.type !== "directional") return;
  const r = gizmo.getBoundingClientRect(), R = r.width / 2 - 6;
  let x = (ev.clientX - r.left - r.width / 2) / R, z = (ev.clientY - r.top - r.height / 2) / R;
  const h = Math.hypot(x, z);
  if (h > 0.97) { x *= 0.97 / h; z *= 0.97 / h; }
  const d = [x, -Math.sqrt(Math.max(0, 1 - x * x - z * z)), z];
  dragging.last = d;
  l.direction = d;
  drawGizmo(d);
  request([`lights[${lightIndex}].direction=${fmtVec(d)}`], "preview");
}
gizmo.addEventListener("pointermove", gizmoMove);
gizmo.addEventListener("pointerup", () => {
  if (!dragging || dragging.kind !== "gizmo") return;
  const last = dragging.last;
  dragging = null;
  if (last) refine([`lights[${lightIndex}].direction=${fmtVec(last)}`]);
});

connect();
