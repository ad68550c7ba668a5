// Unit tests of the segmentation-prompt picker's pure logic (web/segment_math.js): `node --test tests/web/`.
import assert from "node:assert/strict";
import { test } from "node:test";

import { fitImage, imageToCanvas } from "../../web/picker_math.js";
import {
  HIT_RADIUS_PX, PROMPT_WIDGETS, SEGMENT_KINDS, applyBox, applyClick, describePrompt, emptyPrompt, formatNumber,
  hitTest, isDrag, isEmptyPrompt, linkedIds, normaliseBox, parseEntries, pixelPoint, readPrompt, sourceImageURL,
  upstreamIds, writePrompt,
} from "../../web/segment_math.js";

test("prompt strings split on ';' and new lines; brackets and spaces are tolerated; unreadable entries kept", () => {
  assert.deepEqual(parseEntries("10, 20; 30,40\n(5 6 0)\n\n ; [1, 2, 3, 4] "), {
    entries: [[10, 20], [30, 40], [5, 6, 0], [1, 2, 3, 4]], raw: [],
  });
  assert.deepEqual(parseEntries(""), { entries: [], raw: [] });
  assert.deepEqual(parseEntries(undefined), { entries: [], raw: [] });
  assert.deepEqual(parseEntries("1, 2; abc; 3, x"), { entries: [[1, 2]], raw: ["abc", "3, x"] });
  assert.deepEqual(parseEntries("1.5, -2e1"), { entries: [[1.5, -20]], raw: [] });
});

test("numbers are written plainly: integers as such, two decimals at most, no -0", () => {
  assert.equal(formatNumber(12), "12");
  assert.equal(formatNumber(12.3456), "12.35");
  assert.equal(formatNumber(-0.001), "0");
  assert.equal(formatNumber(0.5), "0.5");
});

test("a click becomes a whole pixel (column, row) clamped into the image", () => {
  assert.deepEqual(pixelPoint(10.4, 20.6, 600, 400), { x: 10, y: 21 });
  assert.deepEqual(pixelPoint(-3, 400, 600, 400), { x: 0, y: 399 });
  assert.deepEqual(pixelPoint(599.7, 0.2, 600, 400), { x: 599, y: 0 });
});

test("a dragged box is sorted, rounded and clamped to the image; a thin one is no box", () => {
  assert.deepEqual(normaliseBox({ u: 300.6, v: 50.2 }, { u: 100.4, v: 250.5 }, 600, 400),
    { x0: 100, y0: 50, x1: 301, y1: 251 });
  assert.deepEqual(normaliseBox({ u: -20, v: 390 }, { u: 700, v: 500 }, 600, 400),
    { x0: 0, y0: 390, x1: 600, y1: 400 });
  assert.equal(normaliseBox({ u: 10, v: 100 }, { u: 300, v: 100.3 }, 600, 400), null, "a horizontal line");
  assert.equal(normaliseBox({ u: 10, v: 10 }, { u: 10.2, v: 10.2 }, 600, 400), null);
});

test("a pointer moved less than the threshold is a click, further a drag", () => {
  assert.equal(isDrag({ x: 10, y: 10 }, { x: 12, y: 12 }, 3), false); // 2.83 px
  assert.equal(isDrag({ x: 10, y: 10 }, { x: 13, y: 10 }, 3), true);
  assert.equal(isDrag({ x: 10, y: 10 }, { x: 10, y: 10 }, 3), false);
});

test("hit-testing finds the nearest point within the radius, in canvas pixels (so at any zoom)", () => {
  const fit = fitImage(600, 400, 300, 300); // scale 0.5, 50 px bar above
  const toCanvas = (x, y) => imageToCanvas(x, y, fit);
  const points = [{ x: 100, y: 100 }, { x: 110, y: 100 }, { x: 400, y: 300 }];
  // (100, 100) is at canvas (50, 100); (110, 100) at (55, 100).
  assert.equal(hitTest(points, { x: 50, y: 100 }, toCanvas), 0);
  assert.equal(hitTest(points, { x: 54, y: 101 }, toCanvas), 1, "the nearer of two close points");
  assert.equal(hitTest(points, { x: 200, y: 200 }, toCanvas), 2);
  assert.equal(hitTest(points, { x: 200, y: 200 + HIT_RADIUS_PX + 0.5 }, toCanvas), -1);
  assert.equal(hitTest(points, { x: 120, y: 30 }, toCanvas), -1);
  assert.equal(hitTest([], { x: 0, y: 0 }, toCanvas), -1);
});

