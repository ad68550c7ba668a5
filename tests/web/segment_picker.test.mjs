// Unit tests of the segmentation-prompt picker's wiring (web/segment_picker.js), run with
// `node --test tests/web/`. The file is loaded as it ships, with its frontend imports
// (../../scripts/app.js, ../../scripts/api.js) pointed at small fakes and the browser objects it uses
// (document, Image, ResizeObserver, requestAnimationFrame) replaced by recording stand-ins. Pointer
// events are sent to the picker's canvas as the browser would: checked is what lands in the node's
// widgets (clicks, Shift-clicks, drags, clicks on a point, the clear button, the SAM node's format),
// that the picker redraws from widgets changed by hand, and that removal lets go of everything.
import assert from "node:assert/strict";
import { mkdtempSync, readFileSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import path from "node:path";
import { test } from "node:test";
import { fileURLToPath, pathToFileURL } from "node:url";

const WEB = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..", "..", "web");

// ---------------------------------------------------------------- browser stand-ins
class Element {
  constructor(tag) {
    this.tagName = tag.toUpperCase();
    this.style = {};
    this.dataset = {};
    this.children = [];
    this.handlers = [];
    this.calls = [];
    this.clientWidth = 320;
    this.clientHeight = 200;
    this.width = 300;
    this.height = 150;
  }
  append(...kids) { this.children.push(...kids); }
  addEventListener(type, fn, opts) { this.handlers.push({ type, fn, signal: opts?.signal }); }
  active(type) { return this.handlers.filter((h) => h.type === type && !h.signal?.aborted); }
  fire(type, event) { for (const h of this.active(type)) h.fn(event); }
  getBoundingClientRect() { return { left: 0, top: 0, width: this.clientWidth, height: this.clientHeight }; }
  setPointerCapture() {}
  getContext() {
    const calls = this.calls;
    this.ctx ??= new Proxy({}, {
      get(t, k) {
        if (k in t) return t[k];
        if (k === "measureText") return (s) => ({ width: 6 * String(s).length });
        return (...args) => { calls.push([k, ...args]); };
      },
      set(t, k, v) { t[k] = v; return true; },
    });
    return this.ctx;
  }
  count(name) { return this.calls.filter((c) => c[0] === name).length; }
  lastLabel() { return this.calls.filter((c) => c[0] === "fillText").at(-1)?.[1]; }
}

function installBrowser() {
  const env = { frames: [], timers: [], observers: [], loaded: [] };
  globalThis.window = { devicePixelRatio: 1 };
  globalThis.document = { createElement: (tag) => new Element(tag) };
  globalThis.Image = class {
    set src(url) {
      this._src = url;
      env.loaded.push(url);
      queueMicrotask(() => { this.naturalWidth = 600; this.naturalHeight = 400; this.onload?.(); });
    }
    get src() { return this._src; }
  };
  globalThis.ResizeObserver = class {
    constructor(cb) { this.cb = cb; this.targets = []; this.disconnected = false; env.observers.push(this); }
    observe(el) { this.targets.push(el); }
    disconnect() { this.disconnected = true; this.targets = []; }
    trigger() { if (!this.disconnected) this.cb([]); }
  };
  globalThis.requestAnimationFrame = (fn) => { env.frames.push(fn); return env.frames.length; };
  globalThis.cancelAnimationFrame = () => {};
  globalThis.setInterval = (...args) => { env.timers.push(args); return 0; };
  return env;
}

async function settle(env) {
  for (let i = 0; i < 3; i++) {
    for (const fn of env.frames.splice(0)) fn(0);
    await new Promise((r) => setImmediate(r));
  }
}

// ---------------------------------------------------------------- frontend stand-ins
function fakeFrontend() {
  const api = new EventTarget();
  api.apiURL = (route) => `/api${route}`;
  const app = { extensions: [], registerExtension(ext) { this.extensions.push(ext); },
                canvas: { onDrawForeground: undefined }, graph: null };
  return { app, api };
}

let imports = 0;
async function loadExtension(fakes) {
  const dir = mkdtempSync(path.join(tmpdir(), "pm-segpicker-"));
  const key = `__pmSegFakes${imports++}`;
  globalThis[key] = fakes;
  writeFileSync(path.join(dir, "app.js"), `export const app = globalThis.${key}.app;\n`);
  writeFileSync(path.join(dir, "api.js"), `export const api = globalThis.${key}.api;\n`);
  let src = readFileSync(path.join(WEB, "segment_picker.js"), "utf8");
  for (const [from, to] of [
    ['"../../scripts/app.js"', '"./app.js"'],
    ['"../../scripts/api.js"', '"./api.js"'],
    ['"./picker_math.js"', JSON.stringify(pathToFileURL(path.join(WEB, "picker_math.js")).href)],
    ['"./picker_widget.js"', JSON.stringify(pathToFileURL(path.join(WEB, "picker_widget.js")).href)],
    ['"./segment_math.js"', JSON.stringify(pathToFileURL(path.join(WEB, "segment_math.js")).href)],
  ]) {
    assert.ok(src.includes(from), `segment_picker.js no longer imports ${from}`);
    src = src.replace(from, to);
  }
  writeFileSync(path.join(dir, "segment_picker.mjs"), src);
  try {
    await import(pathToFileURL(path.join(dir, "segment_picker.mjs")).href);
  } finally {
    // The module stays loaded; its copy on disk is not needed any more.
    rmSync(dir, { recursive: true, force: true });
  }
  assert.equal(fakes.app.extensions.length, 1, "one extension registered");
  return fakes.app.extensions[0];
}

function newGraph() {
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

function newNode(comfyClass, id, widgets) {
  return {
    id, comfyClass, inputs: [], outputs: [], properties: {}, size: [300, 150], domWidgets: [],
    widgets: widgets.map(([name, value]) => ({ name, value, options: {}, changes: [],
                                               callback(v) { this.changes.push(v); } })),
    computeSize() { return [300, 420]; },
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

const SEGMENT_WIDGETS = [["method", "auto"], ["mask_polarity", "auto"], ["grabcut_iterations", 5],
  ["object_points", ""], ["background_points", ""], ["box", ""]];
const SAM_WIDGETS = [["points", ""], ["boxes", ""], ["coordinates", "pixels"], ["clean", true]];

/** LoadImage -> Segment node (the photo is 600x400, the canvas 320x200: scale 0.5, x offset 10). */
async function scene(kind = "PhysMotionSegment", widgets = SEGMENT_WIDGETS) {
  const env = installBrowser();
  const fakes = fakeFrontend();
  const ext = await loadExtension(fakes);
  ext.setup?.(fakes.app);
  const graph = newGraph();
  const load = newNode("LoadImage", 1, [["image", "cat.png"], ["upload", "image"]]);
  const node = newNode(kind, 2, widgets);
  for (const n of [load, node]) ext.nodeCreated(n, fakes.app);
  for (const n of [load, node]) graph.add(n);
  graph.link(1, load, node);
  fakes.app.graph = graph;
  ext.afterConfigureGraph?.([]);
  await settle(env);
  return { env, fakes, ext, graph, load, node, picker: node.physmotionSegmentPicker };
}

const value = (node, name) => node.widgets.find((w) => w.name === name).value;
const canvasAt = (u, v) => ({ x: 10 + u / 2, y: v / 2 }); // image pixel -> canvas point in these scenes

function pointer(x, y, mods = {}) {
  return { clientX: x, clientY: y, button: 0, pointerId: 1, shiftKey: false, ctrlKey: false, metaKey: false,
           ...mods, preventDefault() {}, stopPropagation() { this.stopped = true; } };
}

function click(canvas, u, v, mods) {
  const c = canvasAt(u, v);
  const down = pointer(c.x, c.y, mods);
  canvas.fire("pointerdown", down);
  canvas.fire("pointerup", pointer(c.x, c.y, mods));
  return down;
}

function drag(canvas, from, to, mods) {
  const a = canvasAt(...from);
  const b = canvasAt(...to);
  canvas.fire("pointerdown", pointer(a.x, a.y, mods));
  canvas.fire("pointermove", pointer((a.x + b.x) / 2, (a.y + b.y) / 2, mods));
  canvas.fire("pointermove", pointer(b.x, b.y, mods));
  canvas.fire("pointerup", pointer(b.x, b.y, mods));
}

test("the extension registers through nodeCreated for the two Segment nodes only, with no timer", async () => {
  const env = installBrowser();
  const fakes = fakeFrontend();
  const ext = await loadExtension(fakes);
  assert.equal(ext.name, "PhysMotion.SegmentPicker");
  assert.equal(typeof ext.nodeCreated, "function");
  ext.setup?.(fakes.app);
  const others = ["LoadImage", "PhysMotionForce", "PhysMotionSAMLoader", "KSampler"]
    .map((c, i) => newNode(c, 10 + i, [["points", ""]]));
  for (const n of others) ext.nodeCreated(n, fakes.app);
  for (const n of others) assert.equal(n.domWidgets.length, 0, n.comfyClass);
  const seg = newNode("PhysMotionSegment", 20, SEGMENT_WIDGETS);
  const sam = newNode(undefined, 21, SAM_WIDGETS);
  sam.constructor = { comfyClass: "PhysMotionSAMSegment" };
  ext.nodeCreated(seg, fakes.app);
  ext.nodeCreated(sam, fakes.app);
  for (const [n, kind] of [[seg, "grabcut"], [sam, "sam"]]) {
    assert.equal(n.domWidgets.length, 1);
    assert.equal(n.domWidgets[0].serialize, false, "the picker is no backend input");
    assert.equal(n.physmotionSegmentPicker.kind, kind);
    assert.match(n.physmotionSegmentPicker.hint.textContent, /Shift-click: background/);
    assert.ok(n.size[0] >= 340 && n.size[1] >= 420, "the node grows to fit the picker");
  }
  assert.match(sam.physmotionSegmentPicker.hint.textContent, /Ctrl-drag/);
  await settle(env);
  assert.deepEqual(env.timers, [], "no setInterval");
  assert.equal(env.observers.length, 2, "one ResizeObserver per picker");
});

test("no-model Segment: click, Shift-click, click on a point, drag, a new drag and clear write the widgets", async () => {
  const { env, node, picker } = await scene();
  const canvas = picker.canvas;
  assert.deepEqual(env.loaded, ["/api/view?filename=cat.png&type=input&subfolder="]);
  assert.ok(canvas.count("drawImage") >= 1, "the photo is drawn");

  const down = click(canvas, 200, 100);
  assert.ok(down.stopped, "the graph canvas does not also get the click");
  assert.equal(value(node, "object_points"), "200, 100");
  assert.deepEqual(node.widgets.find((w) => w.name === "object_points").changes, ["200, 100"],
    "written through the widget's callback");
  click(canvas, 401, 301); // lands on pixel (401, 301) -> clamped and rounded: a whole pixel
  click(canvas, 20, 40, { shiftKey: true });
  assert.equal(value(node, "object_points"), "200, 100; 401, 301");
  assert.equal(value(node, "background_points"), "20, 40");

  // A click within a few canvas pixels of a dot removes it (whatever the modifier).
  click(canvas, 204, 104, { shiftKey: true });
  assert.equal(value(node, "object_points"), "401, 301");
  assert.equal(value(node, "background_points"), "20, 40");

  drag(canvas, [300, 280], [100, 80]);
  assert.equal(value(node, "box"), "100, 80, 300, 280", "corners sorted");
  assert.equal(value(node, "object_points"), "401, 301", "a drag adds no point");
  drag(canvas, [10, 10], [50, 60], { ctrlKey: true });
  assert.equal(value(node, "box"), "10, 10, 50, 60", "a new drag replaces the box (one box on this node)");
  drag(canvas, [10, 10], [590, 10.4]);
  assert.equal(value(node, "box"), "10, 10, 50, 60", "a flat drag is no box");

  // Outside the photo (the letterbox bar left of it) and with the right button: nothing.
  canvas.fire("pointerdown", pointer(4, 50));
  canvas.fire("pointerup", pointer(4, 50));
  const right = canvasAt(300, 300);
  canvas.fire("pointerdown", pointer(right.x, right.y, { button: 2 }));
  canvas.fire("pointerup", pointer(right.x, right.y, { button: 2 }));
  assert.equal(value(node, "object_points"), "401, 301");

  await settle(env);
  assert.equal(canvas.lastLabel(), "1 object · 1 background · box 40×50");
  picker.clearButton.fire("click", pointer(0, 0));
  for (const n of ["object_points", "background_points", "box"]) assert.equal(value(node, n), "", n);
  assert.equal(value(node, "method"), "auto", "other widgets untouched");
  await settle(env);
  assert.equal(canvas.lastLabel(), "no prompt");
  assert.deepEqual(env.timers, []);
});

test("the picker redraws from widgets typed by hand or loaded with a workflow, and not without a change", async () => {
  const { env, fakes, node, picker } = await scene();
  const canvas = picker.canvas;
  let draws = canvas.count("clearRect");
  fakes.api.dispatchEvent(new Event("graphChanged"));
  fakes.app.canvas.onDrawForeground({}, [0, 0, 10, 10]);
  await settle(env);
  assert.equal(canvas.count("clearRect"), draws, "no change, no redraw");

  const w = node.widgets.find((x) => x.name === "object_points");
  w.value = "100, 100; 500, 300";
  w.callback(w.value);
  await settle(env);
  assert.equal(canvas.count("clearRect"), draws + 1, "a typed value redraws once");
  assert.equal(canvas.lastLabel(), "2 object");
  assert.equal(canvas.count("arc"), 2, "two dots");

  // A workflow is loaded: values set without callbacks, then onConfigure.
  draws = canvas.count("clearRect");
  node.widgets.find((x) => x.name === "box").value = "0, 0, 300, 200";
  node.widgets.find((x) => x.name === "background_points").value = "1, 1";
  node.onConfigure?.({});
  await settle(env);
  assert.equal(canvas.count("clearRect"), draws + 1);
  assert.equal(canvas.lastLabel(), "2 object · 1 background · box 300×200");
  assert.ok(canvas.count("strokeRect") >= 1, "the box is drawn");

  // A change with no event at all is seen on the graph canvas' next draw.
  node.widgets.find((x) => x.name === "box").value = "";
  fakes.app.canvas.onDrawForeground({}, [0, 0, 10, 10]);
  assert.equal(canvas.lastLabel(), "2 object · 1 background");

  // A click then removes the typed point it lands on.
  click(canvas, 500, 300);
  assert.equal(w.value, "100, 100");
});

test("SAM node: written in pixels (fractions converted, coordinates set), background as 'x, y, 0', Ctrl-drag adds a box", async () => {
  const widgets = SAM_WIDGETS.map(([n, v]) => [n, { points: "0.5, 0.5; 0.1, 0.1, 0, 0", boxes: "0, 0, 0.5, 0.5",
                                                    coordinates: "fraction" }[n] ?? v]);
  const { env, node, picker } = await scene("PhysMotionSAMSegment", widgets);
  const canvas = picker.canvas;
  assert.equal(canvas.lastLabel(), "1 object · 1 background · box 300×200", "fractions shown in pixels");
  click(canvas, 20, 380, { shiftKey: true });
  assert.equal(value(node, "points"), "300, 200; 60, 40, 0, 0; 20, 380, 0");
  assert.equal(value(node, "boxes"), "0, 0, 300, 200");
  assert.equal(value(node, "coordinates"), "pixels");
  drag(canvas, [320, 100], [580, 390], { ctrlKey: true });
  assert.equal(value(node, "boxes"), "0, 0, 300, 200; 320, 100, 580, 390", "Ctrl-drag: one more object");
  drag(canvas, [100, 100], [200, 200]);
  assert.equal(value(node, "boxes"), "100, 100, 200, 200", "a plain drag replaces the boxes");
  click(canvas, 300, 200);
  assert.equal(value(node, "points"), "60, 40, 0, 0; 20, 380, 0", "the clicked point is removed");
  picker.clearButton.fire("click", pointer(0, 0));
  assert.equal(value(node, "points"), "");
  assert.equal(value(node, "boxes"), "");
  assert.equal(value(node, "clean"), true);
  await settle(env);
  assert.equal(canvas.lastLabel(), "no prompt");
});

test("removing the node releases its listeners and observer; it never draws or loads again", async () => {
  const { env, fakes, graph, load, node, picker } = await scene();
  const canvas = picker.canvas;
  const observer = env.observers.find((o) => o.targets.includes(canvas));
  assert.ok(observer);
  assert.equal(canvas.active("pointerdown").length, 1);
  assert.equal(picker.clearButton.active("click").length, 1);
  node.widgets.find((x) => x.name === "box").callback("1, 1, 5, 5"); // a refresh is pending
  graph.nodes.delete(node.id);
  node.onRemoved();
  assert.equal(observer.disconnected, true);
  for (const t of ["pointerdown", "pointermove", "pointerup", "pointercancel"]) {
    assert.equal(canvas.active(t).length, 0, t);
  }
  assert.equal(picker.clearButton.active("click").length, 0);
  const draws = canvas.count("clearRect");
  const loads = env.loaded.length;
  load.widgets[0].value = "dog.png";
  fakes.api.dispatchEvent(new Event("graphChanged"));
  fakes.api.dispatchEvent(new Event("executed"));
  fakes.app.canvas.onDrawForeground({}, [0, 0, 10, 10]);
  observer.trigger();
  await settle(env);
  assert.equal(canvas.count("clearRect"), draws, "no redraw after removal");
  assert.equal(env.loaded.length, loads, "no image load after removal");
  node.domWidgets[0].onRemove(); // the DOM widget's own hook is safe as well
});

test("picks remember their photo: on another photo the label says so, and the first pick there starts afresh", async () => {
  const { env, load, node, picker } = await scene();
  click(picker.canvas, 300, 200);
  drag(picker.canvas, [100, 80], [500, 360]);
  assert.equal(node.properties.physmotion_prompt_photo, "cat.png");
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
  // the user loads their own photo into the Load Image node: the picks stay, the label warns
  load.widgets[0].value = "my photos/dog.png";
  picker.invalidate();
  await settle(env);
  assert.equal(picker.canvas.lastLabel(), "set on cat.png: click and drag again on this photo, or clear");
  assert.equal(value(node, "box"), "100, 80, 500, 360");
  // the first click on this photo replaces the old picks and belongs to it
  click(picker.canvas, 60, 40);
  assert.equal(value(node, "object_points"), "60, 40");
  assert.equal(value(node, "box"), "");
  assert.equal(node.properties.physmotion_prompt_photo, "my photos/dog.png");
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
  // back to the first photo: now these picks are the stale ones; "clear" forgets the photo too
  load.widgets[0].value = "cat.png";
  picker.invalidate();
  await settle(env);
  assert.match(picker.canvas.lastLabel(), /^set on my photos\/dog\.png/);
  picker.clearButton.fire("click", { preventDefault() {}, stopPropagation() {} });
  assert.equal(node.properties.physmotion_prompt_photo, undefined);
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
});

test("a prompt typed by hand belongs to the photo shown; a workflow's picks without a photo never warn", async () => {
  const { env, load, node, picker } = await scene();
  const box = node.widgets.find((w) => w.name === "box");
  box.value = "10, 10, 200, 200";
  box.callback(box.value); // what the frontend calls after a user edit
  assert.equal(node.properties.physmotion_prompt_photo, "cat.png");
  // picks loaded from an older workflow carry no photo: nothing to compare, no warning
  delete node.properties.physmotion_prompt_photo;
  load.widgets[0].value = "dog.png";
  picker.invalidate();
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
  // a template's picks name their photo (scripts/build_workflows.py): loading another warns at once
  node.properties.physmotion_prompt_photo = "physmotion_coffee.png";
  picker.invalidate();
  await settle(env);
  assert.match(picker.canvas.lastLabel(), /^set on physmotion_coffee\.png/);
});

test("the SAM node's fractions fit any photo: never stamped, never stale", async () => {
  const { env, load, node, picker } = await scene("PhysMotionSAMSegment",
    [["points", ""], ["boxes", "0.28, 0.03, 0.70, 0.74"], ["coordinates", "fraction"], ["clean", true]]);
  const boxes = node.widgets.find((w) => w.name === "boxes");
  boxes.callback(boxes.value);
  assert.equal(node.properties.physmotion_prompt_photo, undefined);
  node.properties.physmotion_prompt_photo = "cat.png"; // even if something left a name
  load.widgets[0].value = "dog.png";
  picker.invalidate();
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
  // a drag writes pixels: those belong to the photo shown
  drag(picker.canvas, [100, 80], [500, 360]);
  assert.equal(value(node, "coordinates"), "pixels");
  assert.equal(node.properties.physmotion_prompt_photo, "dog.png");
});

test("the mask editor's copy of the photo is the same photo: no warning, and the original keeps its name", async () => {
  const { env, load, node, picker } = await scene();
  click(picker.canvas, 300, 200);
  assert.equal(node.properties.physmotion_prompt_photo, "cat.png");
  load.widgets[0].value = "clipspace/clipspace-painted-masked-17.png [input]"; // saved by the mask editor
  picker.invalidate();
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
  click(picker.canvas, 100, 100); // a pick on the copy adds to the picks, and the name stays the original's
  assert.equal(value(node, "object_points"), "300, 200; 100, 100");
  assert.equal(node.properties.physmotion_prompt_photo, "cat.png");
  load.widgets[0].value = "cat.png";
  picker.invalidate();
  await settle(env);
  assert.doesNotMatch(picker.canvas.lastLabel(), /set on/);
});
