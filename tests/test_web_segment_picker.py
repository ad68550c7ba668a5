"""The segmentation-prompt picker's frontend code (web/segment_picker.js, web/segment_math.js): its JS unit
tests pass under Node's test runner, both files parse as ES modules, and the node ids and widget names the
picker uses are the backend's (read from the module itself, not copied here). Skipped without Node.js."""

import json
import shutil
import subprocess

import pytest

from comfy_harness import ROOT

NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(NODE is None, reason="Node.js is not installed")

JS_TESTS = [ROOT / "tests" / "web" / "segment_math.test.mjs", ROOT / "tests" / "web" / "segment_picker.test.mjs"]


def test_segment_picker_js_unit_tests_pass():
    proc = subprocess.run([NODE, "--test", *map(str, JS_TESTS)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "# fail 0" in proc.stdout and "# pass " in proc.stdout


@pytest.mark.parametrize("name", ["segment_math.js", "segment_picker.js"])
def test_segment_picker_files_parse(name):
    proc = subprocess.run([NODE, "--check", str(ROOT / "web" / name)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def _picker_names() -> dict:
    """What web/segment_math.js says: node classes -> kinds, the widgets each kind reads and writes."""
    script = """
      const m = await import(process.argv[1]);
      const writes = Object.fromEntries(Object.keys(m.PROMPT_WIDGETS)
        .map((k) => [k, Object.keys(m.writePrompt(k, m.emptyPrompt()))]));
      console.log(JSON.stringify({ kinds: m.SEGMENT_KINDS, reads: m.PROMPT_WIDGETS, writes }));
    """
    url = (ROOT / "web" / "segment_math.js").as_uri()
    proc = subprocess.run([NODE, "--input-type=module", "-e", script, url], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_the_picker_registers_for_both_segment_nodes_and_uses_their_widgets():
    from comfy_harness import input_spec, load_pack

    src = (ROOT / "web" / "segment_picker.js").read_text()
    assert "app.registerExtension" in src and "nodeCreated" in src
    assert "setInterval" not in src, "the picker must not poll"
    names = _picker_names()
    assert names["kinds"] == {"PhysMotionSegment": "grabcut", "PhysMotionSAMSegment": "sam"}
    nodes = load_pack().NODE_CLASS_MAPPINGS
    for node_id, kind in names["kinds"].items():
        spec = input_spec(nodes[node_id])
        used = set(names["reads"][kind]) | set(names["writes"][kind])
        for name in used:
            assert name in spec, (node_id, name, sorted(spec))
            if name == "coordinates":
                assert "pixels" in spec[name][0], spec[name]
            else:
                assert spec[name][0] == "STRING", (node_id, name, spec[name])
