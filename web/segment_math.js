// Pure logic of the PhysMotion segmentation-prompt picker (web/segment_picker.js): reading and
// writing the Segment nodes' prompt strings, hit-testing the drawn points, telling a click from a
// drag, normalising a dragged box, and finding the picture to show by following the graph's links.
// No DOM, no ComfyUI: unit-tested with `node --test` (tests/web/segment_math.test.mjs).
//
// Coordinates are image pixels: x = column (right), y = row (down), as the nodes read them.
//
// The two nodes' formats:
//   PhysMotionSegment     object_points      "x, y; x, y"          object points
//                         background_points  "x, y; x, y"          points that are NOT the object
//                         box                "x0, y0, x1, y1" or ""  one box
//   PhysMotionSAMSegment  points             "x, y" object, "x, y, 0" background, "x, y, label, k" point
//                                            of object number k; entries separated by ";" or new lines
//                         boxes              "x0, y0, x1, y1" entries, one object each
//                         coordinates        "pixels" | "fraction" (0..1 of the width / height)
// Entries the picker cannot read are kept verbatim (`raw`), so a hand-typed mistake is not silently
// dropped when a click rewrites the field: the node reports it when the workflow is queued.

import { nearestSource, showsPhoto, viewParams } from "./picker_math.js";

export const HIT_RADIUS_PX = 8; // canvas pixels: a click this close to a drawn point removes it
export const MIN_BOX_PX = 1; // image pixels: a dragged box narrower or lower than this is no box

export const SEGMENT_KINDS = {
  PhysMotionSegment: "grabcut",
  PhysMotionSAMSegment: "sam",
};

/** The widgets a kind of node reads its prompts from (all STRING widgets but `coordinates`). */
export const PROMPT_WIDGETS = {
  grabcut: ["object_points", "background_points", "box"],
  sam: ["points", "boxes", "coordinates"],
};

/** Split a prompt string into entries, each a list of numbers; unreadable entries come back in `raw`. */
export function parseEntries(text) {
  const entries = [];
  const raw = [];
  for (const part of String(text ?? "").split(/[;\n]/)) {
    const s = part.trim();
    if (!s) continue;
    const tokens = s.replace(/^[\s()[\]]+|[\s()[\]]+$/g, "").split(/[,\s]+/).filter((t) => t !== "");
    const nums = tokens.map(Number);
    if (tokens.length === 0 || !nums.every(Number.isFinite)) raw.push(s);
    else entries.push(nums);
  }
  return { entries, raw };
}

/** A number as a prompt string writes it: integers plain, others with at most 2 decimals, never -0. */
export function formatNumber(x) {
  const r = Math.round(x * 100) / 100;
  return String(Object.is(r, -0) ? 0 : r);
}

/** A click's image point as an integer pixel (column, row) of a imgW x imgH image. */
export function pixelPoint(u, v, imgW, imgH) {
  const clampInt = (x, hi) => Math.min(Math.max(Math.round(x), 0), Math.max(hi - 1, 0));
  return { x: clampInt(u, imgW), y: clampInt(v, imgH) };
}

/**
 * The box spanned by a drag from `a` to `b` (image points {u, v}): corners sorted, rounded to whole
 * pixels and clamped to the image (0..imgW, 0..imgH). Null when it is thinner than MIN_BOX_PX.
 */
export function normaliseBox(a, b, imgW, imgH) {
  const clamp = (x, hi) => Math.min(Math.max(Math.round(x), 0), hi);
  const x0 = clamp(Math.min(a.u, b.u), imgW);
  const x1 = clamp(Math.max(a.u, b.u), imgW);
  const y0 = clamp(Math.min(a.v, b.v), imgH);
  const y1 = clamp(Math.max(a.v, b.v), imgH);
  if (x1 - x0 < MIN_BOX_PX || y1 - y0 < MIN_BOX_PX) return null;
  return { x0, y0, x1, y1 };
}

/** Whether a pointer that went down at `start` and up at `end` (canvas pixels) dragged. */
export function isDrag(start, end, minPx) {
  return Math.hypot(end.x - start.x, end.y - start.y) >= minPx;
}

/**
 * The index of the point nearest to the canvas point `c` within `radius` canvas pixels, or -1.
 * `toCanvas(x, y)` maps an image pixel to the canvas ({x, y}).
 */
export function hitTest(points, c, toCanvas, radius = HIT_RADIUS_PX) {
  let best = -1;
  let bestD = radius;
  points.forEach((p, i) => {
    const q = toCanvas(p.x, p.y);
    const d = Math.hypot(q.x - c.x, q.y - c.y);
    if (d <= bestD) {
      best = i;
      bestD = d;
    }
  });
  return best;
}

