"""`physmotion` command line."""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from pathlib import Path
from typing import Optional, Sequence

from .errors import PhysMotionError


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    parts = [p for p in text.replace(" ", "").split(",") if p != ""]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be {n} comma-separated numbers; got '{text}'") from None
    if len(values) != n:
        raise argparse.ArgumentTypeError(f"{what} must be {n} comma-separated numbers; got '{text}'")
    return values


def _build_parser() -> argparse.ArgumentParser:
    from .types.material import material_names

    p = argparse.ArgumentParser(prog="physmotion", description="Physics-grounded image-to-video.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details of every stage")
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="animate the object in an image and write an mp4",
                       description="Segment the object in IMAGE, lift it to 3D Gaussians, simulate it with MPM "
                                   "under the given forces, render and blend it over the inpainted background.")
    g.add_argument("image", type=Path, help="input photo (PNG/JPEG; an alpha channel is used as the object mask)")
    g.add_argument("-o", "--output", type=Path, default=Path("physmotion.mp4"),
                   help="output video: .mp4 (H.264), .mov, .mkv, .webm (VP9), .avi (MPEG-4) or .gif")
    g.add_argument("--mask", type=Path, help="optional object mask image (white = object)")
    g.add_argument("--material", default="jelly", choices=material_names(), help="material preset")
    g.add_argument("--E", type=float, help="override Young's modulus (Pa)")
    g.add_argument("--nu", type=float, help="override Poisson's ratio (0 to <0.5)")
    g.add_argument("--density", type=float, help="override density (kg/m^3)")
    g.add_argument("--force", action="append", default=[], metavar="FX,FY,FZ",
                   help="a push in newtons (world axes: +x right, +y up, +z towards the camera); repeatable")
    g.add_argument("--at", action="append", default=[], metavar="U,V",
                   help="pixel (column,row) of the input image where the matching --force is applied; "
                        "omitted = the whole object")
    g.add_argument("--radius", type=float, default=25.0, help="pixel radius of the --at / --torque-at region (default 25)")
    g.add_argument("--force-time", default=None, metavar="T0,T1",
                   help="time window of every --force in seconds (default 0,0.25)")
    g.add_argument("--torque", action="append", default=[], metavar="TX,TY,TZ",
                   help="a twist in N·m about the region's centre of mass (world axes; +y turns it about the vertical); "
                        "repeatable")
    g.add_argument("--torque-at", action="append", default=[], metavar="U,V",
                   help="pixel where the matching --torque acts (the part under it, through the depth); omitted = the "
                        "whole object")
    g.add_argument("--torque-time", default=None, metavar="T0,T1",
                   help="time window of every --torque in seconds (default 0,0.25)")
    g.add_argument("--velocity", metavar="VX,VY,VZ", help="initial velocity of the whole object in m/s (a throw)")
    g.add_argument("--spin", metavar="WX,WY,WZ",
                   help="initial angular velocity in rad/s about the object's centre of mass (right-hand rule)")
    g.add_argument("--frames", type=int, default=48, help="number of frames (default 48)")
    g.add_argument("--fps", type=float, default=24.0, help="frames per second (default 24)")
    g.add_argument("--quality", default="standard", choices=["draft", "standard", "high"],
                   help="simulation resolution when --grid-res is not given: draft (0.67x), standard (24 cells across "
                        "the object on CPU, 48 on CUDA), high (1.5x) (default standard)")
    g.add_argument("--grid-res", type=int, default=None, help="MPM cells across the object (default: from --quality)")
    g.add_argument("--object-height", type=float, default=None,
                   help="real height in metres of what the photo shows of the object (default: 0.3, assumed); it "
                        "sets how fast everything happens (a 3 m statue moves slower than a 0.3 m toy)")
    g.add_argument("--ground", default="friction", choices=["friction", "slip", "sticky", "none"],
                   help="ground contact under the object (default: Coulomb friction)")
    g.add_argument("--friction", type=float, default=0.5, help="ground friction coefficient μ (default 0.5)")
    g.add_argument("--device", default="auto", help="simulation device: auto, cpu, cuda")
    g.add_argument("--models", default="auto", choices=["auto", "none"],
                   help="auto: use SAM / LGM + ImageDream when their weights are in the models folder "
                        "($PHYSMOTION_MODELS, default ./models); none: never load a model (default auto)")
    g.add_argument("--seed", type=int, default=0, help="seed of the learned stages (default 0)")
    _add_prompt_args(g)
    g.add_argument("--no-hold-edges", dest="hold_edges", action="store_false",
                   help="do not hold the object where the photo's edge cuts it off (by default such parts are held: "
                        "the rest of the body outside the frame holds them)")
    g.add_argument("--preview", action="store_true",
                   help="segment, lift and weigh only: write the mask overlay (--overlay, default OUTPUT.mask.png), "
                        "print the summary (mask, support, mass, what each force will do) and stop before simulating")
    g.add_argument("--texture", default="photo", choices=["photo", "splat"],
                   help="photo: the surface the photo saw keeps the photo's own pixels as it moves (default); "
                        "splat: the Gaussians' colours only")
    g.add_argument("--overlay", type=Path, help="also write the mask overlay PNG here (the outline over the photo "
                                                "beside the filled background)")
    g.add_argument("--max-side", type=int, default=1024,
                   help="scale a larger photo down so its long side is this many pixels (--at points are in the "
                        "original photo's pixels); 0 keeps the full size (default 1024)")
    g.add_argument("--save-ply", type=Path, help="also write the lifted Gaussians as a 3DGS .ply")
    g.add_argument("--stats", type=Path, help="write timings and simulation statistics as JSON")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sg = sub.add_parser("segment", help="show the object mask a run would use, drawn over the photo",
                        description="Segment the object in IMAGE as generate would (alpha channel, --mask, SAM when "
                                    "its weights are present, else GrabCut seeded by your points and box), write the "
                                    "outline over the photo beside the filled background, and check the mask.")
    sg.add_argument("image", type=Path, help="input photo")
    sg.add_argument("-o", "--output", type=Path, default=Path("overlay.png"), help="overlay PNG (default overlay.png)")
    sg.add_argument("--mask", type=Path, help="an object mask image (white = object), checked and drawn")
    _add_prompt_args(sg)
    sg.add_argument("--max-side", type=int, default=None, help="as generate's --max-side (default 1024)")
    sg.add_argument("--models", default="auto", choices=["auto", "none"], help="as generate's --models")
    sg.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_check_parsers(sub)
    from .batch.cli import add_parser as _add_batch_parser

    _add_batch_parser(sub)
    return p


