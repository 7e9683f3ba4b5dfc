// chatsplat's viewer page: the scene (Spark over three.js, or frames from chatsplat's own
// rasterizer), orbit / pan / zoom / WASD fly, a click to pick an object (tinted red), and a chat
// with three scopes whose answers stream in. Everything it loads comes from the chatsplat binary.
import * as THREE from "three";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);

// ---------------------------------------------------------------- the API
async function failure(r) {
  let msg = `${r.status} ${r.statusText}`;
  let field = null;
  try {
    const e = await r.json();
    msg = e.field ? `${e.field}: ${e.error}` : e.error;
    field = e.field;
  } catch (_) { /* not JSON */ }
  const err = new Error(msg);
  err.field = field;
  return err;
}

async function post(path, body, signal) {
  const r = await fetch(path, {
    method: "POST", headers: { "content-type": "application/json" }, body: JSON.stringify(body), signal,
  });
  if (!r.ok) throw await failure(r);
  return r;
}

// Reads a text/event-stream response, calling onEvent(name, data) per event.
async function readEvents(response, onEvent) {
  const reader = response.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += decoder.decode(value, { stream: true });
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onEvent(name, JSON.parse(data.join("\n")));
    }
  }
}

// ---------------------------------------------------------------- state
const state = {
  scene: null,
  mode: "webgl", // or "server"
  camera: null, // THREE.PerspectiveCamera: the page's camera in the scene's world
  target: new THREE.Vector3(), // orbit centre
  up: new THREE.Vector3(0, 1, 0),
  size: { width: 640, height: 480 }, // the canvas in pixels (what the server renders and picks at)
  selection: null, // {id, name, mask, bbox} from the last pick / select
  found: null, // the last search's reply (/api/find) and the camera it was made at
  hidden: [], // ids of the objects left out of the view (hide), in the order hidden
  keepView: false, // a camera change that keeps the menu's camera (a jump to it)
  splatFormat: "ply", // or "spz" (Niantic's compressed splats), whichever the server makes smaller
  splatsUrl: null, // what the WebGL renderer shows
  converse: true, // questions follow their scope's conversation (the model holds one, or ?converse=1)
  scope: "view",
  histories: { view: [], object: [], scene: [] },
  // per scope, the conversation its next question follows up: {id, key} (key: what it is about)
  conversations: { view: null, object: null, scene: null },
  busy: null, // AbortController of the answer streaming in
  frames: 0,
  lastPickMs: null,
  ready: false,
};

// ---------------------------------------------------------------- cameras
// The camera contract (model/viewer/src/camera.rs): three.js position, quaternion, vertical fov
// and the canvas size.
function apiCamera() {
  const c = state.camera;
  return {
    position: c.position.toArray(),
    quaternion: [c.quaternion.x, c.quaternion.y, c.quaternion.z, c.quaternion.w],
    fov: c.fov, width: state.size.width, height: state.size.height,
  };
}

function setCamera(v) {
  const c = state.camera;
  c.position.fromArray(v.position);
  c.quaternion.set(v.quaternion[0], v.quaternion[1], v.quaternion[2], v.quaternion[3]).normalize();
  c.fov = v.fov;
  c.updateProjectionMatrix();
  c.updateMatrixWorld(true);
  // orbit about the point ahead of the camera at the scene centre's depth
  const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(c.quaternion);
  const centre = new THREE.Vector3().fromArray(state.scene.center);
  const depth = Math.max(centre.clone().sub(c.position).dot(forward), 0.1 * state.scene.radius);
  state.target.copy(c.position).addScaledVector(forward, depth);
  cameraMoved(true);
}

function jump(i) {
  const v = state.scene.views[i];
  if (!v) return;
  state.keepView = true;
  setCamera(v.camera);
  state.keepView = false;
  $("views").value = String(i);
}

// ---------------------------------------------------------------- controls
const drag = { active: false, button: 0, x: 0, y: 0, startX: 0, startY: 0, moved: false };
const keys = new Set();
let settleTimer = null;

function orbit(dx, dy) {
  const c = state.camera;
  const offset = c.position.clone().sub(state.target);
  const yaw = new THREE.Quaternion().setFromAxisAngle(state.up, -dx * 0.005);
  offset.applyQuaternion(yaw);
  const right = new THREE.Vector3().crossVectors(offset, state.up).normalize();
  const pitched = offset.clone().applyQuaternion(new THREE.Quaternion().setFromAxisAngle(right, dy * 0.005));
  // stop short of the poles
  if (Math.abs(pitched.clone().normalize().dot(state.up)) < 0.985) offset.copy(pitched);
  c.position.copy(state.target).add(offset);
  c.up.copy(state.up);
  c.lookAt(state.target);
}

