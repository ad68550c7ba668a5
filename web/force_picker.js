// PhysMotion force/torque picker: draws the input image inside the Force (push) and Torque (twist)
// nodes; click where the push is applied and drag an arrow for its direction and strength. On a
// Torque node a drag sets the axis (perpendicular to the arrow, like rolling a trackball) and the
// magnitude; Shift-drag twists about the viewing axis instead. The values go into the node's own
// widgets (u, v, fx, fy / tx, ty, tz, region), so they are saved with the workflow and queued as
// usual; the picker itself stores nothing but its scale (node properties).
//
// The image comes from the nearest LoadImage (or any node showing an image) linked to the node,
// following the graph in both directions (Force -> Simulate -> Lift -> LoadImage).
//
// Wiring: the frontend's `nodeCreated` hook gives each Force/Torque node its picker. Nothing polls:
// the picker refreshes when one of the node's widgets changes (their callbacks, onWidgetChanged),
// its links change (onConnectionsChange), a workflow is loaded (onConfigure, afterConfigureGraph),
// the graph changes elsewhere (the api's `graphChanged` and `executed` events, and a cheap check on
// each draw of the graph canvas), or its canvas resizes (ResizeObserver); all released on removal.

import { app } from "../../scripts/app.js";
import { api } from "../../scripts/api.js";
import {
  DEFAULT_FORCE_FULL_SCALE,
  DEFAULT_TORQUE_FULL_SCALE,
  MIN_DRAG_PX,
  PROMPT_PHOTO_PROPERTY,
  dragToForce,
  dragToTorque,
  forceToArrow,
  imageToCanvas,
  magnitude,
  nearestSource,
  showsPhoto,
  torqueToArrow,
  viewParams,
} from "./picker_math.js";
import { ImagePicker, chain, comfyClassOf, mountPicker, pickerRegistry } from "./picker_widget.js";

const PICKER_NODES = {
  PhysMotionForce: { kind: "force", scaleProperty: "picker_newtons_per_image_height",
                     defaultScale: DEFAULT_FORCE_FULL_SCALE },
  PhysMotionTorque: { kind: "torque", scaleProperty: "picker_newton_metres_per_image_height",
                      defaultScale: DEFAULT_TORQUE_FULL_SCALE },
};
const PICKER_HEIGHT = 240;

function widget(node, name) {
  return node.widgets?.find((w) => w.name === name);
}

function setWidget(node, name, value) {
  const w = widget(node, name);
  if (!w || w.value === value) return;
  w.value = value;
  w.callback?.(value, app.canvas, node);
}

function getLink(graph, id) {
  if (id == null || !graph) return null;
  if (typeof graph.getLink === "function") return graph.getLink(id);
  const links = graph.links;
  return links?.get ? links.get(id) : links?.[id];
}

function linkedIds(graph, id) {
  const node = graph?.getNodeById(id);
  if (!node) return [];
  const out = [];
  for (const input of node.inputs ?? []) {
    const link = getLink(graph, input.link);
    if (link) out.push(link.origin_id);
  }
  for (const output of node.outputs ?? []) {
    for (const lid of output.links ?? []) {
      const link = getLink(graph, lid);
      if (link) out.push(link.target_id);
    }
  }
  return out;
}

/** The URL of the picture the picker shows for `node`, or null. */
function sourceImageURL(node) {
  const graph = node.graph ?? app.graph;
  const isSource = (id) => showsPhoto(graph.getNodeById(id));
  const id = nearestSource(node.id, (i) => linkedIds(graph, i), isSource);
  if (id == null) return null;
  const src = graph.getNodeById(id);
  const imageWidget = widget(src, "image");
  if ((src.comfyClass === "LoadImage" || src.type === "LoadImage") && imageWidget?.value) {
    const p = viewParams(imageWidget.value);
    const q = new URLSearchParams({ filename: p.filename, type: p.type, subfolder: p.subfolder });
    return api.apiURL(`/view?${q.toString()}`);
  }
  return src.imgs?.[0]?.src ?? null;
}

function drawArrow(ctx, a, b, colour, width) {
  const dx = b.x - a.x;
  const dy = b.y - a.y;
  const len = Math.hypot(dx, dy);
  ctx.strokeStyle = colour;
  ctx.fillStyle = colour;
  ctx.lineWidth = width;
  ctx.beginPath();
  ctx.moveTo(a.x, a.y);
  ctx.lineTo(b.x, b.y);
  ctx.stroke();
  if (len < 1) return;
  const ux = dx / len;
  const uy = dy / len;
  const head = Math.min(12, len * 0.5);
  ctx.beginPath();
  ctx.moveTo(b.x, b.y);
  ctx.lineTo(b.x - head * ux + head * 0.5 * uy, b.y - head * uy - head * 0.5 * ux);
  ctx.lineTo(b.x - head * ux - head * 0.5 * uy, b.y - head * uy + head * 0.5 * ux);
  ctx.closePath();
  ctx.fill();
}