def _add_prompt_args(p) -> None:
    p.add_argument("--object-point", action="append", default=[], metavar="U,V",
                   help="a pixel (column,row) on the object you mean; repeatable. Seeds GrabCut, or prompts SAM when "
                        "its weights are present")
    p.add_argument("--background-point", action="append", default=[], metavar="U,V",
                   help="a pixel that is NOT the object (e.g. a neighbouring object that got included); repeatable")
    p.add_argument("--box", metavar="X0,Y0,X1,Y1", help="a box around the object, in pixels (left, top, right, bottom)")


def _prompts(args) -> dict:
    return {"object_points": [_floats(t, 2, "--object-point") for t in args.object_point],
            "background_points": [_floats(t, 2, "--background-point") for t in args.background_point],
            "box": _floats(args.box, 4, "--box") if args.box else None}


def _segment_cmd(args) -> int:
    """`physmotion segment`: the mask the run would simulate, drawn over the photo, and its check."""
    from .fsutil import check_outputs, protect_inputs
    from .image_io import load_image
    from .pipeline import DEFAULT_MAX_SIDE, _resize, available_models, segment_photo
    from .segment.check import CLI_PROMPT_TIP, check_mask, overlay_caption, retry_hint
    from .segment.overlay import mask_overlay, with_caption, write_overlay

    check_outputs({"-o/--output": args.output}, inputs=[args.image, args.mask])
    rgb, alpha = load_image(args.image)
    if alpha is not None and float(alpha.min()) >= 1.0 - 0.5 / 255.0:
        alpha = None
    pr = _prompts(args)
    H, W = int(rgb.shape[0]), int(rgb.shape[1])
    mask = None
    if args.mask is not None:
        m_rgb, _ = load_image(args.mask)
        mask = (m_rgb.mean(dim=-1) > 0.5).float()
        if tuple(mask.shape) != (H, W):
            raise PhysMotionError(f"--mask is {mask.shape[1]}x{mask.shape[0]} but the photo is {W}x{H}; give a mask "
                                  "of the photo's size")
    max_side = DEFAULT_MAX_SIDE if args.max_side is None else args.max_side
    s = 1.0
    if max_side and max(H, W) > max_side:
        s = max_side / max(H, W)
        w, h = max(1, round(W * s)), max(1, round(H * s))
        rgb = _resize(rgb, w, h)
        alpha = None if alpha is None else _resize(alpha, w, h)
        mask = None if mask is None else _resize(mask, w, h)
    scale_pts = [[(u * s, v * s) for u, v in pr[k]] for k in ("object_points", "background_points")]
    box = None if pr["box"] is None else tuple(c * s for c in pr["box"])
    sam = available_models()["sam"] if args.models == "auto" else None
    import time

    t0 = time.perf_counter()
    from .progress import TextBar, end_line

    seg, how = segment_photo(rgb, alpha=alpha, mask=mask, box=box, object_points=scale_pts[0],
                             background_points=scale_pts[1], sam_name=sam,
                             progress=None if args.quiet else TextBar("segment"))
    seconds = time.perf_counter() - t0
    end_line()
    report = check_mask(seg.mask, object_points=scale_pts[0], background_points=scale_pts[1], image=seg.image)
    prompted = bool(pr["object_points"]) or box is not None or how in ("alpha", "mask")
    picture = mask_overlay(seg.image, seg.mask, seg.background, object_points=scale_pts[0],
                           background_points=scale_pts[1], box=box)
    with protect_inputs(args.image, args.mask):
        write_overlay(args.output, with_caption(picture, overlay_caption(report, prompted=prompted,
                                                                         tip=CLI_PROMPT_TIP)))
    print(f"wrote {args.output} ({how}, {seconds:.1f}s)")
    for line in report.summary_lines():
        print(line)
    from .pipeline import unused_prompts_line

    unused = unused_prompts_line(how, box=box, object_points=scale_pts[0], background_points=scale_pts[1])
    if unused:
        print(unused)
    else:
        from .segment.check import box_past_photo

        past = box_past_photo(pr["box"], W, H)  # the photo's own pixels
        if past:
            print(past)
    if not report.ok:
        print("generate would " + ("warn about this mask" if prompted else
                                   "refuse this mask: give --object-point U,V, --box X0,Y0,X1,Y1 or --mask FILE"))
        hint = "" if how in ("alpha", "mask") else retry_hint(points=bool(pr["object_points"]), box=box is not None,
                                                              model=how == "sam")
        if hint:
            print(hint)
    return 0


