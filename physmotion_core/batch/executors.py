"""Where jobs run: a local process pool (the default), a Ray cluster, or a ComfyUI server.

Each executor takes tasks (plain dicts, see ``runner._task``) and hands back outcomes:

* ``("result", task, record)``: the job ran; ``record["status"]`` is "done" or "failed" (a failed job
  is a result, never retried: it would fail the same way again);
* ``("infra", task, message)``: the worker died under it (killed, out of memory, a lost node, an
  unreachable server); the runner retries these up to ``--retries`` times;
* ``("requeue", task, message)``: the job never got its turn (its pool broke because another job's
  worker died); it runs again without counting an attempt.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import signal
import tempfile
import time
from pathlib import Path
from typing import Optional

from ..errors import InputError
from . import job as J


def available_cores() -> int:
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # macOS, Windows
        return max(os.cpu_count() or 1, 1)


class LocalExecutor:
    """A pool of ``workers`` processes (started with 'spawn': torch's and Warp's threads do not survive
    a fork), each running jobs on ``threads`` threads, so workers x threads = the cores. With GPUs,
    worker i gets GPU i mod n (CUDA_VISIBLE_DEVICES). Workers write each output straight into the
    job's folder, atomically."""

    name = "local"

    def __init__(self, out: Path, workers: int, threads: int, gpus: int = 0, kernel_cache: Optional[str] = None):
        self.out, self.workers, self.threads, self.gpus = Path(out), int(workers), int(threads), int(gpus)
        self.kernel_cache = kernel_cache
        self.capacity = self.workers
        self._pool: Optional[cf.ProcessPoolExecutor] = None
        self._inflight: dict = {}
        self._procs: dict = {}
        self._pending: list = []  # outcomes found while submitting, handed back by the next wait()

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        ctx = mp.get_context("spawn")
        slots = None
        if self.gpus:
            slots = ctx.Queue()
            for i in range(self.workers):
                slots.put(i % self.gpus)
        self._procs = {}
        return cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=J.worker_init,
                                      initargs=(self.threads, slots, self.kernel_cache))

    def start(self) -> None:
        self._pool = self._new_pool()
        # Start every worker now, side by side: the pool would otherwise start one only when a job finds
        # no idle worker, and a worker takes seconds to import torch.
        spawn = getattr(self._pool, "_spawn_process", None)
        if spawn is not None:
            for _ in range(self.workers):
                spawn()

    def warm(self, device: str) -> dict:
        return self._pool.submit(J.warm_kernels, device).result()

    def submit(self, task: dict) -> None:
        try:
            fut = self._pool.submit(J.local_task, task, str(self.out / task["id"]))
        except cf.process.BrokenProcessPool:
            # A worker died since the last wait() (another job finished first and freed this slot): the
            # pool fails every job it held. Sort them out now, hand the outcomes to the next wait(), and
            # give this task to a new pool.
            cf.wait(list(self._inflight), timeout=30)
            outcomes, _ = self._harvest([f for f in list(self._inflight) if f.done()])
            self._pending.extend(outcomes)
            self._pending.extend(self._recover())
            fut = self._pool.submit(J.local_task, task, str(self.out / task["id"]))
        self._inflight[fut] = task
        self._procs.update(getattr(self._pool, "_processes", None) or {})

    def wait(self, timeout: float) -> list:
        pending, self._pending = self._pending, []
        if not self._inflight:
            return pending
        done, _ = cf.wait(list(self._inflight), timeout=0 if pending else timeout, return_when=cf.FIRST_COMPLETED)
        self._procs.update(getattr(self._pool, "_processes", None) or {})
        outcomes, broken = self._harvest(done)
        if broken:
            outcomes.extend(self._recover())
        return pending + outcomes

    def _harvest(self, done) -> tuple:
        """Outcomes of finished futures; those the broken pool dropped stay in flight for _recover."""
        outcomes, broken = [], False
        for fut in done:
            task = self._inflight.pop(fut)
            try:
                outcomes.append(("result", task, fut.result()))
            except cf.process.BrokenProcessPool:
                broken = True
                self._inflight[fut] = task  # sorted out below, with the rest of the pool's jobs
            except Exception as exc:  # noqa: BLE001 - e.g. a result that could not be sent back
                outcomes.append(("infra", task, f"{type(exc).__name__}: {exc}"))
        return outcomes, broken

    def _recover(self) -> list:
        """A worker died, so the pool is broken and every job on it was dropped. The job whose
        worker died (found by its running marker's pid and that process's exit code) counts an
        attempt; the others were stopped by the pool (SIGTERM) or never started, and run again."""
        pool, procs = self._pool, dict(self._procs)
        pool.shutdown(wait=True, cancel_futures=True)
        for p in procs.values():
            p.join(timeout=5)
        tasks = list(self._inflight.values())
        self._inflight.clear()
        blamed = []
        culprits = {}
        for task in tasks:
            try:
                pid = int((self.out / task["id"] / ".running").read_text().split()[0])
            except (OSError, ValueError, IndexError):
                continue  # never started
            p = procs.get(pid)
            code = p.exitcode if p is not None else None
            if code is not None and code != -signal.SIGTERM:
                how = f"killed by signal {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"
                culprits[task["id"]] = f"its worker process (pid {pid}) {how}"
        outcomes = []
        for task in tasks:
            if task["id"] in culprits:
                blamed.append(task["id"])
                outcomes.append(("infra", task, culprits[task["id"]]))
            elif culprits:
                outcomes.append(("requeue", task, "its pool was restarted after another job's worker died"))
            else:  # no way to tell which job took the worker down: each counts an attempt
                outcomes.append(("infra", task, "a worker process of the pool died (BrokenProcessPool)"))
        for task in tasks:
            try:
                (self.out / task["id"] / ".running").unlink()
            except OSError:
                pass
        self.start()
        return outcomes

    def stop(self, abort: bool = False) -> None:
        pool, self._pool = self._pool, None
        if pool is None:
            return
        if abort:
            procs = dict(getattr(pool, "_processes", None) or {})
            pool.shutdown(wait=False, cancel_futures=True)
            for p in procs.values():  # SIGTERM: the job unwinds and its atomic writers clean up
                if p.is_alive():
                    p.terminate()
            deadline = time.monotonic() + 10
            for p in procs.values():
                p.join(timeout=max(0.1, deadline - time.monotonic()))
                if p.is_alive():
                    p.kill()
                    p.join(timeout=5)
        else:
            pool.shutdown(wait=True)
        self._inflight.clear()