/** An empty prompt. Points: {x, y, label: 1 object | 0 background, object?: k}; boxes: {x0, y0, x1, y1}. */
export function emptyPrompt() {
  return { points: [], boxes: [], raw: { points: [], boxes: [] } };
}

function boxOf(nums, sx, sy) {
  const [a, b, c, d] = nums;
  return { x0: Math.min(a, c) * sx, y0: Math.min(b, d) * sy, x1: Math.max(a, c) * sx, y1: Math.max(b, d) * sy };
}

/**
 * A node's prompt (in image pixels) from its widget values. `values` holds the strings of
 * PROMPT_WIDGETS[kind]. A SAM node in "fraction" coordinates is converted with the image's size
 * (imgW, imgH), to whole pixels; without a size fractions stay as they are (`fraction` is then true).
 */
export function readPrompt(kind, values, { imgW = 0, imgH = 0 } = {}) {
  const prompt = emptyPrompt();
  if (kind === "grabcut") {
    for (const [name, label] of [["object_points", 1], ["background_points", 0]]) {
      const { entries, raw } = parseEntries(values[name]);
      for (const e of entries) {
        if (e.length === 2) prompt.points.push({ x: e[0], y: e[1], label });
        else raw.push(e.join(", "));
      }
      prompt.raw.points.push(...raw.map((text) => ({ text, label })));
    }
    const { entries, raw } = parseEntries(values.box);
    for (const e of entries) {
      if (e.length === 4 && prompt.boxes.length === 0) prompt.boxes.push(boxOf(e, 1, 1));
      else raw.push(e.join(", "));
    }
    prompt.raw.boxes.push(...raw);
    return prompt;
  }
  const fraction = values.coordinates === "fraction";
  const convert = fraction && imgW > 0 && imgH > 0;
  const sx = convert ? imgW : 1;
  const sy = convert ? imgH : 1;
  const px = (x, s) => (convert ? Math.round(x * s) : x);
  prompt.fraction = fraction && !convert;
  const pts = parseEntries(values.points);
  for (const e of pts.entries) {
    const label = e.length >= 3 ? e[2] : 1;
    const k = e.length === 4 ? e[3] : undefined;
    const ok = e.length >= 2 && e.length <= 4 && (label === 0 || label === 1) &&
      (k === undefined || (Number.isInteger(k) && k >= 0));
    if (!ok) {
      pts.raw.push(e.join(", "));
      continue;
    }
    const p = { x: px(e[0], sx), y: px(e[1], sy), label };
    if (k !== undefined) p.object = k;
    prompt.points.push(p);
  }
  prompt.raw.points.push(...pts.raw.map((text) => ({ text })));
  const bxs = parseEntries(values.boxes);
  for (const e of bxs.entries) {
    if (e.length !== 4) {
      bxs.raw.push(e.join(", "));
      continue;
    }
    const b = boxOf(e, sx, sy);
    prompt.boxes.push(convert ? { x0: Math.round(b.x0), y0: Math.round(b.y0), x1: Math.round(b.x1),
                                  y1: Math.round(b.y1) } : b);
  }
  prompt.raw.boxes.push(...bxs.raw);
  return prompt;
}

const joinEntries = (entries) => entries.join("; ");
const pointText = (p) => `${formatNumber(p.x)}, ${formatNumber(p.y)}`;
const boxText = (b) => [b.x0, b.y0, b.x1, b.y1].map(formatNumber).join(", ");

/**
 * The widget values that say `prompt`: {object_points, background_points, box} for the no-model
 * Segment node, {points, boxes, coordinates: "pixels"} for the SAM node. Unreadable entries read
 * from the widgets are written back after the picker's own.
 */
export function writePrompt(kind, prompt) {
  if (kind === "grabcut") {
    const side = (label) => joinEntries([
      ...prompt.points.filter((p) => p.label === label).map(pointText),
      ...prompt.raw.points.filter((r) => r.label === label).map((r) => r.text),
    ]);
    return {
      object_points: side(1),
      background_points: side(0),
      box: joinEntries([...prompt.boxes.slice(0, 1).map(boxText), ...prompt.raw.boxes]),
    };
  }
  const points = prompt.points.map((p) => {
    if (p.object !== undefined) return `${pointText(p)}, ${p.label}, ${p.object}`;
    return p.label === 0 ? `${pointText(p)}, 0` : pointText(p);
  });
  return {
    points: joinEntries([...points, ...prompt.raw.points.map((r) => r.text)]),
    boxes: joinEntries([...prompt.boxes.map(boxText), ...prompt.raw.boxes]),
    coordinates: "pixels",
  };
}