def _generate(args) -> int:
    from .pipeline import generate
    from .progress import TextBar, end_line
    from .types.conditions import Conditions, Force, Ground, InitialVelocity, Region, Torque
    from .types.settings import SimSettings

    from .fsutil import atomic_write_text, check_outputs, protect_inputs
    from .video import video_format

    if len(args.at) > len(args.force):
        raise PhysMotionError("each --at needs a matching --force (they pair up in order)")
    if args.force_time is not None and not args.force:
        raise PhysMotionError("--force-time sets the time window of the --force pushes, but no --force is given; "
                              "add one (e.g. --force 20,0,0) or drop --force-time")
    t0, t1 = _floats(args.force_time or "0,0.25", 2, "--force-time")
    if len(args.torque_at) > len(args.torque):
        raise PhysMotionError("each --torque-at needs a matching --torque (they pair up in order)")
    if args.torque_time is not None and not args.torque:
        raise PhysMotionError("--torque-time sets the time window of the --torque twists, but no --torque is given; "
                              "add one (e.g. --torque 0,0.5,0) or drop --torque-time")
    q0, q1 = _floats(args.torque_time or "0,0.25", 2, "--torque-time")
    # Every output is checked before any work: a writable folder, a name the file system takes, a
    # video format this writes, no output replacing an input or another output, never a device.
    inputs = [args.image, args.mask]
    check_outputs({"-o/--output": args.output, "--stats": args.stats, "--save-ply": args.save_ply,
                   "--overlay": args.overlay}, inputs=inputs)
    video_format(args.output)
    def loads(kind, vectors, pixels, vec_opt, at_opt, window):
        """One load per vector; the i-th pixel option (if given) is where the i-th one acts."""
        out = []
        for i, text in enumerate(vectors):
            region = Region()
            if i < len(pixels):
                u, v = _floats(pixels[i], 2, at_opt)
                region = Region.at_pixel(u, v, args.radius)
            out.append(kind(_floats(text, 3, vec_opt), region, *window))
        return out

    conds = (loads(Force, args.force, args.at, "--force", "--at", (t0, t1))
             + loads(Torque, args.torque, args.torque_at, "--torque", "--torque-at", (q0, q1)))
    if args.velocity or args.spin:
        conds.append(InitialVelocity(_floats(args.velocity, 3, "--velocity") if args.velocity else (0.0, 0.0, 0.0),
                                     _floats(args.spin, 3, "--spin") if args.spin else (0.0, 0.0, 0.0)))
    ground = None if args.ground == "none" else Ground(0.0, args.ground, args.friction)
    settings = SimSettings(frames=args.frames, fps=args.fps, device=args.device, quality=args.quality)
    if args.grid_res is not None:
        settings.grid_res = args.grid_res
    mask = None
    if args.mask is not None:
        from .image_io import load_image

        m_rgb, _ = load_image(args.mask)
        mask = (m_rgb.mean(dim=-1) > 0.5).float()
    params = {k: getattr(args, k) for k in ("E", "nu", "density") if getattr(args, k) is not None}
    progress = None if args.quiet else (lambda name: TextBar(name))

    def report(line: str) -> None:
        if not args.quiet:
            end_line()  # a stage's bar may be mid-line (the forecast comes as the simulation starts)
            print(line, file=sys.stderr, flush=True)

    with protect_inputs(*inputs):
        res = generate(args.image, conditions=Conditions(conds), material=args.material, material_params=params,
                       mask=mask, ground=ground, object_height=args.object_height, settings=settings,
                       output=None if args.preview else args.output, progress=progress, max_side=args.max_side,
                       models=args.models, seed=args.seed, hold_edges=args.hold_edges, report=report,
                       overlay=args.overlay or (args.output.with_name(args.output.stem + ".mask.png")
                                                if args.preview else None),
                       preview=args.preview, texture=args.texture, **_prompts(args))
        if args.preview:
            print(f"preview: stopped before simulating; the mask overlay is {res.overlay_path}", file=sys.stderr)
            if args.stats is not None:
                atomic_write_text(args.stats, json.dumps({"preview": True, "notes": res.lines, "stages": res.stages,
                                                          "mass_kg": res.mass_kg}, indent=2))
            return 0
        if args.save_ply is not None:
            from .ply import write_ply

            write_ply(args.save_ply, res.gaussians)
    summary = {"output": str(res.video_path), "frames": int(res.frames.shape[0]), "stages": res.stages,
               "size": [int(res.frames.shape[2]), int(res.frames.shape[1])],
               "timings_s": {k: round(v, 3) for k, v in res.timings.items()},
               "simulation": {k: v for k, v in res.sim.stats.items()}, "notes": res.notes}
    if args.stats is not None:
        with protect_inputs(*inputs):
            atomic_write_text(args.stats, json.dumps(summary, indent=2))
    if not args.quiet:
        t = res.timings
        print(f"wrote {res.video_path} ({summary['frames']} frames, {summary['size'][0]}x{summary['size'][1]}) in "
              f"{t['total_s']:.1f}s: segment {t['segment_s']:.1f}s, lift {t['lift_s']:.1f}s, "
              f"simulate {t['simulate_s']:.1f}s ({res.sim.stats['particles']} particles, "
              f"{res.sim.stats['substeps']} substeps), render {t['render_s']:.1f}s, encode {t.get('encode_s', 0):.1f}s",
              file=sys.stderr)
    return 0


