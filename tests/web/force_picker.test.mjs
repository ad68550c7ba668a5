// Unit tests of the force/torque picker's wiring into the ComfyUI frontend (web/force_picker.js), run
// with `node --test tests/web/`. The file is loaded as it ships, with its two frontend imports
// (../../scripts/app.js, ../../scripts/api.js) pointed at small fakes, and the browser objects it uses
// (document, Image, ResizeObserver, requestAnimationFrame) replaced by recording stand-ins. What is
// checked: the extension uses the frontend's nodeCreated hook for the Force and Torque nodes only,
// creates no timer, redraws when the node's widgets, its links or the rest of the graph change or its
// canvas resizes (and not when nothing changed), and lets go of everything when the node is removed.
import assert from "node:assert/strict";
import { mkdtempSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { test } from "node:test";
import { fileURLToPath, pathToFileURL } from "node:url";

const WEB = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..", "..", "web");

// ---------------------------------------------------------------- browser stand-ins
function fakeContext(log) {
  // Records every drawing call by name; properties (strokeStyle, font, ...) are stored.
  return new Proxy({}, {
    get(target, key) {
      if (key in target) return target[key];
      if (key === "measureText") return (s) => ({ width: 6 * String(s).length });
      return (...args) => { log.push([key, ...args]); };
    },
    set(target, key, value) { target[key] = value; return true; },
  });
}

class FakeElement {
  constructor(tag) {
    this.tagName = tag.toUpperCase();
    this.style = {};
    this.dataset = {};
    this.children = [];
    this.listeners = [];
    this.clientWidth = 320;
    this.clientHeight = 200;
    this.width = 300;
    this.height = 150;
    this.log = [];
  }
  append(...children) { this.children.push(...children); }
  addEventListener(type, fn, opts) { this.listeners.push({ type, fn, signal: opts?.signal }); }
  live(type) { return this.listeners.filter((l) => l.type === type && !l.signal?.aborted); }
  getContext() { this.ctx ??= fakeContext(this.log); return this.ctx; }
  getBoundingClientRect() { return { left: 0, top: 0, x: 0, y: 0, width: this.clientWidth, height: this.clientHeight }; }
  setPointerCapture() {}
  count(call) { return this.log.filter((c) => c[0] === call).length; }
  texts() { return this.log.filter((c) => c[0] === "fillText").map((c) => c[1]); }
}

function installBrowser() {
  const env = { frames: [], intervals: [], observers: [], requested: [] };
  globalThis.window = { devicePixelRatio: 1 };
  globalThis.document = { createElement: (tag) => new FakeElement(tag) };
  globalThis.Image = class {
    set src(url) {
      this._src = url;
      env.requested.push(url);
      queueMicrotask(() => { this.naturalWidth = 600; this.naturalHeight = 400; this.onload?.(); });
    }
    get src() { return this._src; }
  };
  globalThis.ResizeObserver = class {
    constructor(callback) { this.callback = callback; this.targets = []; this.disconnected = false; env.observers.push(this); }
    observe(el) { this.targets.push(el); }
    disconnect() { this.disconnected = true; this.targets = []; }
    fire() { if (!this.disconnected) this.callback(this.targets.map((target) => ({ target }))); }
  };
  globalThis.requestAnimationFrame = (fn) => { env.frames.push(fn); return env.frames.length; };
  globalThis.cancelAnimationFrame = () => {};
  globalThis.setInterval = (...args) => { env.intervals.push(args); return 0; };
  return env;
}

/** Run the queued animation frames, then let the image loads (microtasks) finish. */
async function flush(env) {
  for (let round = 0; round < 3; round++) {
    const frames = env.frames.splice(0);
    for (const fn of frames) fn(0);
    await new Promise((resolve) => setImmediate(resolve));
  }
}

// ---------------------------------------------------------------- the frontend stand-ins
function fakeApp() {
  const api = new EventTarget();
  api.apiURL = (route) => `/api${route}`;
  const app = {
    extensions: [],
    registerExtension(ext) { this.extensions.push(ext); },
    canvas: { onDrawForeground: undefined },
    graph: null,
  };
  return { app, api };
}

let loads = 0;
/** Import web/force_picker.js afresh with its frontend imports pointed at `fakes`. */
async function loadPicker(fakes) {
  const dir = mkdtempSync(path.join(tmpdir(), "pm-picker-"));
  const key = `__pmPickerFakes${loads++}`;
  globalThis[key] = fakes;
  writeFileSync(path.join(dir, "app.js"), `export const app = globalThis.${key}.app;\n`);
  writeFileSync(path.join(dir, "api.js"), `export const api = globalThis.${key}.api;\n`);
  let src = readFileSync(path.join(WEB, "force_picker.js"), "utf8");
  const swaps = [
    ['"../../scripts/app.js"', '"./app.js"'],
    ['"../../scripts/api.js"', '"./api.js"'],
    ['"./picker_math.js"', JSON.stringify(pathToFileURL(path.join(WEB, "picker_math.js")).href)],
    ['"./picker_widget.js"', JSON.stringify(pathToFileURL(path.join(WEB, "picker_widget.js")).href)],
  ];
  for (const [from, to] of swaps) {
    assert.ok(src.includes(from), `force_picker.js no longer imports ${from}`);
    src = src.replace(from, to);
  }
  writeFileSync(path.join(dir, "force_picker.mjs"), src);
  try {
    await import(pathToFileURL(path.join(dir, "force_picker.mjs")).href);
  } finally {
    // The module stays loaded; its copy on disk is not needed any more.
    rmSync(dir, { recursive: true, force: true });
  }
  assert.equal(fakes.app.extensions.length, 1, "the file registers one extension");
  return fakes.app.extensions[0];
}

function makeGraph() {
  const nodes = new Map();
  const links = new Map();
  return {
    nodes, links,
    getNodeById: (id) => nodes.get(id) ?? null,
    getLink: (id) => links.get(id),
    setDirtyCanvas() {},
    add(node) { nodes.set(node.id, node); node.graph = this; node.onAdded?.(this); },
    link(id, from, to) {
      links.set(id, { id, origin_id: from.id, target_id: to.id });
      from.outputs.push({ links: [id] });
      to.inputs.push({ link: id });
    },
  };
}

/** A node as the frontend's constructor leaves it when nodeCreated runs: widgets, no graph, no type. */
function makeNode(comfyClass, id, widgets) {
  return {
    id, comfyClass, inputs: [], outputs: [], properties: {}, size: [300, 200], domWidgets: [],
    widgets: widgets.map(([name, value, callback]) => ({ name, value, options: {}, callback })),
    computeSize() { return [300, 520]; },
    setSize(s) { this.size = s; },
    setDirtyCanvas() {},
    addDOMWidget(name, type, element, options) {
      const w = { name, type, element, options };
      this.widgets.push(w);
      this.domWidgets.push(w);
      return w;
    },
  };
}

const FORCE_WIDGETS = [["u", 300], ["v", 200], ["fx", 20], ["fy", 0], ["fz", 0], ["region", "image point"],
  ["radius_px", 30]];
const TORQUE_WIDGETS = [["u", 300], ["v", 200], ["tx", 0], ["ty", 1], ["tz", 0], ["region", "whole object"],
  ["radius_px", 30]];

/** LoadImage -> Lift -> Simulate <- Force (as in the templates). */
function wiredScene(ext, kind = "PhysMotionForce", widgets = FORCE_WIDGETS) {
  const graph = makeGraph();
  const load = makeNode("LoadImage", 1, [["image", "jelly.png"], ["upload", "image"]]);
  const lift = makeNode("PhysMotionSilhouetteLift", 2, []);
  const sim = makeNode("PhysMotionSimulate", 3, []);
  const node = makeNode(kind, 4, widgets);
  for (const n of [load, lift, sim, node]) ext.nodeCreated(n);
  for (const n of [load, lift, sim, node]) graph.add(n);
  graph.link(1, load, lift);
  graph.link(2, lift, sim);
  graph.link(3, node, sim);
  return { graph, load, lift, sim, node };
}

const widgetOf = (node, name) => node.widgets.find((w) => w.name === name);
const viewURL = (file) => `/api/view?filename=${file}&type=input&subfolder=`;

test("the extension registers through nodeCreated, for the Force and Torque nodes only, and starts no timer", async () => {
  const env = installBrowser();
  const fakes = fakeApp();
  const ext = await loadPicker(fakes);
  assert.equal(ext.name, "PhysMotion.ForceTorquePicker");
  assert.equal(typeof ext.nodeCreated, "function");
  assert.equal(ext.beforeRegisterNodeDef, undefined, "the prototype is no longer wrapped");
  ext.setup?.(fakes.app);

  const others = ["LoadImage", "PhysMotionSimulate", "PhysMotionSilhouetteLift", "KSampler"]
    .map((c, i) => makeNode(c, 10 + i, [["u", 1]]));
  for (const n of others) ext.nodeCreated(n, fakes.app);
  for (const n of others) {
    assert.equal(n.domWidgets.length, 0, n.comfyClass);
    assert.equal(n.physmotionPicker, undefined, n.comfyClass);
  }
  const force = makeNode("PhysMotionForce", 20, FORCE_WIDGETS);
  const torque = makeNode("PhysMotionTorque", 21, TORQUE_WIDGETS);
  ext.nodeCreated(force, fakes.app);
  ext.nodeCreated(torque, fakes.app);
  for (const [n, kind] of [[force, "force"], [torque, "torque"]]) {
    assert.equal(n.domWidgets.length, 1);
    const w = n.domWidgets[0];
    assert.equal(w.serialize, false, "the picker widget is not a backend input");
    assert.equal(n.physmotionPicker.spec.kind, kind);
    assert.equal(n.physmotionPicker.canvas.dataset.physmotionPicker, kind);
    assert.ok(n.size[1] >= 520 && n.size[0] >= 340, "the node grows to fit the picker");
  }
  // The class can also come from the constructor (the frontend sets it there as well).
  const byCtor = makeNode(undefined, 22, FORCE_WIDGETS);
  byCtor.constructor = { comfyClass: "PhysMotionTorque" };
  ext.nodeCreated(byCtor, fakes.app);
  assert.equal(byCtor.physmotionPicker?.spec.kind, "torque");

  await flush(env);
  assert.deepEqual(env.intervals, [], "no setInterval");
  assert.equal(env.observers.length, 3, "one ResizeObserver per picker");
  assert.deepEqual(env.observers.map((o) => o.targets[0]), [force, torque, byCtor].map((n) => n.physmotionPicker.canvas));
});

test("the photo is found once the node is on a wired graph; a widget change or a link change redraws; no change, no redraw", async () => {
  const env = installBrowser();
  const fakes = fakeApp();
  const ext = await loadPicker(fakes);
  ext.setup?.(fakes.app);
  const fxCalls = [];
  const widgets = FORCE_WIDGETS.map(([n, v]) => (n === "fx" ? [n, v, (value) => fxCalls.push(value)] : [n, v]));
  const { graph, node, sim } = wiredScene(ext, "PhysMotionForce", widgets);
  fakes.app.graph = graph;
  ext.afterConfigureGraph?.([]);
  await flush(env);
  const picker = node.physmotionPicker;
  const canvas = picker.canvas;
  assert.deepEqual(env.requested, [viewURL("jelly.png")], "the LoadImage three links away is the source");
  assert.equal(picker.image?.naturalWidth, 600);
  assert.ok(canvas.count("drawImage") >= 1, "the photo is drawn");

  // Nothing changed: refreshing again (events, canvas draws) draws nothing.
  let draws = canvas.count("clearRect");
  fakes.api.dispatchEvent(new Event("graphChanged"));
  fakes.app.canvas.onDrawForeground({}, [0, 0, 100, 100]);
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws, "no redraw without a change");

  // One of the node's own widgets changes (the frontend sets the value, then runs its callback).
  const fx = widgetOf(node, "fx");
  fx.value = 45;
  fx.callback(45, fakes.app.canvas, node);
  assert.deepEqual(fxCalls, [45], "the widget's own callback still runs");
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws + 1, "one redraw for the widget change");
  assert.ok(canvas.texts().includes("(45, 0, 0) N"), canvas.texts());

  // litegraph's per-node widget hook (a value changed on the canvas) redraws as well.
  draws = canvas.count("clearRect");
  widgetOf(node, "fy").value = -5;
  node.onWidgetChanged?.("fy", -5, 0, widgetOf(node, "fy"));
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws + 1);
  assert.ok(canvas.texts().includes("(45, -5, 0) N"));

  // The node's link is removed: the frontend calls the node's onConnectionsChange.
  draws = canvas.count("clearRect");
  graph.links.delete(3);
  node.outputs[0].links = [];
  sim.inputs = sim.inputs.filter((s) => s.link !== 3);
  node.onConnectionsChange(2 /* output */, 0, false, undefined, node.outputs[0]);
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws + 1, "the link change redraws");
  assert.equal(picker.image, null);
  assert.ok(canvas.texts().at(-1).startsWith("connect the graph to a Load Image node"), canvas.texts().at(-1));
  assert.deepEqual(env.intervals, []);
});

