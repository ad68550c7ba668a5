"""The batch driver: resume, schedule, retry infrastructure faults, record, report progress."""

from __future__ import annotations

import collections
import contextlib
import datetime as _dt
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from ..errors import InputError
from . import job as J
from . import manifest as M
from .spec import BatchSpec, load_spec, physics_version

KILL_ENV = "PHYSMOTION_BATCH_TEST_KILL"  # test hook: job ids whose worker dies on their first attempt


@dataclass
class BatchSummary:
    out: Path
    total: int = 0
    done: int = 0
    failed: int = 0
    skipped: int = 0  # finished (or failed for good) in an earlier run, outputs verified
    failed_earlier: int = 0  # of the skipped: failed in an earlier run (--retry-failed runs them again)
    ran: int = 0  # jobs run in this call
    retried: int = 0
    interrupted: bool = False
    seconds: float = 0.0
    startup_s: float = 0.0  # until the executor was ready (workers up, Warp kernels loaded)
    executor: str = ""
    failures: list = field(default_factory=list)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


class _Bar:
    """One progress bar over the jobs, with ETA: tqdm when installed, else a line of text on stderr."""

    def __init__(self, total: int, initial: int, enabled: bool, stream):
        self.total, self.n, self.stream, self.enabled = total, initial, stream, enabled
        self.start_n, self.t0, self.failed = initial, time.monotonic(), 0
        self._tqdm = None
        if enabled:
            try:
                from tqdm import tqdm

                self._tqdm = tqdm(total=total, initial=initial, unit="job", desc="batch", file=stream,
                                  dynamic_ncols=True, smoothing=0.1)
            except ModuleNotFoundError:
                self._draw()

    def update(self, failed: bool = False) -> None:
        self.n += 1
        self.failed += int(failed)
        if not self.enabled:
            return
        if self._tqdm is not None:
            self._tqdm.set_postfix(failed=self.failed, refresh=False)
            self._tqdm.update(1)
        else:
            self._draw()

    def _draw(self) -> None:
        done_now = self.n - self.start_n
        elapsed = time.monotonic() - self.t0
        eta = "?" if done_now == 0 else f"{elapsed / done_now * (self.total - self.n):.0f}s"
        width = 30
        filled = int(width * self.n / max(self.total, 1))
        self.stream.write(f"\rbatch [{'#' * filled}{'.' * (width - filled)}] {self.n}/{self.total} jobs, "
                          f"{self.failed} failed, {elapsed:.0f}s, ETA {eta}  ")
        self.stream.flush()

    def close(self) -> None:
        if not self.enabled:
            return
        if self._tqdm is not None:
            self._tqdm.close()
        else:
            self.stream.write("\n")
            self.stream.flush()


def _wants(spec: BatchSpec, record: dict) -> str:
    """Why a finished job must run again for the outputs the spec asks for now ('' if it need not)."""
    from . import extras

    files = record.get("files") or {}
    o = spec.outputs
    if o["ply"] == "rest" and "gaussians.ply" not in files:
        return "the spec now asks for the lifted Gaussians (.ply)"
    if o["ply"] == "sequence" and not any(f.startswith("ply/") for f in files):
        return "the spec now asks for a .ply sequence"
    for what, name in (("tracks", "tracks.npz"), ("flow", "flow.npz")):
        if o[what] and name not in files and (spec.comfy is None and extras.available(what)):
            return f"the spec now asks for {what}"
    return ""