function pan(dx, dy) {
  const c = state.camera;
  const dist = c.position.distanceTo(state.target);
  const scale = (2 * dist * Math.tan((c.fov * Math.PI) / 360)) / state.size.height;
  const right = new THREE.Vector3(1, 0, 0).applyQuaternion(c.quaternion);
  const up = new THREE.Vector3(0, 1, 0).applyQuaternion(c.quaternion);
  const move = right.multiplyScalar(-dx * scale).add(up.multiplyScalar(dy * scale));
  c.position.add(move);
  state.target.add(move);
}

function zoom(delta) {
  const c = state.camera;
  const offset = c.position.clone().sub(state.target);
  const r = state.scene.radius;
  const len = Math.min(Math.max(offset.length() * Math.exp(delta * 0.001), 0.05 * r), 20 * r);
  c.position.copy(state.target).add(offset.setLength(len));
}

function fly(dt) {
  const c = state.camera;
  const speed = 0.5 * state.scene.radius * dt;
  const move = new THREE.Vector3();
  const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(c.quaternion);
  const right = new THREE.Vector3(1, 0, 0).applyQuaternion(c.quaternion);
  if (keys.has("w")) move.add(forward);
  if (keys.has("s")) move.sub(forward);
  if (keys.has("d")) move.add(right);
  if (keys.has("a")) move.sub(right);
  if (keys.has("e")) move.add(state.up);
  if (keys.has("q")) move.sub(state.up);
  if (move.lengthSq() === 0) return false;
  move.setLength(speed);
  c.position.add(move);
  state.target.add(move);
  return true;
}

// Called on every camera change; `settled` when the motion is over (a selection then follows
// the camera and the server draws a full frame).
function cameraMoved(settled) {
  // the menu names a camera of the capture only while the view is that camera's
  if (!state.keepView) $("views").value = "";
  state.camera.updateMatrixWorld(true);
  requestFrame(!settled);
  clearOverlay();
  clearTimeout(settleTimer);
  if (settled) settle();
  else settleTimer = setTimeout(settle, 250);
}

function settle() {
  requestFrame(false);
  if (state.selection) follow();
  else if (state.found) find();
}

