// Unit tests of the force/torque picker's pure geometry (web/picker_math.js): `node --test tests/web/`.
import assert from "node:assert/strict";
import { test } from "node:test";

import {
  canvasToImage, dragToForce, dragToTorque, fitImage, forceToArrow, imageToCanvas, magnitude, nearestSource, showsPhoto,
  photoKey, pixelOf, roundToStep, stalePhoto, torqueToArrow, viewParams,
} from "../../web/picker_math.js";

const close = (a, b, tol, msg) => assert.ok(Math.abs(a - b) <= tol, `${msg ?? ""} ${a} vs ${b} (tol ${tol})`);

test("contain-fit letterboxes a wide image and pillarboxes a tall one", () => {
  // 600x400 into 300x300: scale 0.5, 300x200, 50 px bars above and below.
  assert.deepEqual(fitImage(600, 400, 300, 300), { scale: 0.5, offsetX: 0, offsetY: 50, width: 300, height: 200 });
  // 200x400 into 300x300: scale 0.75, 150x300, 75 px bars left and right.
  assert.deepEqual(fitImage(200, 400, 300, 300), { scale: 0.75, offsetX: 75, offsetY: 0, width: 150, height: 300 });
  assert.equal(fitImage(0, 400, 300, 300).scale, 0);
});

test("canvas and image coordinates are inverse maps; points off the image are flagged and clamped", () => {
  const fit = fitImage(600, 400, 300, 300);
  for (const [u, v] of [[0, 0], [600, 400], [200, 150], [599.5, 0.25]]) {
    const c = imageToCanvas(u, v, fit);
    const back = canvasToImage(c.x, c.y, fit, 600, 400);
    close(back.u, u, 1e-9);
    close(back.v, v, 1e-9);
    assert.equal(back.inside, true);
  }
  // The image's top-left pixel sits below the 50 px letterbox bar.
  assert.deepEqual(imageToCanvas(0, 0, fit), { x: 0, y: 50 });
  const above = canvasToImage(100, 10, fit, 600, 400); // in the bar above the image
  assert.equal(above.inside, false);
  assert.equal(above.v, 0);
  assert.equal(above.u, 200);
});

test("a drag one image-height long to the right is a push of the full scale along +x at the start pixel", () => {
  const f = dragToForce({ u: 200.4, v: 150.6 }, { u: 600.4, v: 150.6 }, { imgW: 600, imgH: 400, fullScale: 50 });
  assert.deepEqual(f, { u: 200, v: 151, fx: 50, fy: 0 });
});

test("dragging up pushes along +y (image down is world -y); strength is proportional to length", () => {
  const f = dragToForce({ u: 100, v: 300 }, { u: 100, v: 200 }, { imgW: 600, imgH: 400, fullScale: 40 });
  assert.equal(f.fx, 0);
  close(f.fy, 10, 1e-12); // a quarter of the height: a quarter of 40 N
  const g = dragToForce({ u: 100, v: 300 }, { u: 160, v: 380 }, { imgW: 600, imgH: 400, fullScale: 40 });
  close(magnitude(g.fx, g.fy), 40 * 100 / 400, 0.1); // |(60, 80)| = 100 px
  close(Math.atan2(g.fy, g.fx), Math.atan2(-80, 60), 0.01);
});

test("the arrow drawn from the widget values is the drag that set them (to the widget's rounding)", () => {
  const start = { u: 321, v: 77 };
  const end = { u: 250.3, v: 190.8 };
  const opts = { imgW: 640, imgH: 480, fullScale: 25, step: 0.1 };
  const f = dragToForce(start, end, opts);
  const arrow = forceToArrow({ ...f }, opts);
  assert.deepEqual(arrow.start, { u: 321, v: 77 });
  // Rounding fx, fy to 0.1 N moves the tip by at most 0.05 N * 480/25 px per axis.
  close(arrow.end.u, end.u, 0.05 * 480 / 25 + 1e-9, "u");
  close(arrow.end.v, end.v, 0.05 * 480 / 25 + 1e-9, "v");
});

test("a torque drag rolls the front of the object along the arrow (axis = z x drag)", () => {
  const opts = { imgW: 600, imgH: 400, fullScale: 2, step: 0.01 };
  for (const [du, dv] of [[200, 0], [0, -100], [-120, 60], [30, 170]]) {
    const t = dragToTorque({ u: 300, v: 200 }, { u: 300 + du, v: 200 + dv }, opts);
    assert.equal(t.tz, 0);
    // Angular velocity along the torque: the front point (0, 0, 1) moves as w x z = (ty, -tx, 0).
    const vel = [t.ty, -t.tx];
    const drag = [du, -dv]; // world x right, y up
    const cos = (vel[0] * drag[0] + vel[1] * drag[1]) / (Math.hypot(...vel) * Math.hypot(...drag));
    close(cos, 1, 1e-3, `direction for drag ${du},${dv}`);
    close(magnitude(t.tx, t.ty), 2 * Math.hypot(du, dv) / 400, 0.01, "magnitude");
  }
  // Dragging right spins it like a turntable, about +y.
  const spin = dragToTorque({ u: 300, v: 200 }, { u: 500, v: 200 }, opts);
  assert.deepEqual([spin.tx, spin.ty, spin.tz], [0, 1, 0]);
});

