// PhysMotion pickers' shared wiring: how a picker (the force/torque picker, the segmentation-prompt
// picker) becomes a DOM widget of its node, which of the node's events refresh it, the graph-wide
// triggers that refresh every picker of a page, and its release on removal. No frontend imports:
// the picker files pass ComfyUI's `app` and `api` in, so this module also loads under Node's tests.
//
// A picker object has: `el` (its DOM element), `invalidate()` (redraw soon), `refresh()` (a cheap
// check that redraws only when something it shows changed), `remove()` (which calls
// `releasePicker`), and the fields `releasePicker` clears (frame, resizeObserver, listeners, image);
// the ImagePicker class below gives all of these.

import { PROMPT_PHOTO_PROPERTY, canvasToImage, fitImage, photoKey, stalePhoto } from "./picker_math.js";

/** obj[name] = its old value (if any) followed by `after`, same arguments and return value. */
export function chain(obj, name, after) {
  const prev = obj[name];
  obj[name] = function (...args) {
    const r = prev?.apply(this, args);
    after.apply(this, args);
    return r;
  };
}

/** The ComfyUI class of a node as the frontend creates it (node.type is set only after the
 *  constructor, where nodeCreated runs). */
export function comfyClassOf(node) {
  return node.comfyClass ?? node.constructor?.comfyClass ?? node.constructor?.nodeData?.name ?? node.type;
}

/** The live pickers of one extension, and its graph-wide triggers. One per picker file: each
 *  extension keeps its own set, installs its own triggers once, and forgets a picker on removal. */
export function pickerRegistry(app, api) {
  const live = new Set();
  let installed = false;
  return {
    live,
    /** Once per page: changes made elsewhere in the graph (another node's widget, a link upstream,
     *  a node's new preview image) refresh every picker. The frontend dispatches `graphChanged` on
     *  the api when the serialised graph differs after a user action, and `executed` when a node
     *  shows an output; besides, each draw of the graph canvas (it draws when something on it
     *  changed) runs the cheap refresh check of every picker, which also covers changes that raise
     *  no event. Too early (no canvas yet): the extension's setup() calls it again. */
    installSharedTriggers() {
      if (installed) return;
      const canvas = app.canvas;
      if (!canvas) return;
      installed = true;
      const invalidateAll = () => { for (const p of live) p.invalidate(); };
      api.addEventListener?.("graphChanged", invalidateAll);
      api.addEventListener?.("executed", invalidateAll);
      chain(canvas, "onDrawForeground", () => { for (const p of live) p.refresh(); });
    },
    invalidateAll() {
      for (const p of live) p.invalidate();
    },
  };
}

/** Give `node` the `picker` as a DOM widget named `widgetName` (`height` px, never serialised), with
 *  the node's own events wired to refresh it: each widget's callback (the user or the picker set
 *  it), onWidgetChanged (litegraph: a widget changed on the canvas), onConnectionsChange (a link
 *  made or removed), onConfigure (values loaded from a workflow), onAdded (put on a graph), and
 *  any `alsoOn` events (e.g. onPropertyChanged for a picker with properties); removal of the node
 *  or the widget removes the picker. `node[nodeField]` holds the picker. */
export function mountPicker(node, picker, registry, { widgetName, nodeField, height, alsoOn = [] }) {
  for (const w of node.widgets ?? []) chain(w, "callback", () => picker.invalidate());
  const w = node.addDOMWidget(widgetName, widgetName, picker.el, {
    serialize: false,
    hideOnZoom: false,
    getMinHeight: () => height,
    getHeight: () => height,
  });
  w.serialize = false; // not a backend input: never part of widgets_values or the prompt
  w.physmotionPicker = picker;
  node[nodeField] = picker;
  const invalidate = () => picker.invalidate();
  for (const event of ["onWidgetChanged", "onConnectionsChange", ...alsoOn, "onConfigure", "onAdded"]) {
    chain(node, event, invalidate);
  }
  chain(node, "onRemoved", () => picker.remove());
  chain(w, "onRemove", () => picker.remove());
  registry.live.add(picker);
  registry.installSharedTriggers();
  const size = node.computeSize?.();
  if (size) node.setSize?.([Math.max(node.size?.[0] ?? 0, 340), Math.max(node.size?.[1] ?? 0, size[1])]);
  return picker;
}

/** A picker's removal: once only; its pending frame, resize observer and every listener go, and
 *  the registry forgets it. */
export function releasePicker(picker, registry) {
  if (picker.removed) return;
  picker.removed = true;
  if (picker.frame != null) {
    if (typeof cancelAnimationFrame === "function") cancelAnimationFrame(picker.frame);
    clearTimeout(picker.frame);
    picker.frame = null;
  }
  picker.resizeObserver?.disconnect();
  picker.listeners.abort();
  registry.live.delete(picker);
  picker.image = null;
}

/** What both pickers share: the photo drawn on a canvas inside the node, pointer events mapped to
 *  the photo's pixels, redraws batched to one per frame, the photo followed through the graph and
 *  reloaded when it changes, and release on removal. A subclass appends its own controls under
 *  `this.canvas` (in `this.el`) and defines `sourceURL()` (the photo's URL or null), `shownState()`
 *  (what else the drawing depends on, JSON-able), `draw()`, and `onDown/onMove/onUp(e)`. */