function installControls() {
  const el = $("gl");
  el.addEventListener("contextmenu", (e) => e.preventDefault());
  el.addEventListener("pointerdown", (e) => {
    el.setPointerCapture(e.pointerId);
    Object.assign(drag, { active: true, button: e.button, x: e.clientX, y: e.clientY, startX: e.clientX, startY: e.clientY, moved: false });
    el.style.cursor = "grabbing";
  });
  el.addEventListener("pointermove", (e) => {
    if (!drag.active) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (Math.hypot(e.clientX - drag.startX, e.clientY - drag.startY) > 4) drag.moved = true;
    if (!drag.moved) return;
    if (drag.button === 2 || e.shiftKey) pan(dx, dy);
    else orbit(dx, dy);
    cameraMoved(false);
  });
  el.addEventListener("pointerup", (e) => {
    if (!drag.active) return;
    drag.active = false;
    el.style.cursor = "grab";
    if (drag.moved) { cameraMoved(true); return; }
    if (drag.button === 0) {
      const r = el.getBoundingClientRect();
      pick(((e.clientX - r.left) * state.size.width) / r.width, ((e.clientY - r.top) * state.size.height) / r.height);
    }
  });
  el.addEventListener("wheel", (e) => { e.preventDefault(); zoom(e.deltaY); cameraMoved(false); }, { passive: false });
  window.addEventListener("keydown", (e) => {
    if (e.target.closest && e.target.closest("textarea, input, select")) return;
    const k = e.key.toLowerCase();
    if (k === "escape") { clearSelection(); clearFound(); return; }
    if ("wasdqe".includes(k) && k.length === 1) { keys.add(k); e.preventDefault(); }
  });
  window.addEventListener("keyup", (e) => {
    const k = e.key.toLowerCase();
    if (keys.delete(k) && keys.size === 0) cameraMoved(true);
  });
  window.addEventListener("blur", () => keys.clear());
  let last = performance.now();
  const tick = (now) => {
    if (fly(Math.min((now - last) / 1000, 0.1))) cameraMoved(false);
    last = now;
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}

// ---------------------------------------------------------------- drawing
const draw = { renderer: null, scene: null, until: 0, minFrames: 0, serverBusy: false, serverWanted: null, fpsFrames: [] };

function requestFrame(moving) {
  if (state.mode === "webgl") {
    // Spark sorts splats in a worker: keep drawing a moment (and a few frames) after the last change
    draw.until = performance.now() + 1500;
    draw.minFrames = state.frames + 3;
  } else {
    draw.serverWanted = moving ? "preview" : "full";
    serverFrame();
  }
}

async function startWebgl() {
  const { SparkRenderer, SplatMesh } = await import("/vendor/spark.module.min.js");
  const canvas = $("gl");
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(state.size.width, state.size.height, false);
  renderer.setClearColor(new THREE.Color().fromArray(state.scene.background), 1);
  Object.assign(draw, { SparkRenderer, SplatMesh });
  const scene = await splatScene(renderer, state.splatsUrl);
  Object.assign(draw, { renderer, scene });
  renderer.setAnimationLoop((now) => {
    if (now > draw.until && state.frames >= draw.minFrames) return;
    renderer.render(draw.scene, state.camera);
    countFrame(now);
  });
}

// A scene of its own for the splats at `url` (a new one each time the hidden objects change:
// Spark then sorts and draws only what it was loaded with).
async function splatScene(renderer, url) {
  const scene = new THREE.Scene();
  scene.add(new draw.SparkRenderer({ renderer }));
  const mesh = new draw.SplatMesh({ url, fileName: `splats.${state.splatFormat}` });
  scene.add(mesh);
  await mesh.initialized;
  return scene;
}

function countFrame(now) {
  state.frames += 1;
  draw.fpsFrames.push(now);
  while (draw.fpsFrames.length && now - draw.fpsFrames[0] > 2000) draw.fpsFrames.shift();
  if (draw.fpsFrames.length > 1) {
    const span = (draw.fpsFrames[draw.fpsFrames.length - 1] - draw.fpsFrames[0]) / 1000;
    $("fps").textContent = `· ${((draw.fpsFrames.length - 1) / span).toFixed(1)} fps`;
  }
}

// Server frames: low resolution while moving, full when the camera rests; one request at a time,
// the latest camera wins.
async function serverFrame() {
  if (draw.serverBusy || !draw.serverWanted || !state.camera) return;
  const kind = draw.serverWanted;
  draw.serverWanted = null;
  draw.serverBusy = true;
  try {
    const cam = apiCamera();
    if (kind === "preview") {
      const s = Math.min(1, 160 / Math.max(cam.width, cam.height));
      cam.width = Math.max(8, Math.round(cam.width * s));
      cam.height = Math.max(8, Math.round(cam.height * s));
    }
    const r = await post("/api/render", { camera: cam, hidden: state.hidden });
    const url = URL.createObjectURL(await r.blob());
    const img = $("server-frame");
    await new Promise((ok) => { img.onload = ok; img.onerror = ok; img.src = url; });
    if (img.dataset.url) URL.revokeObjectURL(img.dataset.url);
    img.dataset.url = url;
    img.dataset.kind = kind;
    countFrame(performance.now());
  } catch (e) {
    status(`render failed: ${e.message}`);
  } finally {
    draw.serverBusy = false;
    if (draw.serverWanted) serverFrame();
  }
}

function status(text) { $("status").textContent = text; }

// ---------------------------------------------------------------- picking
// Picks render the identity at the page's camera with at most PICK_SIDE pixels on the longest
// side (the same view, fewer pixels: a pick stays near 100 ms on two CPU cores); the mask is drawn
// scaled to the canvas.
const PICK_SIDE = 320;

function pickCamera() {
  const cam = apiCamera();
  const s = Math.min(1, PICK_SIDE / Math.max(cam.width, cam.height));
  cam.width = Math.max(8, Math.round(cam.width * s));
  cam.height = Math.max(8, Math.round(cam.height * s));
  return cam;
}

async function pick(x, y) {
  if (!state.scene.masks) { status("this scene was trained without object masks: nothing to pick"); return; }
  try {
    const camera = pickCamera();
    const [sx, sy] = [camera.width / state.size.width, camera.height / state.size.height];
    const r = await (await post("/api/pick", { camera, x: x * sx, y: y * sy })).json();
    state.lastPickMs = r.ms;
    if (!r.object) { clearSelection(); status(`background (${r.ms.toFixed(0)} ms)`); return; }
    if (state.hidden.includes(r.object.id)) {
      clearSelection();
      status(`the ${r.object.name} is hidden here ("show hidden" brings it back)`);
      return;
    }
    select({ ...r.object, camera });
    status(`picked ${r.object.name} in ${r.ms.toFixed(0)} ms`);
  } catch (e) {
    status(`pick failed: ${e.message}`);
  }
}

// A selection follows the camera: its mask is asked for again once the camera rests.
async function follow() {
  const id = state.selection.id;
  try {
    const camera = pickCamera();
    const r = await (await post("/api/select", { camera, id })).json();
    if (!state.selection || state.selection.id !== id) return;
    if (r.object) select({ ...r.object, camera });
    else status(`${state.selection.name} is not visible from here`);
  } catch (e) {
    status(`selection lost: ${e.message}`);
  }
}

function select(object) {
  const changed = !state.selection || state.selection.id !== object.id;
  state.selection = object;
  drawSelection();
  const b = document.querySelector('[data-scope="object"]');
  b.disabled = false;
  b.textContent = `Object: ${object.name}`;
  b.title = `ask about the ${object.name}`;
  $("download").href = `/api/objects/${object.id}.ply`;
  $("download").textContent = `download ${object.name} (.ply)`;
  $("download-spz").href = `/api/objects/${object.id}.spz`;
  $("download-spz").hidden = !state.scene.splat_bytes.spz;
  $("object-tools").hidden = false;
  if (changed) {
    note("object", `picked: ${object.name}`);
    setScope("object");
  }
}

function clearOverlay() {
  const o = $("overlay");
  o.getContext("2d").clearRect(0, 0, o.width, o.height);
  $("label").hidden = true;
}

function clearSelection() {
  state.selection = null;
  clearOverlay();
  const b = document.querySelector('[data-scope="object"]');
  b.disabled = true;
  b.textContent = "Object";
  $("object-tools").hidden = true;
  if (state.scope === "object") setScope("view");
}

// The paper's display of a picked object: tinted red and outlined, the rest of the view dimmed
// (so that a red object stands out too), its name beside it.
function drawSelection() {
  const s = state.selection;
  const { width, height } = s.mask;
  paintMasks([s.mask], width, height);
  const label = $("label");
  const r = $("overlay").getBoundingClientRect();
  label.textContent = s.name;
  label.style.left = `${(s.bbox[0] * r.width) / width}px`;
  label.style.top = `${(s.bbox[1] * r.height) / height}px`;
  label.hidden = false;
}

// Run-length masks of one width x height view, tinted red and outlined on the dimmed view.
function paintMasks(masks, width, height) {
  const overlay = $("overlay");
  overlay.width = width;
  overlay.height = height;
  const ctx = overlay.getContext("2d");
  const img = ctx.createImageData(width, height);
  const inside = new Uint8Array(width * height);
  for (const { runs } of masks) {
    for (let i = 0; i < runs.length; i += 2) inside.fill(1, runs[i], runs[i] + runs[i + 1]);
  }
  const veil = [10, 12, 16, 150], tint = [255, 0, 0, 90], line = [255, 60, 60, 255];
  for (let p = 0; p < inside.length; p++) {
    let c = veil;
    if (inside[p]) {
      const x = p % width, y = (p / width) | 0;
      const edge = x === 0 || y === 0 || x === width - 1 || y === height - 1
        || !inside[p - 1] || !inside[p + 1] || !inside[p - width] || !inside[p + width];
      c = edge ? line : tint;
    }
    img.data.set(c, 4 * p);
  }
  ctx.putImageData(img, 0, 0);
}

// ---------------------------------------------------------------- find
// A phrase ("red cone") scores every object of the scene through its own object tokens; the
// matches are tinted red at the page's camera (and again after each camera move), listed with
// their scores; a click on one selects it for object chat.
async function find() {
  const phrase = $("phrase").value.trim();
  if (!phrase) { clearFound(); return; }
  const threshold = Number($("threshold").value);
  const camera = pickCamera();
  const seq = (state.findSeq = (state.findSeq || 0) + 1);
  try {
    const r = await (await post("/api/find", { phrase, threshold, camera })).json();
    if (seq !== state.findSeq) return; // a newer search is under way
    if (state.selection) clearSelection();
    state.found = { ...r, camera };
    drawFound();
    const n = r.matches.length;
    status(n ? `${n} match(es) for "${r.query}" in ${r.score_ms.toFixed(0)} ms` : `nothing matches "${r.query}"`);
  } catch (e) {
    status(`find failed: ${e.message}`);
  }
}

function drawFound() {
  const f = state.found;
  clearOverlay();
  const shown = f.matches.filter((m) => m.mask && !state.hidden.includes(m.id));
  if (shown.length) paintMasks(shown.map((m) => m.mask), f.camera.width, f.camera.height);
  const list = $("found");
  list.replaceChildren();
  for (const m of f.matches) {
    const li = document.createElement("li");
    const b = document.createElement("button");
    b.type = "button";
    const where = state.hidden.includes(m.id) ? " (hidden by you)" : m.mask ? "" : " (not in view here)";
    b.textContent = `${m.name} · ${m.score.toFixed(2)}${where}`;
    b.title = `ask about the ${m.name}`;
    b.dataset.id = m.id;
    b.addEventListener("click", () => chooseFound(m.id));
    li.append(b);
    list.append(li);
  }
  if (!f.matches.length) {
    const li = document.createElement("li");
    li.className = "none";
    li.textContent = `nothing matches "${f.query}" at ${f.threshold.toFixed(2)}`;
    list.append(li);
  }
  list.hidden = false;
}

async function chooseFound(id) {
  try {
    const camera = pickCamera();
    const r = await (await post("/api/select", { camera, id })).json();
    if (!r.object) { status("that object is not visible from here"); return; }
    state.found = null;
    select({ ...r.object, camera });
  } catch (e) {
    status(`select failed: ${e.message}`);
  }
}

function clearFound() {
  state.found = null;
  $("found").hidden = true;
  $("found").replaceChildren();
  if (!state.selection) clearOverlay();
}

// ---------------------------------------------------------------- hide
// Hidden objects leave the view (their Gaussians, by identity class): the WebGL renderer loads
// the scene without them, server frames are rendered without them; picks pass over them. The
// model still answers about the whole scene.
async function hideSelection() {
  const s = state.selection;
  if (!s || state.hidden.includes(s.id)) return;
  state.hidden.push(s.id);
  clearSelection();
  status(`hid the ${s.name}`);
  await showSplats();
}

async function showHidden() {
  state.hidden = [];
  status("every object shown");
  await showSplats();
}

async function showSplats() {
  const n = state.hidden.length;
  $("show-hidden").hidden = n === 0;
  $("show-hidden").textContent = `show hidden (${n})`;
  if (state.found) drawFound();
  const url = splatsUrl();
  if (state.mode === "webgl" && draw.scene) {
    let scene;
    try {
      scene = await splatScene(draw.renderer, url);
    } catch (e) {
      status(`could not load the splats: ${e.message}`);
      return;
    }
    const old = draw.scene;
    draw.scene = scene;
    old.traverse((o) => { if (o !== old && typeof o.dispose === "function") o.dispose(); });
  }
  state.splatsUrl = url;
  requestFrame(false);
  // a new scene is sorted from scratch: keep drawing longer than after a camera move
  if (state.mode === "webgl") draw.until = performance.now() + 4000;
}

function splatsUrl() {
  const base = `/api/splats.${state.splatFormat}`;
  return state.hidden.length ? `${base}?without=${state.hidden.join(",")}` : base;
}

function installHide() {
  $("hide").addEventListener("click", hideSelection);
  $("show-hidden").addEventListener("click", showHidden);
}

function installFind() {
  $("find").addEventListener("submit", (e) => { e.preventDefault(); find(); });
  $("threshold").addEventListener("input", () => { $("threshold-value").textContent = Number($("threshold").value).toFixed(2); });
  $("threshold").addEventListener("change", () => { if ($("phrase").value.trim()) find(); });
}

// ---------------------------------------------------------------- chat
function setScope(scope) {
  state.scope = scope;
  for (const b of document.querySelectorAll("#scopes button")) b.classList.toggle("active", b.dataset.scope === scope);
  const what = { view: "this view", object: state.selection ? `the ${state.selection.name}` : "the object", scene: "the whole scene" };
  $("question").placeholder = `Ask about ${what[scope]}…`;
  renderKnown();
  renderHistory();
}

// A model trained on question forms (the built-in one) offers them, as questions about this
// scene's objects, for the scope's level: a click puts one in the question box.
function renderKnown() {
  const forms = state.scene && state.scene.question_forms;
  $("known").hidden = !forms;
  if (!forms) return;
  const list = $("known-list");
  list.replaceChildren();
  for (const f of forms.filter((f) => f.level === state.scope)) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = f.question;
    b.addEventListener("click", () => { $("question").value = f.question; $("question").focus(); });
    list.append(b);
  }
}