class Picker extends ImagePicker {
  constructor(node, spec) {
    super(node, registry, { className: "physmotion-picker", tag: spec.kind });
    this.spec = spec; // this.drag: {start:{u,v}, end:{u,v}, twist, startCanvas}
    node.properties = node.properties ?? {};
    if (node.properties[spec.scaleProperty] == null) node.properties[spec.scaleProperty] = spec.defaultScale;
    const hint = document.createElement("div");
    hint.style.cssText = "font:11px sans-serif;color:#aaa;padding:2px 4px;white-space:nowrap;overflow:hidden;";
    hint.textContent = spec.kind === "force"
      ? "drag on the object: push (start = where, arrow = direction and strength)"
      : "drag: torque axis (trackball) · Shift-drag: twist about the view axis";
    this.el.append(hint);
    this.hint = hint;
  }

  get scale() {
    const s = Number(this.node.properties?.[this.spec.scaleProperty]);
    return s > 0 ? s : this.spec.defaultScale;
  }

  values() {
    const get = (n) => Number(widget(this.node, n)?.value ?? 0);
    const names = this.spec.kind === "force" ? ["u", "v", "fx", "fy", "fz"] : ["u", "v", "tx", "ty", "tz"];
    const out = Object.fromEntries(names.map((n) => [n, get(n)]));
    out.region = widget(this.node, "region")?.value;
    out.radius = get("radius_px");
    return out;
  }

  onDown(e) {
    if (e.button !== 0) return;
    const p = this.eventPoint(e);
    const q = this.toImage(p);
    if (!q || !q.inside) return;
    e.preventDefault();
    e.stopPropagation();
    this.canvas.setPointerCapture?.(e.pointerId);
    this.drag = { start: q, end: q, startCanvas: p, twist: e.shiftKey };
    this.draw();
  }

  onMove(e) {
    if (!this.drag) return;
    e.preventDefault();
    e.stopPropagation();
    const q = this.toImage(this.eventPoint(e));
    if (q) this.drag.end = q;
    this.drag.twist = e.shiftKey || this.drag.twist;
    this.draw();
  }

  onUp(e) {
    if (!this.drag) return;
    e.preventDefault();
    e.stopPropagation();
    const q = this.toImage(this.eventPoint(e));
    if (q) this.drag.end = q;
    const p = this.eventPoint(e);
    const moved = Math.hypot(p.x - this.drag.startCanvas.x, p.y - this.drag.startCanvas.y) >= MIN_DRAG_PX;
    this.commit(this.drag, moved);
    this.drag = null;
    this.draw();
  }

  commit(drag, moved) {
    const node = this.node;
    const imgW = this.image.naturalWidth;
    const imgH = this.image.naturalHeight;
    const stepOf = (n) => {
      const o = widget(node, n)?.options ?? {};
      // litegraph stores FLOAT steps x10 in some versions; the rounding only needs the decimals.
      return Number(o.round) > 0 ? Number(o.round) : 0.1;
    };
    if (this.spec.kind === "force") {
      const f = dragToForce(drag.start, drag.end, { imgW, imgH, fullScale: this.scale, step: stepOf("fx") });
      setWidget(node, "u", f.u);
      setWidget(node, "v", f.v);
      setWidget(node, "region", "image point");
      if (moved) {
        setWidget(node, "fx", f.fx);
        setWidget(node, "fy", f.fy);
      }
    } else {
      const t = dragToTorque(drag.start, drag.end, { imgW, imgH, fullScale: this.scale, step: stepOf("tx"),
                                                     twist: drag.twist });
      setWidget(node, "u", t.u);
      setWidget(node, "v", t.v);
      if (moved) {
        setWidget(node, "tx", t.tx);
        setWidget(node, "ty", t.ty);
        setWidget(node, "tz", t.tz);
      }
    }
    this.stampPhoto();
    node.setDirtyCanvas?.(true, true);
    node.graph?.setDirtyCanvas?.(true, true);
  }

  /** Refresh on the next frame (many triggers in one frame give one refresh). */
  sourceURL() {
    return sourceImageURL(this.node);
  }