def _add_check_parsers(sub) -> None:
    v = sub.add_parser("validate", help="compare the simulator with analytic and published answers",
                       description="Run the accuracy suite (free fall, projectile, momentum, torque spin-up, elastic "
                                   "bar period, convergence order, cantilever, friction, bouncing ball, landing on the ground, granular "
                                   "column collapse) and print measured vs expected with each tolerance.")
    v.add_argument("--quick", action="store_true", help="only the cases that take seconds")
    v.add_argument("--case", action="append", help="run only this case (repeatable); see --list")
    v.add_argument("--list", action="store_true", help="list the case names and exit")
    v.add_argument("--json", type=Path, help="also write the results as JSON here")
    v.add_argument("--markdown", type=Path, help="write the results table into this markdown file's "
                                                  "'validate' section (e.g. docs/accuracy.md)")
    s = sub.add_parser("stress", help="run the numerical-stability stress matrix",
                       description="Extreme stiffness, Poisson ratio, density, loads, thin and wall-touching objects, "
                                   "long runs and oversized steps: every case must complete with finite, in-domain, "
                                   "energy-bounded state or be refused before it starts.")
    s.add_argument("--quick", action="store_true", help="the fast subset CI runs")
    s.add_argument("--json", type=Path, help="also write the outcomes as JSON here")
    s.add_argument("--markdown", type=Path, help="write the table into this markdown file's 'stress' section "
                                                  "(e.g. docs/stability.md)")
    c = sub.add_parser("comfy-run", help="run a workflow on a ComfyUI server and download its outputs",
                       description="Upload the image, apply --set edits, queue the workflow on a running ComfyUI, "
                                   "show its progress and download every output file.")
    c.add_argument("workflow", type=Path, help="workflow JSON (API format, e.g. example_workflows/api/push_a_jelly.json; "
                                               "a UI-format file is converted with the server's node schemas)")
    c.add_argument("--server", default="http://127.0.0.1:8188", help="ComfyUI address")
    c.add_argument("--image", type=Path, help="upload this image and feed it to the workflow's LoadImage node")
    c.add_argument("--set", action="append", default=[], metavar="NODE.INPUT=VALUE",
                   help="change a widget value (node id, title or unique class name); repeatable")
    c.add_argument("-o", "--output", type=Path, default=Path("out"), help="folder for the downloaded outputs")
    c.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for the run")
    c.add_argument("--previews", action="store_true", help="also download the nodes' preview clips/images "
                                                           "(the server's temp folder)")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress lines")