@contextlib.contextmanager
def _lock(out: Path):
    """One batch at a time per output folder (two would race on the same jobs)."""
    try:
        import fcntl
    except ModuleNotFoundError:  # Windows: no advisory locks here
        yield
        return
    fh = open(out / ".batch.lock", "w")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise InputError(f"another batch is writing to {out}; wait for it, or pick another -o folder") from None
    try:
        yield
    finally:
        fcntl.flock(fh, fcntl.LOCK_UN)
        fh.close()


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """A SIGTERM (a scheduler stopping the batch) stops it as Ctrl-C does."""
    def handler(signum, frame):
        raise KeyboardInterrupt

    try:
        old = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _make_executor(out: Path, *, ray: Optional[str], comfy: Optional[str], spec: BatchSpec, workers: Optional[int],
                   threads: Optional[int], gpus_per_job: Optional[float], kernel_cache: Optional[str], pending: int):
    from .executors import ComfyExecutor, LocalExecutor, RayExecutor, available_cores

    if comfy:
        return ComfyExecutor(out, comfy, spec.comfy["workflow"], spec.comfy["map"], workers or 1,
                             timeout=spec.comfy.get("timeout", 3600.0))
    cores = available_cores()
    devices = {j.settings.get("device", "auto") for j in spec.jobs if j.error is None}
    if ray:
        cpus = workers or cores
        return RayExecutor(out, ray, cpus=cpus, threads=threads or 1, gpus=gpus_per_job,
                           device="cuda" if any(d.startswith("cuda") for d in devices) else
                           ("auto" if "auto" in devices else "cpu"))
    gpus = 0
    if any(d != "cpu" for d in devices):
        try:
            import torch

            gpus = torch.cuda.device_count() if (torch.cuda.is_available() and os.environ.get("PHYSMOTION_DEVICE")
                                                 != "cpu") else 0
        except Exception:  # noqa: BLE001
            gpus = 0
    n = workers or (gpus if gpus else cores)
    n = max(1, min(n, pending))
    t = threads or max(1, cores // n)
    return LocalExecutor(out, n, t, gpus=gpus, kernel_cache=kernel_cache)


def run_batch(spec_path, out, *, ray: Optional[str] = None, comfy: Optional[str] = None,
              workers: Optional[int] = None, threads: Optional[int] = None, retries: int = 2,
              retry_failed: bool = False, gpus_per_job: Optional[float] = None, kernel_cache: Optional[str] = None,
              progress: bool = True, stream=None, max_jobs: Optional[int] = None) -> BatchSummary:
    """Run every job of the spec at ``spec_path`` that ``out`` does not already hold, verified.

    Raises KeyboardInterrupt after a clean stop (finished jobs stay finished, nothing half-written)."""
    stream = stream or sys.stderr
    if ray and comfy:
        raise InputError("use either --ray or --comfy, not both")
    if not (isinstance(retries, int) and 0 <= retries <= 100):
        raise InputError(f"--retries must be an integer in [0, 100]; got {retries!r}")
    t0 = time.monotonic()
    from .spec import MAX_JOBS

    spec = load_spec(spec_path, comfy=bool(comfy), max_jobs=MAX_JOBS if max_jobs is None else max_jobs)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out} is a file; give a folder for the batch's outputs")
    out.mkdir(parents=True, exist_ok=True)
    if progress:  # said at once: building and checking many jobs against the manifest takes a while
        stream.write(f"batch: {spec.count} jobs from {spec.path}; checking them against {out}\n")
        stream.flush()
    summary = BatchSummary(out=out, total=len(spec.jobs))
    with _lock(out), _sigterm_as_interrupt():
        return _run(spec, out, summary, t0, ray=ray, comfy=comfy, workers=workers, threads=threads, retries=retries,
                    retry_failed=retry_failed, gpus_per_job=gpus_per_job, kernel_cache=kernel_cache,
                    progress=progress, stream=stream)