test("changes elsewhere in the graph and a resize of the canvas refresh the picker", async () => {
  const env = installBrowser();
  const fakes = fakeApp();
  const ext = await loadPicker(fakes);
  ext.setup?.(fakes.app);
  const { graph, load, node } = wiredScene(ext);
  fakes.app.graph = graph;
  await flush(env);
  const picker = node.physmotionPicker;
  const canvas = picker.canvas;
  assert.deepEqual(env.requested, [viewURL("jelly.png")]);

  // Another node's widget changes (the Load Image gets another photo); the frontend dispatches
  // graphChanged on the api.
  widgetOf(load, "image").value = "ball.png";
  fakes.api.dispatchEvent(new Event("graphChanged"));
  await flush(env);
  assert.deepEqual(env.requested, [viewURL("jelly.png"), viewURL("ball.png")]);
  assert.equal(picker.imageURL, viewURL("ball.png"));

  // A change that raises no event is seen on the graph canvas' next draw.
  widgetOf(load, "image").value = "snow.png [input]";
  fakes.app.canvas.onDrawForeground({}, [0, 0, 100, 100]);
  await flush(env);
  assert.equal(env.requested.at(-1), viewURL("snow.png"));

  // A node that shows an output image after a run: the executed event refreshes.
  const preview = makeNode("PreviewImage", 9, []);
  ext.nodeCreated(preview);
  graph.add(preview);
  graph.link(8, node, preview);
  graph.nodes.delete(1); // the Load Image is gone; the preview is now the nearest source
  preview.imgs = [{ src: "/api/view?filename=preview.png&type=temp&subfolder=" }];
  fakes.api.dispatchEvent(new Event("executed"));
  await flush(env);
  assert.equal(env.requested.at(-1), "/api/view?filename=preview.png&type=temp&subfolder=");

  // The picker's canvas is resized: its ResizeObserver redraws at the new size.
  const observer = env.observers.find((o) => o.targets.includes(canvas));
  let draws = canvas.count("clearRect");
  canvas.clientWidth = 500;
  canvas.clientHeight = 260;
  observer.fire();
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws + 1);
  assert.deepEqual([canvas.width, canvas.height], [500, 260], "the bitmap follows the element's size");

  // The scale in the Properties panel changes.
  draws = canvas.count("clearRect");
  node.properties.picker_newtons_per_image_height = 100;
  node.onPropertyChanged?.("picker_newtons_per_image_height", 100);
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws + 1);
  assert.deepEqual(env.intervals, []);
});

