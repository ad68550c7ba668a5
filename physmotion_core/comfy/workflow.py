"""ComfyUI workflow formats: convert an API-format prompt to the UI (editor/template) format and back.

The API format (what ``POST /prompt`` takes) is the single source of truth of each template; the
UI format is generated from it with the node schemas, so the two cannot drift apart.

``schemas`` maps a node class name to ``{"input": INPUT_TYPES(), "output": RETURN_TYPES,
"output_name": RETURN_NAMES}`` (the shape of ComfyUI's /object_info entries).
"""

from __future__ import annotations

from collections import defaultdict

PRIMITIVES = ("INT", "FLOAT", "STRING", "BOOLEAN")
#: V3 (comfy_api) nodes publish a dropdown as ["COMBO", {"options": [...]}] instead of a list.
COMBO = "COMBO"


def _inputs(schema: dict) -> list[tuple[str, tuple, bool]]:
    spec = schema["input"]
    out = [(k, v, True) for k, v in spec.get("required", {}).items()]
    out += [(k, v, False) for k, v in spec.get("optional", {}).items()]
    return out


def is_widget(spec) -> bool:
    kind = spec[0]
    if isinstance(kind, (list, tuple)) or kind == COMBO:
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
                default = opts.get("default", spec[0][0] if isinstance(spec[0], (list, tuple))
                                   else (opts.get("options") or [None])[0] if spec[0] == COMBO else None)
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


# ---------------------------------------------------------------------------------------------
# Checking an API prompt against node schemas (what ComfyUI's POST /prompt validation checks)
# ---------------------------------------------------------------------------------------------

#: Input types whose inputs V3 nodes expand into several prompt keys ("<id>.<name>").
_DYNAMIC_TYPES = ("COMFY_AUTOGROW_V3", "COMFY_DYNAMICCOMBO_V3")
_UPLOAD_FLAGS = ("image_upload", "video_upload", "audio_upload", "file_upload", "upload")


def node_schemas(classes: dict) -> dict:
    """Schemas (the shape of ``GET /object_info`` entries) of classic node classes, e.g. a pack's
    ``NODE_CLASS_MAPPINGS``."""
    out = {}
    for name, cls in classes.items():
        out[name] = {"input": cls.INPUT_TYPES(), "output": list(cls.RETURN_TYPES),
                     "output_name": list(getattr(cls, "RETURN_NAMES", cls.RETURN_TYPES)),
                     "output_node": bool(getattr(cls, "OUTPUT_NODE", False))}
    return out


def types_compatible(received_type, input_type) -> bool:
    """Whether an output of ``received_type`` may feed an input of ``input_type``, as ComfyUI decides.

    Both are strings "T1,T2,..." (comfy_execution/validation.py ``validate_node_input``, non-strict:
    the link is valid when the two sets share a type); "*" on either side matches anything (the
    ``__ne__`` override of comfy_api's ``_StringIOType`` and of the usual AnyType)."""
    if isinstance(input_type, (list, tuple)) or input_type == COMBO:  # a dropdown fed by a link
        return isinstance(received_type, (list, tuple)) or received_type in (COMBO, "*")
    if not isinstance(received_type, str) or not isinstance(input_type, str):
        return False
    if received_type == input_type or received_type == "*" or input_type == "*":
        return True
    received = {t.strip() for t in received_type.split(",")}
    wanted = {t.strip() for t in input_type.split(",")}
    return "*" in received or "*" in wanted or bool(received & wanted)


