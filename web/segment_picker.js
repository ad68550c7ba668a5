// PhysMotion segmentation-prompt picker: draws the input photo inside the Segment nodes
// (PhysMotionSegment, PhysMotionSAMSegment) and turns clicks on it into their prompt widgets:
//
//   click                  an object point (green dot)
//   Shift-click            a background point (red dot): a pixel that is NOT the object
//   click on a dot         removes that point
//   drag                   the box around the object (a new drag replaces the box)
//   Ctrl-drag (SAM node)   one more box: SAM segments one object per box
//   "clear" button         removes every point and box
//
// The values go into the node's own widgets (object_points / background_points / box, or points /
// boxes / coordinates on the SAM node, always written in pixels), so they are saved with the workflow
// and queued as usual; the picker stores nothing of its own, and redraws from the widgets whenever
// they change (typed by hand, a workflow loaded). Parsing, formatting and geometry live in
// segment_math.js (unit-tested).
//
// The photo comes from the nearest LoadImage (or node showing an image) feeding the node, else the
// nearest one linked either way. Nothing polls: the picker refreshes on the node's widget callbacks,
// onWidgetChanged, onConnectionsChange, onConfigure/onAdded, afterConfigureGraph, the api's
// `graphChanged` and `executed` events, a cheap check on each draw of the graph canvas, and a
// ResizeObserver on its canvas; everything is released when the node is removed.

import { app } from "../../scripts/app.js";
import { api } from "../../scripts/api.js";
import { MIN_DRAG_PX, PROMPT_PHOTO_PROPERTY, imageToCanvas } from "./picker_math.js";
import { ImagePicker, chain, comfyClassOf, mountPicker, pickerRegistry } from "./picker_widget.js";
import {
  PROMPT_WIDGETS,
  SEGMENT_KINDS,
  applyBox,
  applyClick,
  describePrompt,
  emptyPrompt,
  hitTest,
  isDrag,
  isEmptyPrompt,
  normaliseBox,
  pixelPoint,
  readPrompt,
  sourceImageURL,
  writePrompt,
} from "./segment_math.js";

const PICKER_HEIGHT = 260;
const OBJECT_COLOUR = "#35d04a";
const BACKGROUND_COLOUR = "#ff4040";
const BOX_COLOUR = "#ffd336";

const HINTS = {
  grabcut: "click: object · Shift-click: background · drag: box · click a dot: remove",
  sam: "click: object · Shift-click: background · drag: box (Ctrl-drag: another object) · click a dot: remove",
};

function widget(node, name) {
  return node.widgets?.find((w) => w.name === name);
}

function setWidget(node, name, value) {
  const w = widget(node, name);
  if (!w || w.value === value) return;
  w.value = value;
  w.callback?.(value, app.canvas, node);
}

class SegmentPicker extends ImagePicker {
  constructor(node, kind) {
    super(node, registry, { className: "physmotion-segment-picker", tag: `segment-${kind}` });
    this.kind = kind; // this.drag: {startCanvas, endCanvas, start:{u,v}, end:{u,v}, background, add}
    const row = document.createElement("div");
    row.style.cssText = "display:flex;align-items:center;gap:6px;padding:2px 4px;";
    const hint = document.createElement("div");
    hint.style.cssText = "flex:1 1 auto;font:11px sans-serif;color:#aaa;white-space:nowrap;overflow:hidden;" +
      "text-overflow:ellipsis;";
    hint.textContent = HINTS[kind];
    hint.title = HINTS[kind];
    const clear = document.createElement("button");
    clear.type = "button";
    clear.textContent = "clear";
    clear.title = "remove every point and box";
    clear.style.cssText = "flex:0 0 auto;font:11px sans-serif;padding:1px 8px;cursor:pointer;";
    row.append(hint, clear);
    this.el.append(row);
    this.hint = hint;
    this.clearButton = clear;
    const opts = this.listenerOptions();
    clear.addEventListener("pointerdown", (e) => e.stopPropagation(), opts);
    clear.addEventListener("click", (e) => { e.preventDefault?.(); e.stopPropagation?.(); this.clear(); }, opts);
  }