test("removing the node disconnects its ResizeObserver and stops every refresh", async () => {
  const env = installBrowser();
  const fakes = fakeApp();
  const ext = await loadPicker(fakes);
  ext.setup?.(fakes.app);
  const { graph, load, node } = wiredScene(ext, "PhysMotionTorque", TORQUE_WIDGETS);
  fakes.app.graph = graph;
  await flush(env);
  const picker = node.physmotionPicker;
  const canvas = picker.canvas;
  const observer = env.observers.find((o) => o.targets.includes(canvas));
  assert.ok(observer && !observer.disconnected);
  assert.equal(canvas.live("pointerdown").length, 1);

  // A change is pending when the node goes: the queued frame must not draw afterwards.
  widgetOf(node, "tz").value = 3;
  widgetOf(node, "tz").callback?.(3);
  graph.nodes.delete(node.id);
  node.onRemoved();
  const draws = canvas.count("clearRect");
  const requests = env.requested.length;
  assert.equal(observer.disconnected, true, "ResizeObserver disconnected");
  assert.equal(canvas.live("pointerdown").length + canvas.live("pointermove").length +
               canvas.live("pointerup").length + canvas.live("pointercancel").length, 0, "pointer listeners gone");
  await flush(env);
  widgetOf(load, "image").value = "other.png";
  fakes.api.dispatchEvent(new Event("graphChanged"));
  fakes.api.dispatchEvent(new Event("executed"));
  fakes.app.canvas.onDrawForeground({}, [0, 0, 100, 100]);
  node.onConnectionsChange?.(1, 0, true, undefined, {});
  observer.fire();
  await flush(env);
  assert.equal(canvas.count("clearRect"), draws, "a removed picker never draws again");
  assert.equal(env.requested.length, requests, "nor loads images");
  // The DOM widget's own removal hook is safe to run too (either may come first).
  node.domWidgets[0].onRemove();
});