export class ImagePicker {
  constructor(node, registry, { className, tag }) {
    this.node = node;
    this.registry = registry;
    this.image = null;
    this.imageURL = null;
    this.drag = null;
    this.stateKey = "";

    const el = document.createElement("div");
    el.className = className;
    el.style.cssText = "width:100%;height:100%;display:flex;flex-direction:column;";
    const canvas = document.createElement("canvas");
    canvas.style.cssText = "flex:1 1 auto;width:100%;min-height:120px;cursor:crosshair;touch-action:none;" +
      "background:#1b1b1b;border-radius:4px;";
    canvas.dataset.physmotionPicker = tag;
    el.append(canvas);
    this.el = el;
    this.canvas = canvas;

    // Everything this picker listens to is released at once on removal.
    this.listeners = new AbortController();
    const opts = this.listenerOptions();
    canvas.addEventListener("pointerdown", (e) => this.onDown(e), opts);
    canvas.addEventListener("pointermove", (e) => this.onMove(e), opts);
    canvas.addEventListener("pointerup", (e) => this.onUp(e), opts);
    canvas.addEventListener("pointercancel", () => { this.drag = null; this.draw(); }, opts);

    // No timer: the picker refreshes when something it shows may have changed (see mountPicker and
    // the registry's shared triggers); a resize of its canvas is one of those things.
    this.frame = null;
    this.removed = false;
    this.resizeObserver = typeof ResizeObserver === "function" ? new ResizeObserver(() => this.invalidate()) : null;
    this.resizeObserver?.observe(canvas);
  }

  /** Options for a listener that goes when the picker is removed. */
  listenerOptions() {
    return { signal: this.listeners.signal };
  }

  /** Where the photo sits on the canvas (fitImage's answer), or null before it has loaded. */
  fit() {
    if (!this.image?.naturalWidth) return null;
    return fitImage(this.image.naturalWidth, this.image.naturalHeight, this.canvas.clientWidth, this.canvas.clientHeight);
  }

  eventPoint(e) {
    const r = this.canvas.getBoundingClientRect();
    // The node may be zoomed (a CSS transform): map client pixels to the canvas' own pixels.
    const x = (e.clientX - r.left) * (this.canvas.clientWidth / (r.width || 1));
    const y = (e.clientY - r.top) * (this.canvas.clientHeight / (r.height || 1));
    return { x, y };
  }

  /** A canvas point in the photo's pixels ({u, v, inside}), or null before the photo has loaded. */
  toImage(p) {
    const fit = this.fit();
    if (!fit) return null;
    return canvasToImage(p.x, p.y, fit, this.image.naturalWidth, this.image.naturalHeight);
  }

  /** Redraw at the next frame (once, however often it is asked). */
  invalidate() {
    if (this.removed || this.frame != null) return;
    const run = () => { this.frame = null; this.refresh(); };
    this.frame = typeof requestAnimationFrame === "function" ? requestAnimationFrame(run) : setTimeout(run, 0);
  }

  /** Follow the graph to the photo (loading it if it changed) and redraw if anything shown changed.
   *  Cheap when nothing changed: a walk over the few linked nodes and one string compare. */
  refresh() {
    if (this.removed || !this.node.graph) return;
    const url = this.sourceURL();
    if (url !== this.imageURL) {
      this.imageURL = url;
      this.image = null;
      if (url) {
        const img = new Image();
        img.onload = () => { if (this.imageURL === url && !this.removed) { this.image = img; this.draw(); } };
        img.onerror = () => { if (this.imageURL === url && !this.removed) { this.image = null; this.draw(); } };
        img.src = url;
      }
    }
    const key = JSON.stringify([url, this.shownState(), this.canvas.clientWidth, this.canvas.clientHeight]);
    if (key !== this.stateKey) {
      this.stateKey = key;
      this.draw();
    }
  }

  /** Remember, in the node's properties (saved with the workflow), the input photo the picks are on. */
  stampPhoto() {
    const key = photoKey(this.imageURL);
    const props = (this.node.properties = this.node.properties ?? {});
    // the mask editor's copy (clipspace/...) is the same photo: keep the name of the one it came from
    if (key?.startsWith("clipspace/") && props[PROMPT_PHOTO_PROPERTY]) return;
    if (key) props[PROMPT_PHOTO_PROPERTY] = key;
    else delete props[PROMPT_PHOTO_PROPERTY];
  }

  /** Forget the photo the picks were on (they are gone). */
  clearStamp() {
    if (this.node.properties) delete this.node.properties[PROMPT_PHOTO_PROPERTY];
  }

  /** The photo the picks were set on, when the node now shows another one (else null). */
  stalePhoto() {
    return stalePhoto(this.node.properties?.[PROMPT_PHOTO_PROPERTY], photoKey(this.imageURL));
  }

  /** The label at the foot of the picture: white on grey, or on orange for a warning. */
  drawLabel(ctx, label, h, warn = false) {
    ctx.font = "12px sans-serif";
    ctx.fillStyle = warn ? "rgba(200,90,0,0.9)" : "rgba(0,0,0,0.6)";
    ctx.fillRect(4, h - 20, ctx.measureText(label).width + 8, 16);
    ctx.fillStyle = "#fff";
    ctx.fillText(label, 8, h - 8);
  }

  remove() {
    releasePicker(this, this.registry);
  }
}