function note(scope, text) {
  state.histories[scope].push({ note: text });
  if (state.scope === scope) renderHistory();
}

function renderHistory() {
  const h = $("history");
  h.replaceChildren();
  for (const turn of state.histories[state.scope]) h.append(turnElement(turn));
  h.scrollTop = h.scrollHeight;
}

function turnElement(turn) {
  if (turn.note) {
    const n = document.createElement("div");
    n.className = "note";
    n.textContent = turn.note;
    return n;
  }
  if (!turn.el) {
    const el = document.createElement("div");
    el.className = "turn";
    el.innerHTML = '<div class="q"></div><div class="a"></div><div class="t"></div>';
    el.querySelector(".q").textContent = turn.question;
    turn.el = el;
  }
  updateTurn(turn);
  return turn.el;
}

function updateTurn(turn) {
  const a = turn.el.querySelector(".a");
  // a list answer ("red cube blue cone") shows its items apart
  const answer = turn.items ? turn.items.join(", ") : turn.answer;
  a.textContent = turn.error || answer || turn.waiting || "";
  // a question none of the model's forms takes: its answer is a guess, and says so
  a.classList.toggle("guess", Boolean(turn.unknownForm) && !turn.error);
  a.title = turn.unknownForm || "";
  a.classList.toggle("error", Boolean(turn.error));
  // the built-in tabletop model on a scene that is not a tabletop: every answer says so
  a.classList.toggle("tabletop-model", Boolean(state.scene && state.scene.model_note) && !turn.error);
  turn.el.querySelector(".t").textContent = turn.timing || "";
  turn.el.dataset.state = turn.state;
  $("history").scrollTop = $("history").scrollHeight;
}

