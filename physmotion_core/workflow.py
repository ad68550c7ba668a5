"""ComfyUI workflow formats: convert an API-format prompt to the UI (editor/template) format and back.

The API format (what ``POST /prompt`` takes) is the single source of truth of each template; the
UI format is generated from it with the node schemas, so the two cannot drift apart.

``schemas`` maps a node class name to ``{"input": INPUT_TYPES(), "output": RETURN_TYPES,
"output_name": RETURN_NAMES}`` (the shape of ComfyUI's /object_info entries).
"""

from __future__ import annotations

from collections import defaultdict

PRIMITIVES = ("INT", "FLOAT", "STRING", "BOOLEAN")


def _inputs(schema: dict) -> list[tuple[str, tuple, bool]]:
    spec = schema["input"]
    out = [(k, v, True) for k, v in spec.get("required", {}).items()]
    out += [(k, v, False) for k, v in spec.get("optional", {}).items()]
    return out


def is_widget(spec) -> bool:
    kind = spec[0]
    if isinstance(kind, (list, tuple)):
        return True
    if kind in PRIMITIVES:
        # forceInput makes a primitive a socket instead of a widget.
        return not (len(spec) > 1 and isinstance(spec[1], dict) and spec[1].get("forceInput"))
    return False


def _extra_widget_values(name: str, spec) -> list:
    """Values the frontend stores after a widget's own value."""
    opts = spec[1] if len(spec) > 1 and isinstance(spec[1], dict) else {}
    if spec[0] == "INT" and (name in ("seed", "noise_seed") or opts.get("control_after_generate")):
        return ["fixed"]
    if opts.get("image_upload"):
        return ["image"]
    return []


def _is_link(value) -> bool:
    return isinstance(value, list) and len(value) == 2 and isinstance(value[0], str) and isinstance(value[1], int)


DEFAULT_SIZE = (340, 260)


def api_to_ui(prompt: dict, schemas: dict, titles: dict | None = None, sizes: dict | None = None) -> dict:
    """Build a UI-format workflow (version 0.4) from an API prompt.

    ``titles`` maps node ids to titles; ``sizes`` maps class names to [width, height] (nodes whose
    frontend adds a tall widget, e.g. the force picker). Nodes are laid out in columns by their
    depth in the graph, stacked top to bottom."""
    ids = {nid: int(nid) for nid in prompt}
    # Column of each node = longest path from a source, for a readable left-to-right layout.
    depth: dict[str, int] = {}

    def col(nid):
        if nid not in depth:
            ups = [v[0] for v in prompt[nid]["inputs"].values() if _is_link(v)]
            depth[nid] = 1 + max((col(u) for u in ups), default=-1)
        return depth[nid]

    for nid in prompt:
        col(nid)
    rows: dict[int, int] = defaultdict(lambda: 50)  # next free y in each column
    links, nodes = [], []
    out_links: dict[tuple[str, int], list[int]] = defaultdict(list)
    link_id = 0
    pending = []
    for nid in sorted(prompt, key=lambda n: (depth[n], ids[n])):
        node = prompt[nid]
        schema = schemas[node["class_type"]]
        inputs, widgets = [], []
        for name, spec, required in _inputs(schema):
            value = node["inputs"].get(name)
            if is_widget(spec) and not _is_link(value):
                if value is None:
                    if required:
                        raise ValueError(f"node {nid} ({node['class_type']}) lacks widget input '{name}'")
                    continue
                widgets.append(value)
                widgets.extend(_extra_widget_values(name, spec))
                continue
            entry = {"name": name, "type": spec[0] if not isinstance(spec[0], (list, tuple)) else "COMBO",
                     "link": None}
            if is_widget(spec):  # a widget fed by a link keeps its slot (and default) in widgets_values
                opts = spec[1] if len(spec) > 1 and isinstance(spec[1], dict) else {}
                default = opts.get("default", spec[0][0] if isinstance(spec[0], (list, tuple)) else None)
                widgets.append(default)
                widgets.extend(_extra_widget_values(name, spec))
                entry["widget"] = {"name": name}
            if _is_link(value):
                link_id += 1
                entry["link"] = link_id
                pending.append([link_id, ids[value[0]], value[1], ids[nid], len(inputs), value[0]])
                out_links[(value[0], value[1])].append(link_id)
            elif required:
                raise ValueError(f"node {nid} ({node['class_type']}) lacks linked input '{name}'")
            if _is_link(value) or required:
                inputs.append(entry)
        c = depth[nid]
        size = list((sizes or {}).get(node["class_type"], DEFAULT_SIZE))
        pos = [50 + 400 * c, rows[c]]
        rows[c] += size[1] + 70
        nodes.append({
            "id": ids[nid], "type": node["class_type"], "pos": pos, "size": size, "flags": {},
            "order": 0, "mode": 0, "inputs": inputs, "outputs": [], "properties": {"Node name for S&R": node["class_type"]},
            "widgets_values": widgets, "_nid": nid,
        })
        if titles and nid in titles:
            nodes[-1]["title"] = titles[nid]
    by_id = {n["_nid"]: n for n in nodes}
    for order, n in enumerate(nodes):
        n["order"] = order
        schema = schemas[n["type"]]
        names = schema.get("output_name") or schema["output"]
        n["outputs"] = [{"name": names[i], "type": t, "links": out_links.get((n["_nid"], i), []) or None,
                         "slot_index": i} for i, t in enumerate(schema["output"])]
    for lid, src, slot, dst, dst_slot, src_nid in pending:
        links.append([lid, src, slot, dst, dst_slot, schemas[by_id[src_nid]["type"]]["output"][slot]])
    for n in nodes:
        del n["_nid"]
    return {"last_node_id": max(ids.values()), "last_link_id": link_id, "nodes": nodes, "links": links,
            "groups": [], "config": {}, "extra": {}, "version": 0.4}


def ui_to_api(workflow: dict, schemas: dict) -> dict:
    """Recover the API prompt a UI workflow describes (what the frontend's 'Save (API)' produces)."""
    link_src = {l[0]: (str(l[1]), int(l[2])) for l in workflow["links"]}
    prompt = {}
    for n in workflow["nodes"]:
        schema = schemas[n["type"]]
        values = list(n.get("widgets_values", []))
        linked = {i["name"]: link_src[i["link"]] for i in n.get("inputs", []) if i.get("link") is not None}
        inputs = {}
        for name, spec, _ in _inputs(schema):
            if name in linked:
                inputs[name] = list(linked[name])
                # A widget converted to an input still holds its slot in widgets_values.
                if is_widget(spec) and values:
                    values.pop(0)
                    for _ in _extra_widget_values(name, spec):
                        values.pop(0)
            elif is_widget(spec) and values:
                inputs[name] = values.pop(0)
                for _ in _extra_widget_values(name, spec):
                    values.pop(0)
        prompt[str(n["id"])] = {"class_type": n["type"], "inputs": inputs}
    return prompt
