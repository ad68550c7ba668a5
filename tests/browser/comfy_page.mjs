// Drives a real ComfyUI page with Playwright (playwright-core + Debian's chromium) for
// tests/test_browser.py. Usage:
//   node tests/browser/comfy_page.mjs <server url> <result.json> [screenshot dir]
// Templates come from the server (GET /workflow_templates, then
// /api/workflow_templates/ComfyUI-PhysMotion/<name>.json), as the Templates dialog fetches them.
// Prints nothing on success; the result JSON holds what the page reported:
//   templates: {name: {missing: [...], prompt: {...API prompt the frontend makes...}}}
//   picker:    {force: {...before/after widgets, expected...}, torque: {...}}
import { createRequire } from "node:module";
import { writeFileSync } from "node:fs";
import path from "node:path";

const require = createRequire(import.meta.url);
const { chromium } = require(process.env.PLAYWRIGHT_CORE || "playwright-core");

const [url, resultPath, shotDir] = process.argv.slice(2);
const PACK = "ComfyUI-PhysMotion";
const executablePath = process.env.CHROMIUM || "/usr/bin/chromium";

const browser = await chromium.launch({
  executablePath,
  headless: true,
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run"],
});
const result = { templates: {}, picker: {}, console_errors: [] };
try {
  const page = await browser.newPage({ viewport: { width: 1600, height: 1000 } });
  page.on("pageerror", (e) => result.console_errors.push(`${e}\n${e.stack ?? ""}`));
  // A first start shows the frontend's "Get Started with a Template" browser (and, on newer
  // frontends, tours) over the canvas: mark the tutorial done in the user's settings before the page
  // loads, and close any dialog still open (its close button, else Escape) until none is left.
  await fetch(new URL("/settings/Comfy.TutorialCompleted", url), { method: "POST", body: "true" }).catch(() => {});
  // COMFY_VUE_NODES=1: the newer frontends' Vue node rendering ("Comfy.VueNodes.Enabled"), where
  // DOM widgets are laid out by the node components instead of the canvas.
  await fetch(new URL("/settings/Comfy.VueNodes.Enabled", url),
              { method: "POST", body: process.env.COMFY_VUE_NODES === "1" ? "true" : "false" }).catch(() => {});
  await page.goto(url, { waitUntil: "domcontentloaded" });
  await page.waitForFunction(() => window.app?.graph && window.LiteGraph?.registered_node_types?.PhysMotionForce,
                             null, { timeout: 120000 });
  async function dismissDialogs(quietMs = 1500, limitMs = 20000) {
    const t0 = Date.now();
    let quietSince = Date.now();
    while (Date.now() - t0 < limitMs) {
      const open = await page.evaluate(() => {
        const shown = [...document.querySelectorAll(".p-dialog-mask, .p-dialog, [role=dialog]")]
          .filter((d) => d.getBoundingClientRect().width > 0 && getComputedStyle(d).visibility !== "hidden");
        if (!shown.length) return 0;
        const close = document.querySelector(".p-dialog-header-close, .p-dialog-close-button, [aria-label=Close]");
        if (close) close.click();
        return shown.length;
      });
      if (open) {
        await page.keyboard.press("Escape");
        quietSince = Date.now();
      } else if (Date.now() - quietSince >= quietMs) {
        return;
      }
      await page.waitForTimeout(200);
    }
    throw new Error("a dialog stayed open over the canvas for " + limitMs / 1000 + " s");
  }
  await dismissDialogs();

  // Every template as the Templates dialog loads it: listed by the server, fetched from it, opened
  // as a named workflow. The frontend's own graphToPrompt must give the API twin back.
  const listing = await page.evaluate(async () => (await (await fetch("/workflow_templates")).json()));
  result.listed = listing[PACK] ?? [];
  result.fetched = {};
  async function fetchTemplate(name) {
    return await page.evaluate(async ({ pack, name }) => {
      const res = await fetch(`/api/workflow_templates/${pack}/${name}.json`);
      if (!res.ok) throw new Error(`GET /api/workflow_templates/${pack}/${name}.json: ${res.status}`);
      return await res.text();
    }, { pack: PACK, name });
  }
  for (const name of [...result.listed].sort()) {
    const wfText = await fetchTemplate(name);
    result.fetched[name] = wfText;
    const r = await page.evaluate(async ({ name, wfText }) => {
      const wf = JSON.parse(wfText);
      const registered = window.LiteGraph.registered_node_types;
      const missing = wf.nodes.filter((n) => !(n.type in registered)).map((n) => n.type);
      await window.app.loadGraphData(wf, true, true, name, { showMissingNodesDialog: false,
                                                             showMissingModelsDialog: false });
      const loaded = window.app.graph._nodes.map((n) => n.type);
      const p = await window.app.graphToPrompt();
      return { missing, prompt: p.output, loaded };
    }, { name, wfText });
    result.templates[name] = r;
    if (shotDir && name === "push_a_jelly") await page.screenshot({ path: path.join(shotDir, `template_${name}.png`) });
  }

  // The picker: drag on the photo inside a node, read the widgets, save and reload the workflow.
  async function drivePicker(template, nodeType, kind, from, to, modifiers = [], prop = "physmotionPicker",
                             clicks = []) {
    const wf = JSON.parse(await fetchTemplate(template));
    await page.evaluate(async ({ wf, nodeType, template }) => {
      await window.app.loadGraphData(wf, true, false, `${template}_picker`, { showMissingNodesDialog: false,
                                                                              showMissingModelsDialog: false });
      const node = window.app.graph._nodes.find((n) => n.type === nodeType);
      const ds = window.app.canvas.ds;
      ds.scale = 1;
      ds.offset[0] = -node.pos[0] + 420;
      ds.offset[1] = -node.pos[1] + 60;
      window.app.canvas.setDirty(true, true);
      window.__pmNode = node;
    }, { wf, nodeType, template });
    await dismissDialogs(500);
    const sel = `canvas[data-physmotion-picker="${kind}"]`;
    await page.waitForFunction(({ sel, prop }) => {
      const n = window.__pmNode;
      const c = document.querySelector(sel);
      return n?.[prop]?.image?.naturalWidth > 0 && c && c.getBoundingClientRect().width > 50;
    }, { sel, prop }, { timeout: 60000 });
    // Wait until the DOM widget sits still where the node is drawn (the canvas positions it on a
    // redraw, which lags on a busy machine) and is what the mouse will hit.
    let last = null;
    for (let i = 0; i < 40; i++) {
      await page.waitForTimeout(250);
      const probe = await page.evaluate(({ sel, from, prop }) => {
        const c = document.querySelector(sel);
        const r = c.getBoundingClientRect();
        const fit = window.__pmNode[prop].fit();
        const x = r.x + (fit.offsetX + from[0] * fit.scale) * (r.width / c.clientWidth);
        const y = r.y + (fit.offsetY + from[1] * fit.scale) * (r.height / c.clientHeight);
        return { key: [r.x, r.y, r.width, r.height].map(Math.round).join(","), hit: document.elementFromPoint(x, y) === c };
      }, { sel, from, prop });
      if (probe.hit && last === probe.key) break;
      last = probe.key;
    }
    const geo = await page.evaluate(({ sel, prop }) => {
      const n = window.__pmNode;
      const p = n[prop];
      const c = document.querySelector(sel);
      const r = c.getBoundingClientRect();
      const widgets = Object.fromEntries(n.widgets.filter((w) => w.serialize !== false)
        .map((w) => [w.name, w.value]));
      return { fit: p.fit(), rect: { x: r.x, y: r.y, w: r.width, h: r.height }, cw: c.clientWidth,
               ch: c.clientHeight, imgW: p.image.naturalWidth, imgH: p.image.naturalHeight, scale: p.scale,
               widgets };
    }, { sel, prop });
    const sx = geo.rect.w / geo.cw;
    const sy = geo.rect.h / geo.ch;
    const screen = (u, v) => ({ x: geo.rect.x + (geo.fit.offsetX + u * geo.fit.scale) * sx,
                                y: geo.rect.y + (geo.fit.offsetY + v * geo.fit.scale) * sy });
    // Clicks first (the segmentation picker: object points, Shift-clicks for background points).
    for (const [u, v, mods] of clicks) {
      const p = screen(u, v);
      for (const m of mods) await page.keyboard.down(m);
      await page.mouse.click(p.x, p.y);
      for (const m of mods) await page.keyboard.up(m);
    }
    const a = screen(...from);
    const b = screen(...to);
    for (const m of modifiers) await page.keyboard.down(m);
    await page.mouse.move(a.x, a.y);
    await page.mouse.down();
    for (let i = 1; i <= 8; i++) await page.mouse.move(a.x + (b.x - a.x) * i / 8, a.y + (b.y - a.y) * i / 8);
    await page.mouse.up();
    for (const m of modifiers) await page.keyboard.up(m);
    if (shotDir) await page.screenshot({ path: path.join(shotDir, `picker_${kind}${modifiers.length ? "_mod" : ""}.png`) });
    const after = await page.evaluate(async (prop) => {
      const n = window.__pmNode;
      const values = (node) => Object.fromEntries(node.widgets.filter((w) => w.serialize !== false)
        .map((w) => [w.name, w.value]));
      const widgets = values(n);
      // Save the workflow and load it back: the picked values must survive.
      const saved = JSON.parse(JSON.stringify(window.app.graph.serialize()));
      await window.app.loadGraphData(saved, true, false, "reloaded", { showMissingNodesDialog: false });
      const reloaded = window.app.graph._nodes.find((x) => String(x.id) === String(n.id));
      const prompt = (await window.app.graphToPrompt()).output;
      // The picker is wired by events, not a timer: loading a workflow removes the old node, which
      // must release its picker, and the new node gets one of its own.
      const wiring = { old_removed: n[prop].removed === true,
                       new_live: !!reloaded[prop] && reloaded[prop].removed === false,
                       timer: "timer" in n[prop] || "timer" in (reloaded[prop] ?? {}) };
      return { widgets, saved_widgets_values: saved.nodes.find((x) => String(x.id) === String(n.id))?.widgets_values,
               reloaded: values(reloaded), prompt_inputs: prompt[String(n.id)].inputs, wiring };
    }, prop);
    return { before: geo.widgets, geometry: geo, from, to, modifiers, ...after };
  }

  result.picker.force = await drivePicker("push_a_jelly", "PhysMotionForce", "force", [300, 200], [400, 120]);
  result.picker.torque = await drivePicker("torque_spin", "PhysMotionTorque", "torque", [300, 200], [420, 200]);
  result.picker.twist = await drivePicker("torque_spin", "PhysMotionTorque", "torque", [300, 200], [240, 200],
                                          ["Shift"]);
  // The segmentation picker: a click on the cup, a Shift-click on the table, a box dragged round both.
  result.picker.segment = await drivePicker("push_a_jelly", "PhysMotionSegment", "segment-grabcut", [40, 12],
                                            [520, 392], [], "physmotionSegmentPicker",
                                            [[300, 150, []], [560, 60, ["Shift"]]]);

  // Picks remember their photo: the template's box and push point name its example photo; once the Load
  // Image shows another photo both pickers say so (the canvas redraw refreshes them), and saving keeps the names.
  result.stale = await page.evaluate(async (wf) => {
    await window.app.loadGraphData(wf, true, false, "stale_picks", { showMissingNodesDialog: false,
                                                                     showMissingModelsDialog: false });
    const nodes = window.app.graph._nodes;
    const seg = nodes.find((n) => n.type === "PhysMotionSegment");
    const force = nodes.find((n) => n.type === "PhysMotionForce");
    const load = nodes.find((n) => n.type === "LoadImage");
    const until = async (ok) => {
      for (let i = 0; i < 150; i++) {
        if (ok()) return true;
        window.app.canvas.setDirty(true, true);
        await new Promise((r) => setTimeout(r, 100));
      }
      return false;
    };
    const shows = (p, name) => p?.image?.naturalWidth > 0 && String(p.imageURL).includes(name);
    await until(() => shows(seg.physmotionSegmentPicker, "physmotion_coffee") &&
                      shows(force.physmotionPicker, "physmotion_coffee"));
    const props = (n) => n.properties?.physmotion_prompt_photo ?? null;
    const before = { seg: seg.physmotionSegmentPicker.staleOn(), force: force.physmotionPicker.stalePhoto(),
                     props: [props(seg), props(force)] };
    const w = load.widgets.find((x) => x.name === "image");
    w.value = "physmotion_block.png";
    w.callback?.(w.value);
    const loaded = await until(() => shows(seg.physmotionSegmentPicker, "physmotion_block") &&
                                     shows(force.physmotionPicker, "physmotion_block"));
    const after = { loaded, seg: seg.physmotionSegmentPicker.staleOn(), force: force.physmotionPicker.stalePhoto() };
    const saved = JSON.parse(JSON.stringify(window.app.graph.serialize()));
    const savedProps = saved.nodes.filter((n) => n.properties?.physmotion_prompt_photo)
      .map((n) => [n.type, n.properties.physmotion_prompt_photo]);
    const ds = window.app.canvas.ds;
    ds.scale = 1;
    ds.offset[0] = -seg.pos[0] + 420;
    ds.offset[1] = -seg.pos[1] + 60;
    window.app.canvas.setDirty(true, true);
    return { before, after, savedProps };
  }, JSON.parse(await fetchTemplate("push_a_jelly")));
  if (shotDir) {
    await page.waitForTimeout(1500);
    await page.screenshot({ path: path.join(shotDir, "stale_picks.png") });
  }
} finally {
  writeFileSync(resultPath, JSON.stringify(result, null, 1));
  await browser.close();
}