// What a question is about, as a string: a conversation is about one camera / object / view count.
function conversationKey(body) {
  return JSON.stringify([body.camera || null, body.id ?? null, body.views ?? null]);
}

const NEW_CONVERSATION = {
  view: "new conversation: the camera moved",
  object: "new conversation: another object, or the object seen from another camera",
  scene: "new conversation: another number of views",
};

function newConversation() {
  if (!state.conversations[state.scope]) return;
  state.conversations[state.scope] = null;
  note(state.scope, "new conversation");
}

async function ask(question) {
  const scope = state.scope;
  const body = { scope, question };
  if (scope === "view") body.camera = apiCamera();
  if (scope === "object") {
    if (!state.selection) return;
    // the camera it was picked (or last followed) in: the server keeps that pick and its tokens
    body.camera = state.selection.camera;
    body.id = state.selection.id;
  }
  if (scope === "scene") body.views = state.scene.scene_views;
  // a follow-up of the scope's conversation while it is about the same target
  const key = conversationKey(body);
  const conversation = state.conversations[scope];
  // (a model trained on single questions gets every question on its own: no conversation kept)
  if (conversation && conversation.key === key) body.conversation = conversation.id;
  else if (conversation) {
    state.conversations[scope] = null;
    note(scope, NEW_CONVERSATION[scope]);
  }
  const turn = { question, answer: "", waiting: "…", state: "asking", scope };
  state.histories[scope].push(turn);
  if (state.scope === scope) renderHistory();
  const abort = new AbortController();
  state.busy = abort;
  $("send").disabled = true;
  $("stop").disabled = false;
  try {
    const r = await post("/api/ask", body, abort.signal);
    await readEvents(r, (name, ev) => {
      if (name === "queued") turn.waiting = ev.ahead > 0 ? `waiting: ${ev.ahead} question(s) ahead` : "next…";
      else if (name === "start") {
        turn.waiting = "thinking…";
        turn.tokensMs = ev.tokens_ms;
        turn.start = ev;
        turn.unknownForm = ev.unknown_form || null;
        if (state.converse) state.conversations[scope] = { id: ev.conversation, key };
        if (ev.dropped > 0) {
          note(scope, `the oldest ${ev.dropped} exchange(s) were dropped to fit the model's context`);
        }
      }
      else if (name === "token") turn.answer += ev.text;
      else if (name === "done") {
        const parts = [];
        if (scope === "object" && state.lastPickMs != null) parts.push(`pick ${state.lastPickMs.toFixed(0)} ms`);
        if (turn.start && turn.start.turn > 1) {
          parts.push(`follow-up ${turn.start.turn}: ${turn.start.cached_tokens} of ${turn.start.prompt_tokens} prompt tokens kept`);
        }
        parts.push(`tokens ${turn.tokensMs.toFixed(0)} ms`, `first token ${ev.first_token_ms.toFixed(0)} ms`);
        if (ev.tokens > 1) parts.push(`${ev.tokens_per_s.toFixed(1)} tokens/s`);
        parts.push(`${ev.tokens} token${ev.tokens === 1 ? "" : "s"}`);
        turn.timing = parts.join(" · ");
        if (turn.unknownForm) turn.timing = `${turn.unknownForm} · ${turn.timing}`;
        turn.items = ev.items || null;
        turn.state = "done";
      } else if (name === "error") { turn.error = ev.error; turn.state = "error"; }
      updateTurn(turn);
    });
    if (turn.state === "asking") { turn.state = "done"; }
  } catch (e) {
    if (e.name === "AbortError") { turn.timing = "stopped"; turn.state = "stopped"; }
    else {
      turn.error = e.message;
      turn.state = "error";
      // a conversation the server no longer keeps: the next question starts a new one
      if (e.field === "conversation") state.conversations[scope] = null;
    }
  } finally {
    updateTurn(turn);
    state.busy = null;
    $("send").disabled = false;
    $("stop").disabled = true;
  }
}