def _run(spec, out, summary, t0, *, ray, comfy, workers, threads, retries, retry_failed, gpus_per_job,
         kernel_cache, progress, stream) -> BatchSummary:
    log = lambda line: M.append_log(out, f"{_now()} {line}")  # noqa: E731
    records: dict = {}
    pending = []
    log(f"batch {spec.path} ({spec.sha256[:12]}): {len(spec.jobs)} jobs, physics {physics_version()}")
    for job in spec.jobs:
        rec = M.read_record(out, job.id)
        if rec is not None and rec.get("status") == "done":
            ok, why = M.verify(out, rec)
            why = why or _wants(spec, rec)
            if ok and not why:
                records[job.id] = rec
                summary.skipped += 1
                continue
            log(f"{job.id} {job.name} runs again: {why}")
        elif rec is not None and rec.get("status") == "failed" and not retry_failed \
                and (rec.get("error") or {}).get("kind") != "infrastructure":
            records[job.id] = rec
            summary.skipped += 1
            summary.failed_earlier += 1
            continue
        pending.append(job)

    def finish(job, record: dict, attempts: int, executor_name: str) -> None:
        record = {"id": job.id, "name": job.name, "image": str(job.image), "image_sha256": job.image_sha256,
                  "settings": job.settings, "sets": job.sets, "spec": str(spec.path), "spec_sha256": spec.sha256,
                  "attempts": attempts, "executor": executor_name, "finished_at": _now(), **record}
        if record.get("status") == "done" and "video" not in record:
            record["video"] = J.VIDEO
        M.write_record(out, record)
        records[job.id] = record
        if record["status"] == "done":
            summary.done += 1
            log(f"{job.id} {job.name} done in {record.get('job_s', 0):.2f}s (attempt {attempts}, "
                f"{executor_name} {record.get('host', '')}:{record.get('pid', '')})")
        else:
            summary.failed += 1
            err = record.get("error") or {}
            summary.failures.append((job.id, job.name, err.get("kind"), err.get("message")))
            log(f"{job.id} {job.name} FAILED ({err.get('kind')}: {err.get('type')}): {err.get('message')}")

    def write_manifest() -> None:
        M.write_manifest(out, [M.manifest_row(j, records.get(j.id), out) for j in spec.jobs])

    # Values no worker could use fail here, before any process starts.
    runnable = []
    for job in pending:
        err = None
        if job.error is not None:
            err = {"kind": "input", "type": "InputError", "message": job.error}
        elif spec.comfy is None:
            err = J.check_inputs(job.settings)
        if err is not None:
            M.clean_partial(out, job.id)
            finish(job, {"status": "failed", "error": err}, 0, "driver")
        else:
            runnable.append(job)

    bar = _Bar(summary.total, summary.total - len(runnable), progress, stream)
    if not runnable:
        bar.close()
        write_manifest()
        summary.seconds = time.monotonic() - t0
        log(f"nothing to run: {summary.skipped} jobs already finished, {summary.failed} failed")
        return summary

    ex = _make_executor(out, ray=ray, comfy=comfy, spec=spec, workers=workers, threads=threads,
                        gpus_per_job=gpus_per_job, kernel_cache=kernel_cache, pending=len(runnable))
    summary.executor = ex.name
    kill = set(filter(None, os.environ.get(KILL_ENV, "").split(",")))
    by_id = {j.id: j for j in runnable}
    attempts = collections.Counter()
    queue = collections.deque(runnable)
    models_cache: dict = {}

    def task(job) -> dict:
        from .spec import models_identity

        attempts[job.id] += 1
        t = {"id": job.id, "settings": job.settings, "attempt": attempts[job.id], "outputs": spec.outputs,
             "image_path": str(job.image), "sets": job.sets, "physics_version": physics_version(),
             "threads": getattr(ex, "threads", 1)}
        if spec.comfy is None:
            m = job.settings["models"]
            t["models"] = models_cache.get(m) if m in models_cache else models_cache.setdefault(m, models_identity(m))
        if job.id in kill and attempts[job.id] == 1:
            t["_test_kill"] = True
        return t

    last_manifest = 0.0
    try:
        ex.start()
        if spec.comfy is None:
            device = "cuda" if any(j.settings["device"] != "cpu" for j in runnable) else "cpu"
            w = ex.warm(device)
        summary.startup_s = time.monotonic() - t0
        if spec.comfy is None:
            log(f"{ex.name}: {ex.capacity} jobs at a time, {getattr(ex, 'threads', 1)} thread(s) each; Warp kernels "
                f"ready in {w.get('seconds', 0):.2f}s (cache {w.get('kernel_cache')})")
        inflight = 0
        while queue or inflight:
            while queue and inflight < ex.capacity:
                job = queue.popleft()
                M.clean_partial(out, job.id)
                ex.submit(task(job))
                inflight += 1
            for kind, t, value in ex.wait(timeout=0.5):
                inflight -= 1
                job = by_id[t["id"]]
                if kind == "result":
                    summary.ran += 1
                    finish(job, value, attempts[job.id], ex.name)
                    bar.update(failed=value.get("status") != "done")
                elif kind == "requeue":
                    attempts[job.id] -= 1
                    log(f"{job.id} {job.name} requeued: {value}")
                    queue.appendleft(job)
                elif attempts[job.id] <= retries:
                    summary.retried += 1
                    log(f"{job.id} {job.name} retrying (attempt {attempts[job.id]} of {retries + 1} failed: {value})")
                    queue.appendleft(job)
                else:
                    summary.ran += 1
                    finish(job, {"status": "failed", "error": {"kind": "infrastructure", "type": "WorkerLost",
                                                               "message": f"{value} ({attempts[job.id]} attempts)"}},
                           attempts[job.id], ex.name)
                    bar.update(failed=True)
            if time.monotonic() - last_manifest > 2.0:
                write_manifest()
                last_manifest = time.monotonic()
        ex.stop()
    except KeyboardInterrupt:
        summary.interrupted = True
        with contextlib.suppress(KeyboardInterrupt):
            ex.stop(abort=True)
        for job in runnable:
            if job.id not in records or records[job.id].get("status") != "done":
                M.clean_partial(out, job.id)
        bar.close()
        write_manifest()
        left = sum(1 for j in spec.jobs if j.id not in records)
        log(f"interrupted: {summary.done} jobs finished in this run, {left} left; rerun to finish them")
        summary.seconds = time.monotonic() - t0
        raise
    except BaseException:
        with contextlib.suppress(BaseException):
            ex.stop(abort=True)
        raise
    bar.close()
    write_manifest()
    summary.seconds = time.monotonic() - t0
    log(f"finished: {summary.done} done, {summary.failed} failed, {summary.skipped} skipped, "
        f"{summary.retried} retries, {summary.seconds:.1f}s")
    return summary
