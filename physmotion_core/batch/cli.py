"""The ``physmotion batch`` subcommand (parser and handler; cli.py only wires them in)."""

from __future__ import annotations

import sys
from pathlib import Path


def add_parser(sub) -> None:
    b = sub.add_parser("batch", help="make many videos from a spec (parameter sweeps, datasets)",
                       description="Expand SPEC (TOML or YAML: images x parameter axes, combined as a grid, zipped "
                                   "or listed) into jobs with content-hash ids and make each job's video in OUT/<id>/, "
                                   "with a row per job in OUT/manifest.jsonl (and manifest.parquet with pyarrow). "
                                   "A rerun skips jobs whose outputs are complete and verified, so an interrupted "
                                   "batch resumes. See docs/batch.md.")
    b.add_argument("spec", type=Path, help="batch spec (.toml, .yaml or .yml)")
    b.add_argument("-o", "--output", type=Path, help="output folder (created; reused to resume); required unless --list")
    b.add_argument("--workers", type=int, help="jobs at a time: local processes (default: one per core, or one per "
                                               "GPU), the CPUs of a --ray auto instance, or prompts in flight with "
                                               "--comfy (default 1)")
    b.add_argument("--threads", type=int, help="threads per job (default: cores / workers locally, 1 with Ray)")
    b.add_argument("--ray", metavar="auto|ADDRESS", help="run the jobs as Ray tasks: 'auto' starts a local Ray "
                                                         "instance, an address (ray://host:10001, host:6379) joins a "
                                                         "cluster (pip install 'physmotion[batch]')")
    b.add_argument("--gpus-per-job", type=float, help="GPUs each Ray task asks for (default: 1 when the cluster has "
                                                      "GPUs and the jobs' device is auto or cuda, else 0)")
    b.add_argument("--comfy", metavar="URL", help="run each job as one prompt on this ComfyUI server, with the "
                                                  "workflow and NODE.INPUT overrides the spec's [comfy] section names")
    b.add_argument("--retries", type=int, default=2, help="retries of a job whose worker died (killed, out of "
                                                          "memory, lost node); bad parameters are never retried "
                                                          "(default 2)")
    b.add_argument("--retry-failed", action="store_true", help="run jobs that failed in an earlier run again")
    b.add_argument("--kernel-cache", help="Warp kernel cache folder every local worker shares (default: Warp's, "
                                          "$WARP_CACHE_PATH or the user cache)")
    b.add_argument("--list", action="store_true", help="print the jobs (id, name, image, swept settings) and exit")
    b.add_argument("--max-jobs", type=int, default=None, metavar="N",
                   help="the most jobs the spec may expand to (default 10000; a grid's size is the product of its "
                        "axes' lengths): a larger spec is refused before any work unless N confirms it; 0 = no limit")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from .runner import run_batch
    from .spec import DEFAULTS, MAX_JOBS, load_spec

    max_jobs = getattr(args, "max_jobs", None)
    if max_jobs is not None and max_jobs < 0:
        from ..errors import InputError

        raise InputError(f"--max-jobs must be 0 (no limit) or a positive number of jobs; got {max_jobs}")
    max_jobs = MAX_JOBS if max_jobs is None else max_jobs
    if args.list:
        spec = load_spec(args.spec, comfy=bool(args.comfy), max_jobs=max_jobs)
        print(f"# {spec.count} jobs (at most; two spellings of one video are listed once)", flush=True)
        for j in spec.iter_jobs():  # one line per job as it is built: the first within a second
            changed = {k: v for k, v in j.settings.items() if DEFAULTS.get(k, object()) != v}
            print(f"{j.id}  {j.name}  {j.image.name}  {changed}{'  INVALID: ' + j.error if j.error else ''}",
                  flush=True)
        return 0
    if args.output is None:
        from ..errors import InputError

        raise InputError("physmotion batch needs -o OUT (the folder for the videos and the manifest)")
    try:
        s = run_batch(args.spec, args.output, ray=args.ray, comfy=args.comfy, workers=args.workers,
                      threads=args.threads, retries=args.retries, retry_failed=args.retry_failed,
                      gpus_per_job=args.gpus_per_job, kernel_cache=args.kernel_cache, progress=not args.quiet,
                      max_jobs=max_jobs)
    except KeyboardInterrupt:
        print(f"physmotion batch: interrupted; finished jobs are kept in {args.output}, nothing half-written. Run the "
              "same command again to finish the rest.", file=sys.stderr)
        return 130
    failed = s.failed + s.failed_earlier
    print(f"{s.total} jobs: {s.done} made now, {s.skipped} already there, {failed} failed"
          f"{f' ({s.retried} retries)' if s.retried else ''} in {s.seconds:.1f}s; manifest: "
          f"{Path(args.output) / 'manifest.jsonl'}", file=sys.stderr)
    for jid, name, kind, msg in s.failures:
        print(f"  failed {jid} {name} ({kind}): {msg}", file=sys.stderr)
    return 1 if failed else 0