function installChat() {
  for (const b of document.querySelectorAll("#scopes button")) b.addEventListener("click", () => setScope(b.dataset.scope));
  $("ask").addEventListener("submit", (e) => {
    e.preventDefault();
    const q = $("question").value.trim();
    if (!q || state.busy) return;
    $("question").value = "";
    ask(q);
  });
  $("question").addEventListener("keydown", (e) => {
    if (e.key === "Enter" && !e.shiftKey) { e.preventDefault(); $("ask").requestSubmit(); }
  });
  $("stop").addEventListener("click", () => state.busy && state.busy.abort());
  $("new-conversation").addEventListener("click", newConversation);
}

// ---------------------------------------------------------------- layout
// The canvas keeps the capture's aspect ratio (what the model was taught on), as large as fits.
function layout() {
  const v0 = state.scene.views[0].camera;
  const frame = $("frame").getBoundingClientRect();
  const aspect = v0.width / v0.height;
  let w = frame.width - 16, h = w / aspect;
  if (h > frame.height - 16) { h = frame.height - 16; w = h * aspect; }
  w = Math.max(64, Math.floor(w));
  h = Math.max(64, Math.floor(h));
  const vp = $("viewport");
  vp.style.width = `${w}px`;
  vp.style.height = `${h}px`;
  state.size = { width: w, height: h };
  $("gl").width = w; $("gl").height = h;
  state.camera.aspect = w / h;
  state.camera.updateProjectionMatrix();
  if (draw.renderer) draw.renderer.setSize(w, h, false);
}