class RayExecutor:
    """Jobs as Ray tasks. ``address`` "auto" starts a local Ray instance with ``cpus`` CPUs (and no
    dashboard); anything else is a cluster address (``ray://head:10001`` or ``head:6379``). Each task
    asks for ``threads`` CPUs and ``gpus`` GPUs. The image goes to the task as bytes (ray.put once per
    image) and the outputs come back as bytes, so the nodes need no shared file system."""

    name = "ray"

    def __init__(self, out: Path, address: str, cpus: int, threads: int, gpus: Optional[float] = None,
                 device: str = "auto"):
        self.out, self.address, self.cpus, self.threads = Path(out), address, int(cpus), int(threads)
        self.gpus, self.device = gpus, device
        self.capacity = 1
        self._inflight: dict = {}
        self._images: dict = {}
        self._started = False

    def start(self) -> None:
        try:
            import ray
        except ModuleNotFoundError:
            raise InputError("--ray needs Ray: pip install 'ray>=2.9' (or pip install 'physmotion[batch]')") from None
        self.ray = ray
        if not ray.is_initialized():
            kw = dict(include_dashboard=False, log_to_driver=False, logging_level="WARNING")
            try:
                if self.address == "auto":
                    ray.init(num_cpus=self.cpus, **kw)
                else:
                    ray.init(address=self.address, **kw)
            except (ImportError, ValueError, RuntimeError) as exc:
                text = str(exc)
                if isinstance(exc, ImportError) or "ray[client]" in text or "Ray Client" in text:
                    # ray:// is Ray Client, which needs extra packages (grpcio, ...) a plain `pip install ray` lacks
                    raise InputError(f"--ray {self.address} needs Ray Client, which this Ray installation lacks. "
                                     "Install it with: pip install 'ray[client]' (the same Ray version as the "
                                     "cluster), or run on the head node with --ray auto or --ray HOST:6379. (Ray: "
                                     f"{text.splitlines()[0][:200] if text else type(exc).__name__})") from None
                if isinstance(exc, ValueError):
                    raise InputError(f"--ray {self.address}: Ray does not accept this address ({text[:200]}). Use "
                                     "auto, ray://HEAD:10001 (Ray Client) or HEAD:6379.") from None
                raise
            except (ConnectionError, TimeoutError) as exc:
                raise InputError(f"--ray {self.address}: cannot connect to the Ray cluster ({exc}). Check the "
                                 "address (ray://HEAD:10001 for Ray Client, HEAD:6379 on the cluster's network) and "
                                 "that the cluster is up.") from None
            self._started = True
        res = ray.cluster_resources()
        cluster_gpus = float(res.get("GPU", 0.0))
        if self.gpus is None:
            self.gpus = 1.0 if (self.device.startswith("cuda") or (self.device == "auto" and cluster_gpus > 0)) else 0.0
        if self.gpus > 0 and cluster_gpus == 0:
            raise InputError(f"the jobs ask for {self.gpus} GPU each but the Ray cluster has none; use device = "
                             "'cpu' in the spec or --gpus-per-job 0")
        slots = float(res.get("CPU", 1.0)) // max(self.threads, 1)
        if self.gpus > 0:
            slots = min(slots, cluster_gpus // self.gpus)
        self.capacity = max(1, int(slots) * 2)  # a second task per slot waits in Ray's queue
        self._fn = ray.remote(J.remote_task).options(num_cpus=self.threads, num_gpus=self.gpus, max_retries=0)

    def warm(self, device: str) -> dict:
        fn = self.ray.remote(J.warm_kernels).options(num_cpus=self.threads, num_gpus=self.gpus, max_retries=0)
        return self.ray.get(fn.remote(device))

    def _ref(self, path: Optional[str]):
        if path is None:
            return None
        if path not in self._images:
            self._images[path] = self.ray.put(Path(path).read_bytes())
        return self._images[path]

    def submit(self, task: dict) -> None:
        task = dict(task, image_suffix=Path(task["image_path"]).suffix or ".png")
        ref = self._fn.remote(task, self._ref(task["image_path"]), self._ref(task["settings"].get("mask")))
        self._inflight[ref] = task

    def wait(self, timeout: float) -> list:
        if not self._inflight:
            return []
        ready, _ = self.ray.wait(list(self._inflight), num_returns=1, timeout=timeout)
        outcomes = []
        for ref in ready:
            task = self._inflight.pop(ref)
            try:
                record = self.ray.get(ref)
            except self.ray.exceptions.RayTaskError as exc:  # our code raised outside run_job: a bug
                outcomes.append(("result", task, {"status": "failed", "error": {
                    "kind": "error", "type": type(exc).__name__, "message": str(exc)[-2000:]}}))
                continue
            except self.ray.exceptions.RayError as exc:  # WorkerCrashedError, OutOfMemoryError, NodeDiedError, ...
                outcomes.append(("infra", task, f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"))
                continue
            payload = record.pop("payload", None) or {}
            base = self.out / task["id"]
            from ..fsutil import atomic_output

            for rel, data in payload.items():
                with atomic_output(base / rel, suffix=".tmp" + Path(rel).suffix) as tmp:
                    Path(tmp).write_bytes(data)
            outcomes.append(("result", task, record))
        return outcomes

    def stop(self, abort: bool = False) -> None:
        if abort:
            for ref in list(self._inflight):
                try:
                    self.ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001 - already finished or gone
                    pass
        self._inflight.clear()
        if self._started:
            self.ray.shutdown()
            self._started = False


def comfy_task(task: dict, server: str, workflow: str, out_dir: str) -> dict:
    """One job as one prompt on a ComfyUI server: upload the image, apply the spec's NODE.INPUT
    overrides (and the settings mapped by comfy.map), queue, follow, download into the job's folder."""
    import json
    import platform

    from ..comfy.client import ComfyError, run_workflow

    t0 = time.perf_counter()
    base = Path(out_dir)
    sets = list(task.get("sets") or [])
    for setting, target in (task.get("map") or {}).items():
        value = task["settings"].get(setting)
        if value is None:
            continue
        if isinstance(target, list):
            if not isinstance(value, list) or len(value) != len(target):
                return {"status": "failed", "error": {"kind": "input", "type": "InputError", "message":
                        f"comfy.map.{setting} names {len(target)} inputs but the value is {value!r}"}}
            sets.extend(f"{t}={json.dumps(v)}" for t, v in zip(target, value))
        else:
            sets.append(f"{target}={json.dumps(value)}")
    record = {"status": "failed", "host": platform.node(), "pid": os.getpid(), "sets_applied": sets}
    try:
        with tempfile.TemporaryDirectory(dir=base.parent, prefix=f".{base.name}.dl.") as tmp:
            saved = run_workflow(Path(workflow), server, Path(tmp), image=Path(task["image_path"]), sets=sets,
                                 timeout=float(task.get("comfy_timeout") or 3600.0))
            base.mkdir(parents=True, exist_ok=True)
            files = {}
            for p in saved:
                os.replace(p, base / p.name)  # same file system: atomic
                files[p.name] = {"sha256": J.sha256_file(base / p.name), "bytes": (base / p.name).stat().st_size}
        if not files:
            raise ComfyError("the workflow saved no output file (is there a Save node?)")
        videos = [f for f in files if f.lower().endswith((".mp4", ".webm", ".mov", ".mkv", ".gif", ".avi"))]
        record.update(status="done", files=files, video=videos[0] if videos else None)
    except ComfyError as exc:
        if str(exc).startswith("Cannot reach ComfyUI"):
            raise ConnectionError(str(exc)) from None
        record["error"] = J.error_info(exc, "comfy")
    except InputError as exc:
        record["error"] = J.error_info(exc, "input")
    record["job_s"] = round(time.perf_counter() - t0, 4)
    return record


class ComfyExecutor:
    """Jobs as prompts on a ComfyUI server, ``workers`` at a time (threads: the server does the work)."""

    name = "comfy"

    def __init__(self, out: Path, server: str, workflow: Path, mapping: dict, workers: int = 1,
                 timeout: float = 3600.0):
        self.out, self.server, self.workflow, self.mapping = Path(out), server, Path(workflow), mapping
        self.timeout = float(timeout)  # the most one job (upload, run, downloads) may take on the server
        self.capacity = max(1, int(workers))
        self._inflight: dict = {}

    def start(self) -> None:
        self._pool = cf.ThreadPoolExecutor(self.capacity, thread_name_prefix="physmotion-comfy")

    def warm(self, device: str) -> dict:
        return {}

    def submit(self, task: dict) -> None:
        task = dict(task, map=self.mapping, comfy_timeout=self.timeout)
        fut = self._pool.submit(comfy_task, task, self.server, str(self.workflow), str(self.out / task["id"]))
        self._inflight[fut] = task

    def wait(self, timeout: float) -> list:
        if not self._inflight:
            return []
        done, _ = cf.wait(list(self._inflight), timeout=timeout, return_when=cf.FIRST_COMPLETED)
        outcomes = []
        for fut in done:
            task = self._inflight.pop(fut)
            try:
                outcomes.append(("result", task, fut.result()))
            except ConnectionError as exc:
                outcomes.append(("infra", task, str(exc)))
            except Exception as exc:  # noqa: BLE001
                outcomes.append(("result", task, {"status": "failed", "error": J.error_info(exc)}))
        return outcomes

    def stop(self, abort: bool = False) -> None:
        self._pool.shutdown(wait=not abort, cancel_futures=True)
        self._inflight.clear()