def _check_widget(where: str, value, kind, opts: dict, extra: list | tuple = ()) -> list[str]:
    """Errors of one literal widget value against its input spec (ComfyUI's error type first);
    ``extra``: values a dropdown also accepts (files the user is told to download)."""
    if isinstance(value, dict) and "__value__" in value:  # ComfyUI unwraps list values sent this way
        value = value["__value__"]
    if isinstance(kind, (list, tuple)) or kind == COMBO:
        options = list(kind) if isinstance(kind, (list, tuple)) else list(opts.get("options") or [])
        listed = bool(options)
        options += [v for v in extra if v not in options]
        if opts.get("multiselect"):
            values = value if isinstance(value, list) else [value]
        else:
            values = [value]
        upload = any(opts.get(f) for f in _UPLOAD_FLAGS)
        if upload and not listed:  # an upload widget listing no files here: any file name will do
            if not all(isinstance(v, str) and v for v in values):
                return [f"{where}: value_not_in_list: {value!r} is not a file name"]
            return []
        bad = [v for v in values if v not in options]
        if bad:
            shown = options if len(options) <= 20 else f"(list of length {len(options)})"
            return [f"{where}: value_not_in_list: {bad[0]!r} not in {shown}"]
        return []
    if kind == "INT":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or float(value) != int(value):
            return [f"{where}: invalid_input_type: {value!r} is not an INT"]
        value = int(value)
    elif kind == "FLOAT":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return [f"{where}: invalid_input_type: {value!r} is not a FLOAT"]
        value = float(value)
    elif kind == "STRING":
        if not isinstance(value, str):
            return [f"{where}: invalid_input_type: {value!r} is not a STRING"]
        return []
    elif kind == "BOOLEAN":
        if not isinstance(value, bool):
            return [f"{where}: invalid_input_type: {value!r} is not a BOOLEAN"]
        return []
    else:
        return [f"{where}: a {kind} input needs a link, not the literal {value!r}"]
    if "min" in opts and value < opts["min"]:
        return [f"{where}: value_smaller_than_min: {value} < min {opts['min']}"]
    if "max" in opts and value > opts["max"]:
        return [f"{where}: value_bigger_than_max: {value} > max {opts['max']}"]
    step = opts.get("step")
    if kind == "INT" and isinstance(step, (int, float)) and step > 1:
        # The frontend's INT widget snaps to min % step + k * step.
        offset = int(opts["min"]) % int(step) if "min" in opts else 0
        if (value - offset) % int(step):
            return [f"{where}: value_not_on_step: {value} is not {offset} + a multiple of step {step}"]
    return []