// ---------------------------------------------------------------- start
function webgl2() {
  try { return Boolean(document.createElement("canvas").getContext("webgl2")); } catch (_) { return false; }
}

async function main() {
  const r = await fetch("/api/scene");
  if (!r.ok) throw await failure(r);
  state.scene = await r.json();
  const s = state.scene;
  document.title = `chatsplat · ${s.name}`;
  $("scene-name").textContent = s.name;
  state.up.fromArray(s.up);
  state.camera = new THREE.PerspectiveCamera(50, 1, 0.01 * s.radius, 100 * s.radius);
  state.camera.up.copy(state.up);
  const free = document.createElement("option");
  free.value = "";
  free.textContent = "(moved: no camera of the capture)";
  free.disabled = true;
  $("views").append(free);
  for (const v of s.views) {
    const o = document.createElement("option");
    o.value = String(v.index);
    o.textContent = `${v.index}: ${v.image}${v.split === "test" ? " (held out)" : ""}`;
    $("views").append(o);
  }
  $("views").addEventListener("change", (e) => jump(Number(e.target.value)));
  $("reset").addEventListener("click", () => jump(0));
  layout();
  // a new size keeps the camera (and the menu's name for it): the frame is drawn again, and the
  // selection (its mask stretched with the view meanwhile, its label moved) asked for at the new size.
  // The frame's own size is watched (after layout), not the window's resize event, which can come
  // before the new layout (the canvas then kept the old size).
  let laidOut = "";
  new ResizeObserver(() => {
    const f = $("frame").getBoundingClientRect(), key = `${f.width}x${f.height}`;
    if (key === laidOut) return;
    laidOut = key;
    layout();
    if (!state.ready) return;
    state.camera.updateMatrixWorld(true);
    requestFrame(false);
    if (state.selection) { drawSelection(); follow(); } else if (state.found) find();
  }).observe($("frame"));
  installControls();
  installChat();
  installFind();
  installHide();
  // a model trained on single questions asks each on its own (?converse=1 holds conversations anyway)
  state.converse = s.converses || params.get("converse") === "1";
  $("new-conversation").hidden = !state.converse;
  if (!state.converse && s.converse_note) {
    for (const scope of ["view", "object", "scene"]) note(scope, s.converse_note);
  }
  setScope("view");
  if (s.model_note) {
    const b = $("model-note");
    b.textContent = s.model_note.charAt(0).toUpperCase() + s.model_note.slice(1);
    b.hidden = false;
  }
  state.mode = params.get("render") === "server" || !webgl2() ? "server" : "webgl";
  const bytes = s.splat_bytes;
  state.splatFormat = bytes.spz && bytes.spz < bytes.ply ? "spz" : "ply";
  state.splatsUrl = splatsUrl();
  if (state.mode === "webgl") {
    const mb = (bytes[state.splatFormat] / 1e6).toFixed(1);
    status(`loading ${s.gaussians.toLocaleString()} Gaussians (${mb} MB .${state.splatFormat})…`);
    try {
      await startWebgl();
    } catch (e) {
      state.mode = "server";
      status(`WebGL renderer failed (${e.message}); frames come from the server`);
    }
  }
  $("gl").style.opacity = state.mode === "server" ? "0" : "1";
  $("server-frame").hidden = state.mode !== "server";
  $("mode").textContent = state.mode === "webgl" ? "Spark (WebGL2)" : "server frames";
  jump(Math.min(Number(params.get("view") || 0), s.views.length - 1));
  if (!$("status").textContent.startsWith("WebGL")) status(`${s.gaussians.toLocaleString()} Gaussians · ${s.objects.length} objects · model ${s.model}`);
  state.ready = true;
}