test("the node classes map to their prompt widgets", () => {
  assert.deepEqual(SEGMENT_KINDS, { PhysMotionSegment: "grabcut", PhysMotionSAMSegment: "sam" });
  assert.deepEqual(PROMPT_WIDGETS.grabcut, ["object_points", "background_points", "box"]);
  assert.deepEqual(PROMPT_WIDGETS.sam, ["points", "boxes", "coordinates"]);
});

test("no-model Segment: object points, background points and one box are read and written back", () => {
  const values = { object_points: "120, 80; 130.5, 90", background_points: "5, 5", box: "200, 150, 40, 30" };
  const p = readPrompt("grabcut", values);
  assert.deepEqual(p.points, [{ x: 120, y: 80, label: 1 }, { x: 130.5, y: 90, label: 1 }, { x: 5, y: 5, label: 0 }]);
  assert.deepEqual(p.boxes, [{ x0: 40, y0: 30, x1: 200, y1: 150 }], "corners sorted");
  assert.deepEqual(writePrompt("grabcut", p),
    { object_points: "120, 80; 130.5, 90", background_points: "5, 5", box: "40, 30, 200, 150" });
  const empty = readPrompt("grabcut", { object_points: "", background_points: "", box: "" });
  assert.ok(isEmptyPrompt(empty));
  assert.deepEqual(writePrompt("grabcut", empty), { object_points: "", background_points: "", box: "" });
  assert.ok(isEmptyPrompt(readPrompt("grabcut", {})), "missing widgets read as empty");
});

test("no-model Segment: unreadable entries survive a rewrite in their own field", () => {
  const p = readPrompt("grabcut", { object_points: "1, 2; oops; 3, 4, 5", background_points: "7, 8; ?",
                                    box: "1, 2, 3" });
  assert.equal(p.points.length, 2);
  assert.equal(describePrompt(p), "1 object · 1 background · 4 unreadable");
  const q = applyClick(p, { x: 9, y: 9 });
  assert.deepEqual(writePrompt("grabcut", q),
    { object_points: "1, 2; 9, 9; oops; 3, 4, 5", background_points: "7, 8; ?", box: "1, 2, 3" });
  // A dragged box replaces the unreadable one.
  const r = applyBox(q, { x0: 1, y0: 1, x1: 50, y1: 60 });
  assert.equal(writePrompt("grabcut", r).box, "1, 1, 50, 60");
  // A second typed box is kept as written (the node says it takes one), until a drag replaces both.
  const two = readPrompt("grabcut", { box: "0, 0, 10, 10; 5, 5, 20, 20" });
  assert.equal(two.boxes.length, 1);
  assert.equal(writePrompt("grabcut", two).box, "0, 0, 10, 10; 5, 5, 20, 20");
  assert.equal(writePrompt("grabcut", applyBox(two, { x0: 2, y0: 2, x1: 9, y1: 9 })).box, "2, 2, 9, 9");
});