  shownState() {
    return [this.values(), this.scale, this.node.properties?.[PROMPT_PHOTO_PROPERTY] ?? null];
  }

  draw() {
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
    if (!fit) {
      ctx.fillStyle = "#888";
      ctx.font = "12px sans-serif";
      ctx.fillText("connect the graph to a Load Image node to pick on the photo", 8, 20);
      return;
    }
    ctx.drawImage(this.image, fit.offsetX, fit.offsetY, fit.width, fit.height);
    const vals = this.values();
    const imgH = this.image.naturalHeight;
    let arrow;
    let label;
    if (this.drag) {
      const d = this.drag;
      if (this.spec.kind === "force") {
        const f = dragToForce(d.start, d.end, { imgW: this.image.naturalWidth, imgH, fullScale: this.scale });
        label = `push ${magnitude(f.fx, f.fy).toFixed(1)} N`;
      } else {
        const t = dragToTorque(d.start, d.end, { imgW: this.image.naturalWidth, imgH, fullScale: this.scale,
                                                 twist: d.twist });
        label = `${d.twist ? "twist" : "torque"} ${magnitude(t.tx, t.ty, t.tz).toFixed(2)} N·m`;
      }
      arrow = { start: d.start, end: d.end, twist: 0 };
    } else if (this.spec.kind === "force") {
      arrow = forceToArrow(vals, { imgH, fullScale: this.scale });
      label = `(${vals.fx}, ${vals.fy}, ${vals.fz}) N`;
    } else {
      arrow = torqueToArrow(vals, { imgH, fullScale: this.scale });
      label = `(${vals.tx}, ${vals.ty}, ${vals.tz}) N·m`;
    }
    const a = imageToCanvas(arrow.start.u, arrow.start.v, fit);
    const b = imageToCanvas(arrow.end.u, arrow.end.v, fit);
    const showPoint = this.spec.kind === "force" ? vals.region === "image point" || this.drag
                                                  : vals.region === "image point";
    if (showPoint) {
      ctx.strokeStyle = "rgba(255,255,255,0.8)";
      ctx.lineWidth = 1;
      ctx.beginPath();
      ctx.arc(a.x, a.y, Math.max(2, vals.radius * fit.scale), 0, 2 * Math.PI);
      ctx.stroke();
    }
    const colour = this.spec.kind === "force" ? "#ff5a36" : "#36b4ff";
    drawArrow(ctx, a, b, colour, 3);
    if (arrow.twist) {
      const r = 18;
      const sweep = Math.max(-1.8 * Math.PI, Math.min(1.8 * Math.PI, arrow.twist / r));
      ctx.strokeStyle = "#ffd336";
      ctx.lineWidth = 3;
      ctx.beginPath();
      // canvas angles run clockwise (y down): a counter-clockwise twist sweeps negative angles
      ctx.arc(a.x, a.y, r, 0, -sweep, sweep > 0);
      ctx.stroke();
    }
    // The image point was set on another photo (a template's, kept after loading your own): say so.
    const stale = !this.drag && vals.region === "image point" ? this.stalePhoto() : null;
    if (stale) label = `point set on ${stale}: drag again on this photo`;
    this.drawLabel(ctx, label, h, Boolean(stale));
  }

}

/** Every Force/Torque picker on the page, and the graph-wide triggers that refresh them. */
const registry = pickerRegistry(app, api);

/** Give a Force/Torque node its picker: a DOM widget, and the node's own events wired to refresh it
 *  (and its Properties panel, which holds the picker's scale). */
function attachPicker(node, spec) {
  const picker = mountPicker(node, new Picker(node, spec), registry, {
    widgetName: "physmotion_picker", nodeField: "physmotionPicker", height: PICKER_HEIGHT,
    alsoOn: ["onPropertyChanged"],
  });
  // u, v typed by hand are the user's for the photo shown now (a workflow load sets values without callbacks)
  for (const name of ["u", "v"]) {
    const w = widget(node, name);
    if (w) chain(w, "callback", () => picker.stampPhoto());
  }
  return picker;
}

app.registerExtension({
  name: "PhysMotion.ForceTorquePicker",
  setup() {
    registry.installSharedTriggers();
  },
  // Runs after the constructor of every node the frontend creates (a new node, a pasted one, or one
  // loaded from a workflow, before its saved values are applied: onConfigure refreshes then).
  nodeCreated(node) {
    const spec = PICKER_NODES[comfyClassOf(node)];
    if (spec) attachPicker(node, spec);
  },
  // A workflow was loaded: its nodes are configured and linked now.
  afterConfigureGraph() {
    registry.invalidateAll();
  },
});