  /** The node's prompt widget values (strings; `coordinates` on the SAM node). */
  values() {
    return Object.fromEntries(PROMPT_WIDGETS[this.kind].map((n) => [n, widget(this.node, n)?.value ?? ""]));
  }

  imageSize() {
    return { imgW: this.image?.naturalWidth ?? 0, imgH: this.image?.naturalHeight ?? 0 };
  }

  /** The prompt the widgets say now, in pixels of the shown photo. */
  prompt() {
    return readPrompt(this.kind, this.values(), this.imageSize());
  }

  onDown(e) {
    if (e.button !== 0) return;
    const p = this.eventPoint(e);
    const q = this.toImage(p);
    if (!q || !q.inside) return;
    e.preventDefault();
    e.stopPropagation();
    this.canvas.setPointerCapture?.(e.pointerId);
    this.drag = { startCanvas: p, endCanvas: p, start: q, end: q, background: e.shiftKey,
                  add: e.ctrlKey || e.metaKey };
    this.draw();
  }

  onMove(e) {
    if (!this.drag) return;
    e.preventDefault();
    e.stopPropagation();
    const p = this.eventPoint(e);
    const q = this.toImage(p);
    this.drag.endCanvas = p;
    if (q) this.drag.end = q;
    this.draw();
  }

  onUp(e) {
    const d = this.drag;
    if (!d) return;
    e.preventDefault();
    e.stopPropagation();
    const p = this.eventPoint(e);
    const q = this.toImage(p);
    d.endCanvas = p;
    if (q) d.end = q;
    this.drag = null;
    if (this.image) {
      const { imgW, imgH } = this.imageSize();
      // picks set on another photo are not added to: the first pick on this photo starts afresh
      const prompt = this.staleOn() ? emptyPrompt() : this.prompt();
      if (isDrag(d.startCanvas, d.endCanvas, MIN_DRAG_PX)) {
        const box = normaliseBox(d.start, d.end, imgW, imgH);
        if (box) this.write(applyBox(prompt, box, { kind: this.kind, add: d.add || e.ctrlKey || e.metaKey }));
      } else {
        const fit = this.fit();
        const hit = hitTest(prompt.points, d.startCanvas, (x, y) => imageToCanvas(x, y, fit));
        const pixel = pixelPoint(d.start.u, d.start.v, imgW, imgH);
        this.write(applyClick(prompt, pixel, { hit, background: d.background || e.shiftKey }));
      }
    }
    this.draw();
  }

  /** Put a prompt into the node's widgets (each through its callback, as a user edit would). */
  write(prompt) {
    if (prompt.fraction) return; // fractions of an image of unknown size: nothing sensible to write
    const node = this.node;
    for (const [name, value] of Object.entries(writePrompt(this.kind, prompt))) setWidget(node, name, value);
    this.promptEdited();
    node.setDirtyCanvas?.(true, true);
    node.graph?.setDirtyCanvas?.(true, true);
    this.invalidate();
  }

  clear() {
    const node = this.node;
    for (const [name, value] of Object.entries(writePrompt(this.kind, emptyPrompt()))) {
      if (name !== "coordinates") setWidget(node, name, value);
    }
    this.clearStamp();
    node.setDirtyCanvas?.(true, true);
    node.graph?.setDirtyCanvas?.(true, true);
    this.invalidate();
  }

  /** The prompt changed (picked, or typed into a widget): it belongs to the photo shown now. */
  promptEdited() {
    if (!this.photoBound() || isEmptyPrompt(this.prompt())) this.clearStamp();
    else this.stampPhoto();
  }

  /** Whether the prompt is in the photo's pixels (the SAM node's fractions fit any photo). */
  photoBound() {
    return this.kind === "grabcut" || this.values().coordinates !== "fraction";
  }

  /** The photo the prompt was set on, when it is in pixels, says something, and the photo shown is another. */
  staleOn() {
    return this.photoBound() && !isEmptyPrompt(this.prompt()) ? this.stalePhoto() : null;
  }

  sourceURL() {
    return sourceImageURL(this.node.graph, this.node.id, (route) => api.apiURL(route));
  }

  shownState() {
    return [this.values(), this.node.properties?.[PROMPT_PHOTO_PROPERTY] ?? null];
  }