test("SAM: labels and object numbers are read, and written in the node's format", () => {
  const values = { points: "320, 240; 40, 20, 0\n50, 60, 1; 70, 80, 1, 2; 90, 95, 0, 1", boxes: "10, 20, 110, 220; 300,300,200,250",
                   coordinates: "pixels" };
  const p = readPrompt("sam", values);
  assert.deepEqual(p.points, [
    { x: 320, y: 240, label: 1 }, { x: 40, y: 20, label: 0 }, { x: 50, y: 60, label: 1 },
    { x: 70, y: 80, label: 1, object: 2 }, { x: 90, y: 95, label: 0, object: 1 },
  ]);
  assert.deepEqual(p.boxes, [{ x0: 10, y0: 20, x1: 110, y1: 220 }, { x0: 200, y0: 250, x1: 300, y1: 300 }]);
  assert.deepEqual(writePrompt("sam", p), {
    points: "320, 240; 40, 20, 0; 50, 60; 70, 80, 1, 2; 90, 95, 0, 1",
    boxes: "10, 20, 110, 220; 200, 250, 300, 300",
    coordinates: "pixels",
  });
  // Labels other than 0/1, negative or fractional object numbers and 5-number entries are unreadable.
  const bad = readPrompt("sam", { points: "1, 2, 3; 1, 2, 1, -1; 1, 2, 1, 0.5; 1; 1, 2, 1, 0, 9", boxes: "1, 2",
                                  coordinates: "pixels" });
  assert.equal(bad.points.length, 0);
  assert.equal(bad.boxes.length, 0);
  assert.deepEqual(writePrompt("sam", bad),
    { points: "1, 2, 3; 1, 2, 1, -1; 1, 2, 1, 0.5; 1; 1, 2, 1, 0, 9", boxes: "1, 2", coordinates: "pixels" });
});

test("SAM in fraction coordinates: shown and rewritten in whole pixels of the image", () => {
  const values = { points: "0.5, 0.5; 0.1, 0.05, 0", boxes: "0.25, 0.25, 0.75, 1", coordinates: "fraction" };
  const p = readPrompt("sam", values, { imgW: 640, imgH: 480 });
  assert.equal(p.fraction, false);
  assert.deepEqual(p.points, [{ x: 320, y: 240, label: 1 }, { x: 64, y: 24, label: 0 }]);
  assert.deepEqual(p.boxes, [{ x0: 160, y0: 120, x1: 480, y1: 480 }]);
  assert.deepEqual(writePrompt("sam", applyClick(p, { x: 1, y: 2 }, { background: true })), {
    points: "320, 240; 64, 24, 0; 1, 2, 0", boxes: "160, 120, 480, 480", coordinates: "pixels",
  });
  // Without the image's size the fractions cannot be placed: flagged, values untouched.
  const q = readPrompt("sam", values);
  assert.equal(q.fraction, true);
  assert.deepEqual(q.points[0], { x: 0.5, y: 0.5, label: 1 });
});

test("a click adds an object point, Shift a background point; a click on a point removes it", () => {
  let p = emptyPrompt();
  p = applyClick(p, { x: 10, y: 20 });
  p = applyClick(p, { x: 30, y: 40 }, { background: true });
  assert.deepEqual(p.points, [{ x: 10, y: 20, label: 1 }, { x: 30, y: 40, label: 0 }]);
  assert.deepEqual(writePrompt("grabcut", p), { object_points: "10, 20", background_points: "30, 40", box: "" });
  assert.deepEqual(writePrompt("sam", p), { points: "10, 20; 30, 40, 0", boxes: "", coordinates: "pixels" });
  const before = p;
  p = applyClick(p, { x: 11, y: 21 }, { hit: 0, background: true });
  assert.deepEqual(p.points, [{ x: 30, y: 40, label: 0 }], "removed, whatever the modifier");
  assert.equal(before.points.length, 2, "the input prompt is not changed");
  assert.equal(describePrompt(p), "1 background");
  assert.equal(describePrompt(emptyPrompt()), "no prompt");
});