test("an image point remembers its photo: on another photo the label says so until it is dragged again", async () => {
  const env = installBrowser();
  const fakes = fakeApp();
  const ext = await loadPicker(fakes);
  ext.setup?.(fakes.app);
  const { graph, node, load } = wiredScene(ext);
  fakes.app.graph = graph;
  ext.afterConfigureGraph?.([]);
  await flush(env);
  const picker = node.physmotionPicker;
  const canvas = picker.canvas;
  // photo 600x400 in a 320x200 canvas: scale 0.5, x offset 10
  const ev = (u, v) => ({ clientX: 10 + u / 2, clientY: v / 2, button: 0, pointerId: 1, shiftKey: false,
                          preventDefault() {}, stopPropagation() {} });
  const dragOn = (from, to) => {
    canvas.live("pointerdown")[0].fn(ev(...from));
    canvas.live("pointermove")[0].fn(ev(...to));
    canvas.live("pointerup")[0].fn(ev(...to));
  };
  dragOn([200, 150], [300, 150]);
  assert.equal(node.properties.physmotion_prompt_photo, "jelly.png");
  assert.equal(widgetOf(node, "u").value, 200);
  await flush(env);
  assert.ok(!canvas.texts().at(-1).includes("set on"), canvas.texts().at(-1));
  widgetOf(load, "image").value = "own.png"; // the user's photo
  picker.invalidate();
  await flush(env);
  assert.equal(canvas.texts().at(-1), "point set on jelly.png: drag again on this photo");
  dragOn([400, 300], [420, 300]);
  assert.equal(node.properties.physmotion_prompt_photo, "own.png");
  await flush(env);
  assert.ok(!canvas.texts().at(-1).includes("set on"), canvas.texts().at(-1));
  // a push on the whole object has no point to go stale
  widgetOf(load, "image").value = "third.png";
  widgetOf(node, "region").value = "whole object";
  picker.invalidate();
  await flush(env);
  assert.ok(!canvas.texts().at(-1).includes("set on"), canvas.texts().at(-1));
});