/**
 * A click at image pixel `pixel` ({x, y}, already whole): removes the point at index `hit` if the
 * click landed on one (hit >= 0), else adds an object point (a background point with `background`).
 * Returns a new prompt; the input is not changed.
 */
export function applyClick(prompt, pixel, { hit = -1, background = false } = {}) {
  const points = prompt.points.slice();
  if (hit >= 0 && hit < points.length) points.splice(hit, 1);
  else points.push({ x: pixel.x, y: pixel.y, label: background ? 0 : 1 });
  return { ...prompt, points };
}

/**
 * A dragged box: replaces the node's box (and any unreadable box entries), or with `add` (SAM node
 * only: one object per box) is added to its boxes. Returns a new prompt.
 */
export function applyBox(prompt, box, { kind = "grabcut", add = false } = {}) {
  if (!box) return prompt;
  const keep = add && kind === "sam";
  return {
    ...prompt,
    boxes: keep ? [...prompt.boxes, box] : [box],
    raw: { ...prompt.raw, boxes: keep ? prompt.raw.boxes : [] },
  };
}

/** Whether the prompt says anything (points, boxes or unreadable entries). */
export function isEmptyPrompt(prompt) {
  return !prompt.points.length && !prompt.boxes.length && !prompt.raw.points.length && !prompt.raw.boxes.length;
}

/** A one-line summary for the picker's label: "2 object · 1 background · box 120×80". */
export function describePrompt(prompt) {
  const obj = prompt.points.filter((p) => p.label === 1).length;
  const bg = prompt.points.length - obj;
  const parts = [];
  if (obj) parts.push(`${obj} object`);
  if (bg) parts.push(`${bg} background`);
  if (prompt.boxes.length === 1) {
    const b = prompt.boxes[0];
    parts.push(`box ${formatNumber(b.x1 - b.x0)}×${formatNumber(b.y1 - b.y0)}`);
  } else if (prompt.boxes.length > 1) {
    parts.push(`${prompt.boxes.length} boxes`);
  }
  const bad = prompt.raw.points.length + prompt.raw.boxes.length;
  if (bad) parts.push(`${bad} unreadable`);
  return parts.length ? parts.join(" · ") : "no prompt";
}

// ---------------------------------------------------------------- the picture to show

const getLink = (graph, id) => {
  if (id == null || !graph) return null;
  if (typeof graph.getLink === "function") return graph.getLink(id);
  const links = graph.links;
  return links?.get ? links.get(id) : links?.[id];
};

/** The ids of the nodes feeding node `id`'s inputs. */
export function upstreamIds(graph, id) {
  const node = graph?.getNodeById(id);
  const out = [];
  for (const input of node?.inputs ?? []) {
    const link = getLink(graph, input.link);
    if (link) out.push(link.origin_id);
  }
  return out;
}

/** The ids of the nodes linked to node `id`: its inputs' sources first, then its outputs' targets. */
export function linkedIds(graph, id) {
  const node = graph?.getNodeById(id);
  const out = upstreamIds(graph, id);
  for (const output of node?.outputs ?? []) {
    for (const lid of output.links ?? []) {
      const link = getLink(graph, lid);
      if (link) out.push(link.target_id);
    }
  }
  return out;
}

const isLoadImage = (n) => n?.comfyClass === "LoadImage" || n?.type === "LoadImage";

/**
 * The URL of the picture to pick on for node `nodeId`: the nearest LoadImage (its file through
 * `apiURL("/view?...")`) or node showing an image (its first image's src). What feeds the node's
 * inputs is searched first, so the photo being segmented wins over a preview downstream; then the
 * graph in both directions. Null when there is none.
 */
export function sourceImageURL(graph, nodeId, apiURL) {
  if (!graph) return null;
  const isSource = (id) => showsPhoto(graph.getNodeById(id));
  let id = nearestSource(nodeId, (i) => upstreamIds(graph, i), isSource);
  if (id == null) id = nearestSource(nodeId, (i) => linkedIds(graph, i), isSource);
  if (id == null) return null;
  const src = graph.getNodeById(id);
  const imageWidget = src.widgets?.find((w) => w.name === "image");
  if (isLoadImage(src) && imageWidget?.value) {
    const p = viewParams(imageWidget.value);
    const q = new URLSearchParams({ filename: p.filename, type: p.type, subfolder: p.subfolder });
    return apiURL(`/view?${q.toString()}`);
  }
  return src.imgs?.[0]?.src ?? null;
}