def validate_prompt_against_schemas(api_prompt: dict, schemas: dict,
                                    extra_options: dict | None = None) -> list[str]:
    """Check an API-format prompt against node schemas; return the errors (empty = valid).

    ``schemas`` maps class names to entries shaped like ``GET /object_info``'s (``input`` with
    ``required``/``optional``/``hidden`` specs, ``output`` types, ``output_node``), e.g. a captured
    object_info JSON merged with :func:`node_schemas` of a pack. The checks are those of ComfyUI's
    ``POST /prompt`` (execution.py ``validate_prompt``/``validate_inputs`` in 0.3.64), each message
    starting with ComfyUI's error type where it has one:

    * every node has a ``class_type`` that exists; the prompt has an output node (``prompt_no_outputs``);
    * every required input is given (``required_input_missing``);
    * a link is ``[node_id, slot]`` to an existing node and output slot (``bad_linked_input``) whose
      type fits the input (``return_type_mismatch``; "*" and comma-separated unions as
      :func:`types_compatible`);
    * a literal is of the widget's type (``invalid_input_type``), within ``min``/``max``
      (``value_smaller_than_min``/``value_bigger_than_max``), in the dropdown's options
      (``value_not_in_list``; both the V1 list and the V3 ``COMBO`` + ``options`` forms).

    Stricter than the server: an input name the node does not have, a literal given to a link-only
    input (IMAGE, MODEL, ...), an INT off its ``step`` grid (``min % step + k * step``, where the
    frontend's INT widget snaps) and a cycle are errors too, and a V3 dropdown's value is checked
    (0.3.64's server skips those). A FLOAT is not held to its ``step``: the frontend keeps a loaded
    value as it is and only rounds what the user edits.

    Model-file dropdowns list the files of the machine that produced the schemas (often none):
    ``extra_options`` maps ``"ClassName.input"`` to further values to accept there, e.g. the files a
    template tells the user to download. An upload dropdown (``image_upload`` etc.) that lists no
    files takes any file name.
    """
    errors: list[str] = []
    if not isinstance(api_prompt, dict) or not api_prompt:
        return ["invalid_prompt: the prompt must be a non-empty {node_id: {class_type, inputs}} object"]
    has_output = False
    for nid, node in api_prompt.items():
        if not isinstance(node, dict) or "class_type" not in node:
            errors.append(f"node {nid}: invalid_prompt: no class_type")
            continue
        cls = node["class_type"]
        schema = schemas.get(cls)
        if schema is None:
            errors.append(f"node {nid}: invalid_prompt: node {cls} does not exist")
            continue
        has_output = has_output or bool(schema.get("output_node"))
        spec_in = schema.get("input") or {}
        required = spec_in.get("required") or {}
        optional = spec_in.get("optional") or {}
        known = {**optional, **required}
        dynamic = [k for k, v in known.items() if v and v[0] in _DYNAMIC_TYPES]
        inputs = node.get("inputs") or {}
        for name in required:
            if name not in inputs and name not in dynamic:
                errors.append(f"node {nid} {cls}.{name}: required_input_missing")
        for name, value in inputs.items():
            where = f"node {nid} {cls}.{name}"
            if name not in known:
                if any(name.startswith(d + ".") for d in dynamic) or name in (spec_in.get("hidden") or {}):
                    continue
                errors.append(f"{where}: no such input (the node has {sorted(known)})")
                continue
            spec = known[name]
            kind = spec[0]
            opts = spec[1] if len(spec) > 1 and isinstance(spec[1], dict) else {}
            multi = (isinstance(kind, (list, tuple)) or kind == COMBO) and opts.get("multiselect")
            if isinstance(value, list) and (_is_link(value) or not multi):
                if len(value) != 2 or not isinstance(value[1], int) or isinstance(value[1], bool):
                    errors.append(f"{where}: bad_linked_input: {value!r} is not [node_id, slot_index]")
                    continue
                src, slot = str(value[0]), value[1]
                if src not in api_prompt or "class_type" not in (api_prompt[src] or {}):
                    errors.append(f"{where}: bad_linked_input: links to missing node {src}")
                    continue
                src_schema = schemas.get(api_prompt[src]["class_type"])
                if src_schema is None:
                    continue  # reported at that node
                outputs = src_schema.get("output") or []
                if not 0 <= slot < len(outputs):
                    errors.append(f"{where}: bad_linked_input: node {src} ({api_prompt[src]['class_type']}) "
                                  f"has no output {slot} (it has {len(outputs)})")
                    continue
                if not types_compatible(outputs[slot], kind):
                    shown = "COMBO" if isinstance(kind, (list, tuple)) else kind
                    errors.append(f"{where}: return_type_mismatch: received_type({outputs[slot]}) mismatch "
                                  f"input_type({shown}) from node {src} output {slot}")
                continue
            errors.extend(_check_widget(where, value, kind, opts, (extra_options or {}).get(f"{cls}.{name}", ())))
    if not has_output and not any(e.endswith("does not exist") for e in errors):
        errors.append("prompt_no_outputs: the prompt has no output node (e.g. SaveVideo)")
    cycle = _find_cycle(api_prompt)
    if cycle:
        errors.append(f"the links form a cycle: {' -> '.join(cycle)}")
    return errors


def _find_cycle(prompt: dict) -> list[str]:
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(nid: str) -> list[str]:
        state[nid] = 1
        path.append(nid)
        for value in ((prompt.get(nid) or {}).get("inputs") or {}).values():
            if _is_link(value) and value[0] in prompt:
                if state.get(value[0]) == 1:
                    return path[path.index(value[0]):] + [value[0]]
                if value[0] not in state:
                    found = visit(value[0])
                    if found:
                        return found
        state[nid] = 2
        path.pop()
        return []

    for nid in prompt:
        if nid not in state:
            found = visit(nid)
            if found:
                return found
    return []