def _progress_line(i: int, n: int, name: str) -> None:
    print(f"[{i + 1}/{n}] {name}", file=sys.stderr, flush=True)


def _validate(args) -> int:
    from .report import machine_description, update_section
    from .validate.cases import all_cases, run_cases
    from .validate.report import cases_markdown

    from .fsutil import check_outputs

    check_outputs({"--json": args.json, "--markdown": args.markdown})  # before minutes of cases
    names = [n for n, _ in all_cases(quick=False)]
    if args.list:
        print("\n".join(names))
        return 0
    unknown = sorted(set(args.case or []) - set(names))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown case(s) {unknown}; choose from {names}")
    results = run_cases(args.case, quick=args.quick, progress=_progress_line)
    for r in results:
        print(f"{'PASS' if r.passed else 'FAIL'}  {r.name}: {r.quantity}: measured {r.measured:.6g}, expected "
              f"{r.expected:.6g}, error {r.error:+.3g} (tolerance {r.tolerance:.3g}) [{r.seconds:.1f}s]")
    if args.json:
        from .fsutil import atomic_write_text

        atomic_write_text(args.json, json.dumps([r.as_dict() for r in results], indent=2, default=float))
    if args.markdown:
        table = cases_markdown(results, machine_description())
        update_section(args.markdown, "validate", "## The accuracy suite\n\n" + table
                       + "\n\nRun with `physmotion validate --markdown docs/accuracy.md`.")
    return 0 if all(r.passed for r in results) else 1


def _stress(args) -> int:
    from dataclasses import asdict

    from .report import machine_description, update_section
    from .validate.stress import markdown, run_matrix, summary

    from .fsutil import check_outputs

    check_outputs({"--json": args.json, "--markdown": args.markdown})  # before minutes of cases
    results = run_matrix(quick=args.quick, progress=_progress_line)
    for r in results:
        print(f"{r.status:9s} {r.group}: {r.name} [{r.seconds:.1f}s] {r.reason}")
    s = summary(results)
    print(f"{len(results)} cases: {s['completed']} completed, {s['refused']} refused, {s['failed']} failed")
    if args.json:
        from .fsutil import atomic_write_text

        atomic_write_text(args.json, json.dumps([asdict(r) for r in results], indent=2, default=float))
    if args.markdown:
        update_section(args.markdown, "stress", markdown(results, machine_description()))
    return 0 if s["failed"] == 0 else 1


def _comfy_run(args) -> int:
    from .comfy.client import run_workflow

    def on_event(kind: str, data: dict) -> None:
        if args.quiet:
            return
        if kind == "progress":
            print(f"  node {data.get('node')}: {data.get('value')}/{data.get('max')}", file=sys.stderr, flush=True)
        elif kind == "executing" and data.get("node") is not None:
            print(f"running node {data['node']}", file=sys.stderr, flush=True)

    from .fsutil import check_outputs

    check_outputs({"-o/--output": args.output}, inputs=[args.workflow, args.image], folders=["-o/--output"])
    saved = run_workflow(args.workflow, args.server, args.output, image=args.image, sets=args.set,
                         on_event=on_event, timeout=args.timeout, previews=args.previews)
    for path in saved:
        print(path)
    return 0