  draw() {
    if (this.removed) return;
    const c = this.canvas;
    const dpr = window.devicePixelRatio || 1;
    const w = c.clientWidth;
    const h = c.clientHeight;
    if (c.width !== Math.round(w * dpr) || c.height !== Math.round(h * dpr)) {
      c.width = Math.round(w * dpr);
      c.height = Math.round(h * dpr);
    }
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const fit = this.fit();
    ctx.font = "12px sans-serif";
    if (!fit) {
      ctx.fillStyle = "#888";
      ctx.fillText("connect the image input to a Load Image node to pick on the photo", 8, 20);
      return;
    }
    ctx.drawImage(this.image, fit.offsetX, fit.offsetY, fit.width, fit.height);
    const prompt = this.prompt();
    const toCanvas = (x, y) => imageToCanvas(x, y, fit);
    let label = describePrompt(prompt);
    // Points or a box set on another photo (a template's, kept after loading your own): say so.
    const stale = this.staleOn();
    if (stale) label = `set on ${stale}: click and drag again on this photo, or clear`;
    if (prompt.fraction) {
      label = "fractions: click to rewrite in pixels";
    } else {
      prompt.boxes.forEach((b, i) => {
        const a = toCanvas(b.x0, b.y0);
        const z = toCanvas(b.x1, b.y1);
        this.drawBox(ctx, a, z, BOX_COLOUR, prompt.boxes.length > 1 ? String(i) : "");
      });
      for (const p of prompt.points) {
        const q = toCanvas(p.x, p.y);
        ctx.beginPath();
        ctx.arc(q.x, q.y, 5, 0, 2 * Math.PI);
        ctx.fillStyle = p.label === 1 ? OBJECT_COLOUR : BACKGROUND_COLOUR;
        ctx.fill();
        ctx.lineWidth = 1.5;
        ctx.strokeStyle = "#fff";
        ctx.stroke();
        if (p.object !== undefined) {
          ctx.fillStyle = "#fff";
          ctx.fillText(String(p.object), q.x + 7, q.y - 6);
        }
      }
    }
    const d = this.drag;
    if (d && isDrag(d.startCanvas, d.endCanvas, MIN_DRAG_PX)) {
      const { imgW, imgH } = this.imageSize();
      const box = normaliseBox(d.start, d.end, imgW, imgH);
      if (box) {
        this.drawBox(ctx, toCanvas(box.x0, box.y0), toCanvas(box.x1, box.y1), "#ffffff", "");
        label = `box ${box.x0}, ${box.y0}, ${box.x1}, ${box.y1}`;
      }
    }
    this.drawLabel(ctx, label, h, Boolean(stale) && !(d && isDrag(d.startCanvas, d.endCanvas, MIN_DRAG_PX)));
  }

  drawBox(ctx, a, z, colour, tag) {
    ctx.setLineDash?.([6, 4]);
    ctx.lineWidth = 2;
    ctx.strokeStyle = colour;
    ctx.strokeRect(a.x, a.y, z.x - a.x, z.y - a.y);
    ctx.setLineDash?.([]);
    if (tag) {
      ctx.fillStyle = colour;
      ctx.fillText(tag, a.x + 4, a.y + 14);
    }
  }

}

/** Every segment picker on the page, and the graph-wide triggers that refresh them. */
const registry = pickerRegistry(app, api);

/** Give a Segment node its picker: a DOM widget, and the node's own events wired to refresh it. */
function attachPicker(node, kind) {
  const picker = mountPicker(node, new SegmentPicker(node, kind), registry, {
    widgetName: "physmotion_segment_picker", nodeField: "physmotionSegmentPicker", height: PICKER_HEIGHT,
  });
  // a prompt typed by hand is the user's for the photo shown now (a workflow load sets values without callbacks)
  for (const name of PROMPT_WIDGETS[kind]) {
    const w = widget(node, name);
    if (w && name !== "coordinates") chain(w, "callback", () => picker.promptEdited());
  }
  return picker;
}

app.registerExtension({
  name: "PhysMotion.SegmentPicker",
  setup() {
    registry.installSharedTriggers();
  },
  nodeCreated(node) {
    const kind = SEGMENT_KINDS[comfyClassOf(node)];
    if (kind) attachPicker(node, kind);
  },
  afterConfigureGraph() {
    registry.invalidateAll();
  },
});