// Hooks for scripts and tests: the page's state, read-only, and the camera.
window.chatsplat = {
  get ready() { return state.ready; },
  get mode() { return state.mode; },
  get frames() { return state.frames; },
  get selection() { return state.selection && { id: state.selection.id, name: state.selection.name, pixels: state.selection.pixels }; },
  get scope() { return state.scope; },
  // an answer is streaming (the chat box takes the next question once it has ended)
  get busy() { return Boolean(state.busy); },
  get found() {
    const f = state.found;
    return f && { query: f.query, threshold: f.threshold, matches: f.matches.map((m) => ({ id: m.id, name: m.name, score: m.score, shown: Boolean(m.mask) })) };
  },
  // nothing left to draw: the splat sort has settled, or the last server frame has come
  get idle() {
    return state.ready && performance.now() > draw.until && state.frames >= draw.minFrames && !draw.serverBusy && !draw.serverWanted;
  },
  // why the page is not idle (for scripts that waited too long)
  debug: () => ({
    now: performance.now(), until: draw.until, frames: state.frames, minFrames: draw.minFrames,
    serverBusy: draw.serverBusy, serverWanted: draw.serverWanted, dragging: drag.active, keys: [...keys],
    size: state.size, visibility: document.visibilityState,
  }),
  camera: () => apiCamera(),
  canvasRect: () => { const r = $("gl").getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; },
  setCamera: (v) => setCamera(v),
  orbit: (dx, dy) => { orbit(dx, dy); cameraMoved(false); },
  jump: (i) => jump(i),
  turns: () => state.histories[state.scope].filter((t) => !t.note).map((t) => ({
    question: t.question, answer: t.answer, error: t.error || null, state: t.state, timing: t.timing || null,
    conversation: t.start ? t.start.conversation : null, turn: t.start ? t.start.turn : null,
    cached: t.start ? t.start.cached_tokens : null, unknown_form: t.unknownForm || null,
    shown: t.el ? t.el.querySelector(".a").textContent : null,
  })),
  // the questions the page offers for the current scope (a model trained on question forms)
  known: () => [...document.querySelectorAll("#known-list button")].map((b) => b.textContent),
  notes: () => state.histories[state.scope].filter((t) => t.note).map((t) => t.note),
  serverFrameKind: () => $("server-frame").dataset.kind || null,
  // the objects hidden, and the splats the WebGL renderer shows (the URL, once loaded)
  hidden: () => [...state.hidden],
  get splatsUrl() { return state.splatsUrl; },
};

main().catch((e) => { status(`cannot load the scene: ${e.message}`); });