test("a drag replaces the box; on the SAM node Ctrl-drag adds another", () => {
  const one = applyBox(emptyPrompt(), { x0: 0, y0: 0, x1: 10, y1: 10 });
  const replaced = applyBox(one, { x0: 5, y0: 5, x1: 50, y1: 40 }, { kind: "sam" });
  assert.deepEqual(replaced.boxes, [{ x0: 5, y0: 5, x1: 50, y1: 40 }]);
  assert.equal(describePrompt(replaced), "box 45×35");
  const added = applyBox(replaced, { x0: 60, y0: 60, x1: 90, y1: 90 }, { kind: "sam", add: true });
  assert.equal(added.boxes.length, 2);
  assert.equal(describePrompt(added), "2 boxes");
  assert.equal(writePrompt("sam", added).boxes, "5, 5, 50, 40; 60, 60, 90, 90");
  const grabcut = applyBox(replaced, { x0: 60, y0: 60, x1: 90, y1: 90 }, { kind: "grabcut", add: true });
  assert.equal(grabcut.boxes.length, 1, "the no-model node takes one box");
  assert.equal(applyBox(one, null), one, "no box, no change");
});

// ---------------------------------------------------------------- the picture to show
function graphOf(nodes, links) {
  const byId = new Map(nodes.map((n) => [n.id, { inputs: [], outputs: [], ...n }]));
  const linkMap = new Map();
  links.forEach(([from, to], i) => {
    const id = 100 + i;
    linkMap.set(id, { id, origin_id: from, target_id: to });
    byId.get(from).outputs.push({ links: [id] });
    byId.get(to).inputs.push({ link: id });
  });
  return { getNodeById: (id) => byId.get(id) ?? null, links: linkMap };
}

const apiURL = (route) => `/api${route}`;

test("the photo is the LoadImage feeding the node, before a preview downstream", () => {
  const g = graphOf([
    { id: 1, comfyClass: "LoadImage", widgets: [{ name: "image", value: "cat.png" }] },
    { id: 2, comfyClass: "ImageScale" },
    { id: 3, comfyClass: "PhysMotionSegment", imgs: [{ src: "/api/view?filename=own.png" }] },
    { id: 4, comfyClass: "PreviewImage", imgs: [{ src: "/api/view?filename=fg.png&type=temp" }] },
  ], [[1, 2], [2, 3], [3, 4]]);
  assert.deepEqual(upstreamIds(g, 3), [2]);
  assert.deepEqual(linkedIds(g, 3), [2, 4]);
  assert.equal(sourceImageURL(g, 3, apiURL), "/api/view?filename=cat.png&type=input&subfolder=");
});

test("without a photo upstream the nearest image either way is used; none gives null", () => {
  const g = graphOf([
    { id: 1, comfyClass: "PhysMotionSAMLoader" },
    { id: 3, comfyClass: "PhysMotionSAMSegment" },
    { id: 4, type: "LoadImage", widgets: [{ name: "image", value: "sub/dir/p.png [output]" }] },
  ], [[1, 3], [3, 4]]);
  assert.equal(sourceImageURL(g, 3, apiURL), "/api/view?filename=p.png&type=output&subfolder=sub%2Fdir");
  const lone = graphOf([{ id: 3, comfyClass: "PhysMotionSegment" }], []);
  assert.equal(sourceImageURL(lone, 3, apiURL), null);
  assert.equal(sourceImageURL(null, 3, apiURL), null);
  const preview = graphOf([
    { id: 3, comfyClass: "PhysMotionSegment" }, { id: 5, comfyClass: "X", imgs: [{ src: "blob:x" }] },
  ], [[5, 3]]);
  assert.equal(sourceImageURL(preview, 3, apiURL), "blob:x");
});

test("a Segment node's own picture (the captioned overlay) is never the picture to pick on", () => {
  // Force-like node 6 -> 7 <- Segment(3, showing its overlay) <- LoadImage(1): the photo is used
  const g = graphOf([
    { id: 1, type: "LoadImage", widgets: [{ name: "image", value: "cat.png" }] },
    { id: 3, comfyClass: "PhysMotionSegment", imgs: [{ src: "/api/view?filename=overlay.png" }] },
    { id: 7, comfyClass: "PhysMotionMPMSimulate" },
    { id: 6, comfyClass: "PhysMotionSAMSegment" },
  ], [[1, 3], [3, 7], [6, 7]]);
  assert.equal(sourceImageURL(g, 6, apiURL), "/api/view?filename=cat.png&type=input&subfolder=");
});