test("a twist drag to the right turns the object clockwise as the camera sees it", () => {
  const t = dragToTorque({ u: 300, v: 200 }, { u: 400, v: 180 }, { imgW: 600, imgH: 400, fullScale: 2,
                                                                    step: 0.01, twist: true });
  assert.equal(t.tx, 0);
  assert.equal(t.ty, 0);
  close(t.tz, -0.5, 1e-12);
  // w = (0, 0, tz): the point right of the centre, r = (1, 0, 0), moves as w x r = (0, tz, 0): down.
  assert.ok(t.tz < 0);
});

test("the torque arrow drawn from the widgets is the drag that set them", () => {
  const opts = { imgW: 600, imgH: 400, fullScale: 2, step: 0.001 };
  const t = dragToTorque({ u: 100, v: 100 }, { u: 180, v: 40 }, opts);
  const arrow = torqueToArrow(t, opts);
  close(arrow.end.u, 180, 0.0005 * 200 + 1e-9);
  close(arrow.end.v, 40, 0.0005 * 200 + 1e-9);
  assert.equal(arrow.twist, 0);
  const tw = dragToTorque({ u: 100, v: 100 }, { u: 60, v: 100 }, { ...opts, twist: true });
  assert.ok(torqueToArrow(tw, opts).twist > 0); // dragged left: counter-clockwise
});

test("rounding follows the widget step and never gives -0; pixels are clamped inside the image", () => {
  assert.equal(roundToStep(12.345, 0.1), 12.3);
  assert.equal(roundToStep(12.355, 0.01), 12.36);
  assert.ok(Object.is(roundToStep(-0.04, 0.1), 0));
  assert.deepEqual(pixelOf({ u: 600, v: -3 }, 600, 400), { u: 599, v: 0 });
});

test("LoadImage values map to /view parameters (sub-folders and annotated folder types)", () => {
  assert.deepEqual(viewParams("physmotion_coffee.png"), { filename: "physmotion_coffee.png", subfolder: "",
                                                          type: "input" });
  assert.deepEqual(viewParams("shots/a/b.png"), { filename: "b.png", subfolder: "shots/a", type: "input" });
  assert.deepEqual(viewParams("clip_00001_.png [output]"), { filename: "clip_00001_.png", subfolder: "",
                                                             type: "output" });
});

test("the picker finds the nearest image source through links in either direction", () => {
  // Force(6) -> Simulate(7) <- Lift(3) <- LoadImage(1); a second LoadImage(20) hangs further away.
  const edges = [[6, 7], [3, 7], [1, 3], [5, 6], [7, 8], [8, 30], [30, 20]];
  const nb = (id) => edges.flatMap(([a, b]) => (a === id ? [b] : b === id ? [a] : []));
  const images = new Set([1, 20]);
  assert.equal(nearestSource(6, nb, (id) => images.has(id)), 1);
  assert.equal(nearestSource(30, nb, (id) => images.has(id)), 20);
  assert.equal(nearestSource(5, nb, (id) => id === 99), null);
});

test("the Segment nodes' pictures are not photos to pick on; LoadImage and other previews are", () => {
  assert.equal(showsPhoto({ comfyClass: "LoadImage" }), true);
  assert.equal(showsPhoto({ type: "LoadImage" }), true);
  assert.equal(showsPhoto({ comfyClass: "PreviewImage", imgs: [{ src: "x" }] }), true);
  assert.equal(showsPhoto({ comfyClass: "PreviewImage" }), false);
  // the overlay: photo beside the fill, under a caption bar
  assert.equal(showsPhoto({ comfyClass: "PhysMotionSegment", imgs: [{ src: "x" }] }), false);
  assert.equal(showsPhoto({ type: "PhysMotionSAMSegment", imgs: [{ src: "x" }] }), false);
  assert.equal(showsPhoto(null), false);
});

test("photoKey names an input photo as Load Image does, and nothing else; stalePhoto compares", () => {
  assert.equal(photoKey("/api/view?filename=cat.png&type=input&subfolder="), "cat.png");
  assert.equal(photoKey("/api/view?filename=dog.png&type=input&subfolder=my%20photos"), "my photos/dog.png");
  assert.equal(photoKey("/api/view?filename=ComfyUI_temp_0001.png&type=temp&subfolder=&rand=0.3"), null);
  assert.equal(photoKey("/api/view?filename=x.png&type=output&subfolder="), null);
  assert.equal(photoKey(null), null);
  assert.equal(photoKey("blob:abc"), null);
  assert.equal(stalePhoto("cat.png", "dog.png"), "cat.png");
  assert.equal(stalePhoto("cat.png", "cat.png"), null);
  assert.equal(stalePhoto(undefined, "dog.png"), null);
  assert.equal(stalePhoto("cat.png", null), null);
  // the mask editor saves the same photo as clipspace/...: not another photo
  assert.equal(stalePhoto("cat.png", photoKey("/api/view?filename=clipspace-painted-masked-1.png&type=input&subfolder=clipspace")), null);
  assert.equal(stalePhoto("clipspace/clipspace-painted-masked-1.png", "dog.png"), "clipspace/clipspace-painted-masked-1.png");
});