#: Options whose value is a comma-separated vector: a value such as "-20,0,0" starts with "-" and
#: argparse would take it for an option, so it is joined to its option ("--force=-20,0,0") first.
VECTOR_OPTIONS = ("--force", "--at", "--force-time", "--object-point", "--background-point", "--box", "--torque",
                  "--torque-at", "--torque-time", "--velocity", "--spin", "--point")
_NUMBERS = re.compile(r"^-[0-9.]?[0-9.eE+\-]*(,\s*[-+]?[0-9.eE+\-]*)*$")


def _join_vector_values(argv: Sequence[str]) -> list[str]:
    """``--force -20,0,0`` -> ``--force=-20,0,0`` (any option in VECTOR_OPTIONS, or an unambiguous
    prefix of one, followed by a value that starts with '-' and is made of numbers and commas)."""
    out, i, argv = [], 0, list(argv)
    while i < len(argv):
        tok = argv[i]
        is_vec = tok.startswith("--") and "=" not in tok and len(tok) > 2 and (
            tok in VECTOR_OPTIONS or sum(o.startswith(tok) for o in VECTOR_OPTIONS) == 1)
        if is_vec and i + 1 < len(argv) and _NUMBERS.match(argv[i + 1]):
            out.append(f"{tok}={argv[i + 1]}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like Ctrl-C so every atomic write removes its temporary
    file on the way out."""


def _on_sigterm(signum, frame):  # noqa: ARG001
    raise Terminated()


def main(argv: Optional[Sequence[str]] = None) -> int:
    import signal

    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except (ValueError, OSError):  # not the main thread (an embedding application): leave it be
        previous = None
    from .warp_build import hide_no_driver_warning

    hide_no_driver_warning()  # our own stderr: Warp's "no NVIDIA driver" line on a CPU machine goes to the log
    try:
        return _main(argv)
    except BrokenPipeError:
        # The reader went away (`physmotion batch --list | head`): nothing more to say, and nothing
        # is wrong with the disk. Point stdout at /dev/null so the interpreter's final flush is quiet.
        import os

        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 0
    except KeyboardInterrupt:
        # Ctrl-C at any point, start-up included. Outputs are written atomically: nothing
        # half-written is left behind.
        _end_bar_line()
        print("physmotion: interrupted; no output was written for the unfinished step", file=sys.stderr)
        return 130
    except Terminated:
        _end_bar_line()
        print("physmotion: terminated (SIGTERM); no output was written for the unfinished step", file=sys.stderr)
        return 143
    finally:
        hide_no_driver_warning(False)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _end_bar_line() -> None:
    from .progress import end_line

    end_line()


def _ending_bar_lines(record: logging.LogRecord) -> bool:
    """A logging filter that lets every record through after ending a progress bar's unfinished line."""
    _end_bar_line()
    return True


def _main(argv: Optional[Sequence[str]] = None) -> int:
    from .fsutil import OutputLocationError
    from .progress import end_line

    parser = _build_parser()
    args = parser.parse_args(_join_vector_values(sys.argv[1:] if argv is None else argv))
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:  # a log record never lands at the end of a progress bar
        handler.addFilter(_ending_bar_lines)
    try:
        if args.command == "generate":
            return _generate(args)
        if args.command == "segment":
            return _segment_cmd(args)
        if args.command == "validate":
            return _validate(args)
        if args.command == "stress":
            return _stress(args)
        if args.command == "comfy-run":
            return _comfy_run(args)
        if args.command == "batch":
            from .batch.cli import run as _batch

            return _batch(args)
    except argparse.ArgumentTypeError as exc:
        parser.error(str(exc))
    except OutputLocationError as exc:  # a folder that cannot be created or written: a file-system error
        end_line()
        print(f"physmotion: error: {exc}", file=sys.stderr)
        return 1
    except PhysMotionError as exc:
        end_line()
        print(f"physmotion: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        raise  # handled in main(): not a file-system error
    except OSError as exc:  # disk full, permissions, a path that is a folder, ...
        end_line()
        print(f"physmotion: error: {exc.strerror or exc} ({exc.filename or 'file system'}); check that the output "
              "folder exists, is writable and has free space", file=sys.stderr)
        return 1
    return 1


if __name__ == "__main__":
    sys.exit(main())
