// Pure geometry of the PhysMotion force/torque picker: no DOM, no ComfyUI, so it is unit-tested
// with `node --test` (tests/web/picker_math.test.js).
//
// Coordinates: canvas pixels (the widget's drawing area, origin top-left) and image pixels (u
// right, v down: the Force/Torque nodes' u, v widgets). World axes as in the pack: +x right, +y up,
// +z towards the camera, so image-down is world -y.
//
// Strength: an arrow as long as the image's height means `fullScale` (newtons for a force, N·m for a
// torque). The scale is a node property, so it is saved with the workflow.

export const DEFAULT_FORCE_FULL_SCALE = 50.0; // N for an arrow one image-height long
export const DEFAULT_TORQUE_FULL_SCALE = 2.0; // N·m for an arrow one image-height long
export const MIN_DRAG_PX = 3; // shorter drags (in canvas pixels) are clicks: they only move the point

/** Contain-fit of an imgW x imgH image into a boxW x boxH area, centred. */
export function fitImage(imgW, imgH, boxW, boxH) {
  if (!(imgW > 0 && imgH > 0 && boxW > 0 && boxH > 0)) {
    return { scale: 0, offsetX: 0, offsetY: 0, width: 0, height: 0 };
  }
  const scale = Math.min(boxW / imgW, boxH / imgH);
  const width = imgW * scale;
  const height = imgH * scale;
  return { scale, offsetX: (boxW - width) / 2, offsetY: (boxH - height) / 2, width, height };
}

/** Canvas point -> image pixel (u, v), clamped to the image; `inside` says whether it was on it. */
export function canvasToImage(x, y, fit, imgW, imgH) {
  if (!(fit.scale > 0)) return { u: 0, v: 0, inside: false };
  const u = (x - fit.offsetX) / fit.scale;
  const v = (y - fit.offsetY) / fit.scale;
  const inside = u >= 0 && v >= 0 && u <= imgW && v <= imgH;
  return { u: Math.min(Math.max(u, 0), imgW), v: Math.min(Math.max(v, 0), imgH), inside };
}

/** Image pixel -> canvas point. */
export function imageToCanvas(u, v, fit) {
  return { x: fit.offsetX + u * fit.scale, y: fit.offsetY + v * fit.scale };
}

/** Round to the precision of a widget step (0.1 -> one decimal), never to -0. */
export function roundToStep(value, step = 0.01) {
  const decimals = Math.max(0, Math.min(6, Math.round(-Math.log10(step > 0 ? step : 0.01))));
  const f = 10 ** decimals;
  const r = Math.round(value * f) / f;
  return Object.is(r, -0) ? 0 : r;
}

/** Pixel column/row widget values (INT) of an image point. */
export function pixelOf(point, imgW, imgH) {
  const clampInt = (x, hi) => Math.min(Math.max(Math.round(x), 0), Math.max(hi - 1, 0));
  return { u: clampInt(point.u, imgW), v: clampInt(point.v, imgH) };
}

/**
 * A push from a drag in image pixels: applied at `start`, along the arrow, with a strength
 * proportional to its length. Returns the Force node's widget values {u, v, fx, fy}.
 */
export function dragToForce(start, end, { imgW, imgH, fullScale = DEFAULT_FORCE_FULL_SCALE, step = 0.1 }) {
  const k = fullScale / imgH;
  const { u, v } = pixelOf(start, imgW, imgH);
  return {
    u,
    v,
    fx: roundToStep((end.u - start.u) * k, step),
    fy: roundToStep(-(end.v - start.v) * k, step), // image down is world -y
  };
}

/**
 * A torque from a drag in image pixels. A plain drag turns the object like a trackball: the axis
 * lies in the image plane, perpendicular to the arrow (drag right: about +y, the front moves right;
 * drag up: about -x, the front moves up). With `twist` the drag turns it about the viewing axis
 * (z): dragging right turns it clockwise as the camera sees it (tz < 0).
 * Returns the Torque node's widget values {u, v, tx, ty, tz}.
 */
export function dragToTorque(start, end, { imgW, imgH, fullScale = DEFAULT_TORQUE_FULL_SCALE, step = 0.1,
                                           twist = false }) {
  const k = fullScale / imgH;
  const dx = (end.u - start.u) * k;
  const dyUp = -(end.v - start.v) * k;
  const { u, v } = pixelOf(start, imgW, imgH);
  if (twist) {
    return { u, v, tx: 0, ty: 0, tz: roundToStep(-dx, step) };
  }
  // axis = z x d with d = (dx, dyUp, 0): (-dyUp, dx, 0)
  return { u, v, tx: roundToStep(-dyUp, step), ty: roundToStep(dx, step), tz: 0 };
}

