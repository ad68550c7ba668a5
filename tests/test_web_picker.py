"""The force/torque picker's frontend code (web/): its pure geometry module is unit-tested with
Node's test runner (tests/web/*.test.mjs); every extension file must parse as an ES module.
Skipped where Node.js is not installed."""

import shutil
import subprocess

import pytest

from comfy_harness import ROOT

NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(NODE is None, reason="Node.js is not installed")


def test_picker_geometry_unit_tests_pass():
    tests = sorted(str(p) for p in (ROOT / "tests" / "web").glob("*.test.mjs"))
    assert tests, "no JS unit tests found"
    proc = subprocess.run([NODE, "--test", *tests], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "# fail 0" in proc.stdout and "# pass " in proc.stdout


@pytest.mark.parametrize("path", sorted((ROOT / "web").glob("*.js")), ids=lambda p: p.name)
def test_every_extension_file_parses(path):
    proc = subprocess.run([NODE, "--check", str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr


def test_the_picker_registers_for_the_force_and_torque_nodes_and_writes_their_widgets():
    """The names the extension uses must be the backend's: node ids and widget names."""
    import re

    from comfy_harness import input_spec, load_pack

    src = (ROOT / "web" / "force_picker.js").read_text()
    assert "app.registerExtension" in src
    nodes = load_pack().NODE_CLASS_MAPPINGS
    for node_id, names in {"PhysMotionForce": ("u", "v", "fx", "fy", "region"),
                           "PhysMotionTorque": ("u", "v", "tx", "ty", "tz")}.items():
        assert re.search(rf"\b{node_id}\s*:", src), node_id
        spec = input_spec(nodes[node_id])
        for name in names:
            assert name in spec, (node_id, name)
            assert re.search(rf'setWidget\(node, "{name}"', src), (node_id, name)
    # The region the picker selects is one the node offers.
    assert '"image point"' in src and "image point" in input_spec(nodes["PhysMotionForce"])["region"][0]