/** The arrow (image pixels) that shows a Force node's current (fx, fy) at (u, v). */
export function forceToArrow({ u, v, fx, fy }, { imgH, fullScale = DEFAULT_FORCE_FULL_SCALE }) {
  const k = imgH / fullScale;
  return { start: { u, v }, end: { u: u + fx * k, v: v - fy * k } };
}

/**
 * The arrow that shows a Torque node's in-image-plane axis (tx, ty) as the drag that made it,
 * plus the twist tz as a signed arc length (image pixels, positive = counter-clockwise).
 */
export function torqueToArrow({ u, v, tx, ty, tz }, { imgH, fullScale = DEFAULT_TORQUE_FULL_SCALE }) {
  const k = imgH / fullScale;
  // inverse of tx = -dyUp, ty = dx  (dyUp = -(end.v - start.v))
  return { start: { u, v }, end: { u: u + ty * k, v: v + tx * k }, twist: tz * k };
}

/** Magnitude of a vector given as numbers. */
export function magnitude(...c) {
  return Math.sqrt(c.reduce((s, x) => s + x * x, 0));
}

/**
 * The file a LoadImage widget value names, as /view query parameters. Values look like
 * "photo.png", "sub/dir/photo.png" or "photo.png [output]" (an annotated folder type).
 */
export function viewParams(widgetValue) {
  let name = String(widgetValue ?? "").trim();
  let type = "input";
  const m = name.match(/^(.*?)\s*\[(input|output|temp)\]$/);
  if (m) {
    name = m[1];
    type = m[2];
  }
  const slash = name.lastIndexOf("/");
  const subfolder = slash >= 0 ? name.slice(0, slash) : "";
  const filename = slash >= 0 ? name.slice(slash + 1) : name;
  return { filename, subfolder, type };
}

/**
 * Nodes whose picture is not the photo: the Segment nodes show the outlined photo beside the filled
 * background, under a caption bar, so a point picked on it would land elsewhere in the photo.
 */
export const OVERLAY_NODES = new Set(["PhysMotionSegment", "PhysMotionSAMSegment"]);

/** Whether node `n` shows a picture to pick points on: a LoadImage, or any other node showing an image
 * except the Segment nodes (OVERLAY_NODES). */
export function showsPhoto(n) {
  if (!n) return false;
  if (n.comfyClass === "LoadImage" || n.type === "LoadImage") return true;
  if (OVERLAY_NODES.has(n.comfyClass ?? n.type)) return false;
  return (n.imgs?.length ?? 0) > 0;
}

/**
 * The nearest node (by links, either direction) accepted by `isSource`, starting from `startId`.
 * `neighbours(id)` lists the ids linked to node `id`. Breadth-first, so the closest image wins; ties
 * keep the neighbours' order. Returns the id or null.
 */
export function nearestSource(startId, neighbours, isSource, maxNodes = 500) {
  const seen = new Set([startId]);
  let frontier = [startId];
  while (frontier.length && seen.size <= maxNodes) {
    const next = [];
    for (const id of frontier) {
      for (const n of neighbours(id)) {
        if (seen.has(n)) continue;
        seen.add(n);
        if (isSource(n)) return n;
        next.push(n);
      }
    }
    frontier = next;
  }
  return null;
}

/**
 * The node property that names the photo a picker's points and box were set on (saved with the
 * workflow): when the Load Image feeding the node shows another photo, the picks are stale (a
 * template's box around the example cup, kept after the user loaded their own photo).
 */
export const PROMPT_PHOTO_PROPERTY = "physmotion_prompt_photo";

/**
 * The input photo behind a picker's image URL, named as Load Image's widget names it
 * ("name.png", "sub/name.png"), or null for anything that is not an input photo (another node's
 * preview: temp or output images change name from run to run, so they are never compared).
 */
export function photoKey(url) {
  if (!url) return null;
  const s = String(url);
  const q = s.indexOf("?");
  if (q < 0) return null;
  const p = new URLSearchParams(s.slice(q + 1));
  const filename = p.get("filename");
  if (!filename || (p.get("type") ?? "input") !== "input") return null;
  const sub = p.get("subfolder") ?? "";
  return sub ? `${sub}/${filename}` : filename;
}

/** The photo the picks were set on when it is not the one shown now (else null). A photo from ComfyUI's
 *  mask editor ("clipspace/...": the same picture with a painted mask) never counts as another photo. */
export function stalePhoto(stamp, key) {
  if (!stamp || !key || key.startsWith("clipspace/")) return null;
  return String(stamp) !== key ? String(stamp) : null;
}
