"""`physmotion batch`: spec expansion and job ids, the local pool and Ray giving the same bytes,
failed jobs recorded while the rest finish, a killed worker retried, resume after a rerun, a
damaged output or Ctrl-C, and the ComfyUI executor (against the stand-in server)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from physmotion_core.batch import SpecError, load_spec, run_batch
from physmotion_core.batch import manifest as M
from physmotion_core.batch.runner import KILL_ENV
from physmotion_core.video import read_video

ROOT = Path(__file__).resolve().parent.parent

# Six tiny valid jobs (3 frames, 8 cells across an 80x64 photo) and two invalid ones: a negative
# Young's modulus (refused by the driver before any worker runs) and a push at a pixel off the
# object (refused inside the worker, after the lift).
SPEC = """
[batch]
images = ["ball.png"]
combine = "list"

[defaults]
frames = 3
grid_res = 8
models = "none"
ground = "none"
device = "cpu"

[[jobs]]
material = "jelly"
force = [20, 0, 0]
[[jobs]]
material = "rubber"
force = [0, 20, 0]
[[jobs]]
material = "jelly"
E = 5e4
force = [-20, 0, 0]
[[jobs]]
material = "rubber"
force = [0, 0, 20]
[[jobs]]
material = "jelly"
velocity = [0.5, 0.5, 0]
spin = [0, 0, 3]
[[jobs]]
material = "sand"
torque = [0, 0.5, 0]
[[jobs]]
material = "jelly"
E = -5.0
force = [20, 0, 0]
[[jobs]]
material = "jelly"
force = [20, 0, 0]
force_at = [1, 1]
"""


def _ball(path: Path, shift: int = 0) -> Path:
    h, w = 64, 80
    img = np.full((h, w, 4), 128, np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    disk = (xx - 40 - shift) ** 2 + (yy - 30) ** 2 <= 14**2
    img[disk, :3] = (20, 20, 220)
    img[..., 3] = np.where(disk, 255, 0)
    cv2.imwrite(str(path), img)
    return path


def _rows(out: Path) -> list[dict]:
    return M.read_manifest(out)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """The 8-job spec run once on the local pool (2 workers), with the worker of job 1 killed
    (SIGKILL, mid-job: as it starts rendering) on its first attempt."""
    d = tmp_path_factory.mktemp("batch")
    _ball(d / "ball.png")
    (d / "sweep.toml").write_text(SPEC)
    spec = load_spec(d / "sweep.toml")
    killed = spec.jobs[1].id
    old = os.environ.get(KILL_ENV)
    os.environ[KILL_ENV] = killed
    try:
        summary = run_batch(d / "sweep.toml", d / "local", workers=2, progress=False)
    finally:
        if old is None:
            os.environ.pop(KILL_ENV, None)
        else:
            os.environ[KILL_ENV] = old
    return SimpleNamespace(dir=d, spec=spec, summary=summary, killed=killed, out=d / "local")


def test_grid_zip_and_list_expansion_and_stable_ids(tmp_path):
    _ball(tmp_path / "a.png")
    _ball(tmp_path / "b.png", shift=3)
    (tmp_path / "g.toml").write_text('[batch]\nimages = ["*.png"]\n[axes]\nmaterial = ["jelly", "rubber", "sand"]\n'
                                     'E = [2e4, 5e4]\n')
    grid = load_spec(tmp_path / "g.toml")
    assert len(grid.jobs) == 2 * 3 * 2 and len({j.id for j in grid.jobs}) == 12
    assert {j.image.name for j in grid.jobs} == {"a.png", "b.png"}
    # The same jobs written differently (YAML, keys reordered, 20000 for 2e4, zip of two columns
    # for one value of E each) get the same ids; other photo bytes or values get others.
    (tmp_path / "z.yaml").write_text("batch: {images: [a.png], combine: zip}\n"
                                     "axes: {E: [20000, 50000], material: [jelly, jelly]}\n")
    zipped = load_spec(tmp_path / "z.yaml")
    assert len(zipped.jobs) == 2
    by = {(j.image.name, j.settings["material"], j.settings["E"]): j.id for j in grid.jobs}
    assert [j.id for j in zipped.jobs] == [by[("a.png", "jelly", 2e4)], by[("a.png", "jelly", 5e4)]]
    (tmp_path / "l.toml").write_text('[batch]\ncombine = "list"\n[defaults]\nE = 2e4\n'
                                     '[[jobs]]\nimage = "b.png"\nmaterial = "rubber"\n')
    listed = load_spec(tmp_path / "l.toml")
    assert [j.id for j in listed.jobs] == [by[("b.png", "rubber", 2e4)]]
    assert by[("a.png", "jelly", 2e4)] != by[("b.png", "jelly", 2e4)]  # the bytes, not the name, count
    (tmp_path / "c.png").write_bytes((tmp_path / "a.png").read_bytes())
    (tmp_path / "c.toml").write_text('[batch]\nimages = ["c.png"]\n[axes]\nmaterial = ["jelly"]\nE = [2e4]\n')
    assert load_spec(tmp_path / "c.toml").jobs[0].id == by[("a.png", "jelly", 2e4)]  # a renamed copy: same job
    # Malformed specs stop before anything runs, with the reason.
    for text, match in [('[batch]\nimages = ["a.png"]\n[axes]\nEE = [1]\n', "unknown setting 'EE'"),
                        ('[batch]\nimages = ["a.png"]\ncombine = "zip"\n[axes]\nE = [1, 2]\nnu = [0.1, 0.2, 0.3]\n',
                         "one length"),
                        ('[batch]\nimages = ["nope.png"]\n', "no image at"),
                        ('[batch]\nimages = ["a.png"]\n[axes]\nE = 5\n', "non-empty list")]:
        (tmp_path / "bad.toml").write_text(text)
        with pytest.raises(SpecError, match=match):
            load_spec(tmp_path / "bad.toml")
    # A bad value belongs to its job only.
    (tmp_path / "v.toml").write_text('[batch]\nimages = ["a.png"]\n[axes]\nframes = [3, 2.5]\n')
    jobs = load_spec(tmp_path / "v.toml").jobs
    assert jobs[0].error is None and "frames must be a whole number" in jobs[1].error


def test_local_sweep_records_every_job_and_the_failures(sweep):
    s = sweep.summary
    assert (s.total, s.done, s.failed, s.retried) == (8, 6, 2, 1)
    rows = _rows(sweep.out)
    assert [r["id"] for r in rows] == [j.id for j in sweep.spec.jobs]  # spec order
    assert [r["status"] for r in rows] == ["done"] * 6 + ["failed"] * 2
    bad_e, off_object = rows[6], rows[7]
    assert bad_e["error"]["kind"] == "input" and "Young's modulus" in bad_e["error"]["message"]
    assert bad_e["attempts"] == 0  # refused by the driver, never sent to a worker
    assert off_object["error"]["kind"] == "input" and "does not touch the object" in off_object["error"]["message"]
    assert off_object["attempts"] == 1
    digests = set()
    for r in rows[:6]:
        assert r["stats"]["particles"] > 100 and r["stats"]["substeps"] >= 2 * 8
        assert set(r["stats"]["energy_final"]) == {"kinetic", "potential", "work"}
        assert r["timings"]["simulate_s"] > 0 and r["stages"] == {"segment": "alpha", "lift": "silhouette"}
        video = sweep.out / r["video"]
        frames, fps = read_video(video)
        assert frames.shape == (3, 64, 80, 3) and fps == pytest.approx(24.0)
        assert M.verify(sweep.out, M.read_record(sweep.out, r["id"]))[0]
        digests.add(r["video_sha256"])
    assert len(digests) == 6  # six different motions
    log = (sweep.out / "batch.log").read_text()
    assert log.count(" done in ") == 6 and log.count(" FAILED ") == 2
    try:
        import pyarrow.parquet as pq
    except ModuleNotFoundError:
        return
    table = pq.read_table(sweep.out / "manifest.parquet").to_pylist()
    assert [t["status"] for t in table] == [r["status"] for r in rows]
    assert [t["stats.particles"] for t in table[:6]] == [r["stats"]["particles"] for r in rows[:6]]


def test_a_killed_worker_is_retried_and_only_its_job_counts_the_attempt(sweep):
    rows = {r["id"]: r for r in _rows(sweep.out)}
    assert rows[sweep.killed]["status"] == "done" and rows[sweep.killed]["attempts"] == 2
    assert all(r["attempts"] <= 1 for i, r in rows.items() if i != sweep.killed)
    log = (sweep.out / "batch.log").read_text()
    assert f"{sweep.killed} ball-0001 retrying" in log and "killed by signal SIGKILL" in log


def test_ray_sweep_gives_byte_identical_videos(sweep):
    import ray  # noqa: F401 - in the test extra: a missing Ray is a failure, not a skip

    out = sweep.dir / "ray"
    s = run_batch(sweep.dir / "sweep.toml", out, ray="auto", workers=2, progress=False)
    assert s.executor == "ray" and (s.done, s.failed) == (6, 2)
    local, remote = _rows(sweep.out), _rows(out)
    for a, b in zip(local, remote):
        assert (a["id"], a["status"]) == (b["id"], b["status"])
        if a["status"] == "done":
            assert b["executor"] == "ray" and a["video_sha256"] == b["video_sha256"]
            assert (sweep.out / a["video"]).read_bytes() == (out / b["video"]).read_bytes()
        else:
            assert a["error"]["message"] == b["error"]["message"]


def test_a_worker_that_dies_before_the_next_submit_does_not_stop_the_batch(tmp_path):
    """The race CI hit: a worker dies, another job finishes first, and the runner submits the next job
    to the broken pool before any wait() has seen the death. The submit must restart the pool, report
    the dropped job at the next wait(), and run the new job on the new pool."""
    from physmotion_core.batch.executors import LocalExecutor

    ex = LocalExecutor(tmp_path, workers=1, threads=1)
    ex.start()
    try:
        # a job in flight when the worker dies: it sleeps inside the worker (no physics, no torch)
        old = dict(ex._pool._processes)
        busy = {"id": "busy", "settings": {}, "attempt": 1, "physics_version": "x"}
        fut = ex._pool.submit(time.sleep, 30)
        ex._inflight[fut] = busy
        (tmp_path / "busy").mkdir()
        deadline = time.monotonic() + 60
        while not old and time.monotonic() < deadline:
            time.sleep(0.1)
            old = dict(ex._pool._processes)
        pid = next(iter(old))
        ex._procs.update(old)  # as submit() records them
        (tmp_path / "busy" / ".running").write_text(f"{pid} 1")
        time.sleep(0.5)
        os.kill(pid, signal.SIGKILL)
        while not ex._pool._broken and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ex._pool._broken, "the pool did not notice its worker died"
        # a job whose worker refuses it at once (another physics version): a quick, real result
        ex.submit({"id": "next", "settings": {}, "attempt": 1, "physics_version": "not-this-one"})
        seen = {}
        while len(seen) < 2 and time.monotonic() < deadline:
            for kind, task, value in ex.wait(timeout=1.0):
                seen[task["id"]] = (kind, value)
        assert seen["busy"][0] == "infra" and "SIGKILL" in seen["busy"][1], seen
        kind, record = seen["next"]
        assert kind == "result" and record["status"] == "failed", seen
        assert record["error"]["type"] == "EnvironmentMismatch", record
        assert record["pid"] not in old, "the new job ran on the dead pool's worker"
    finally:
        ex.stop(abort=True)


def test_rerun_does_no_work(sweep):
    videos = {r["id"]: sweep.out / r["video"] for r in _rows(sweep.out) if r["status"] == "done"}
    stamps = {i: p.stat().st_mtime_ns for i, p in videos.items()}
    s = run_batch(sweep.dir / "sweep.toml", sweep.out, workers=2, progress=False)
    assert (s.ran, s.skipped, s.executor) == (0, 8, "")  # nothing started, not even a worker
    assert {i: p.stat().st_mtime_ns for i, p in videos.items()} == stamps


def test_ctrl_c_stops_cleanly_and_a_rerun_finishes_the_rest(sweep, tmp_path):
    out = tmp_path / "interrupted"
    cmd = [sys.executable, "-m", "physmotion_core.cli", "batch", str(sweep.dir / "sweep.toml"), "-o", str(out),
           "--workers", "1", "-q"]
    env = {k: v for k, v in os.environ.items() if k != KILL_ENV}
    # SIGINT as a terminal gives it: a shell without job control starts background commands (and so
    # this test's children) with SIGINT ignored.
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    first = None
    while time.monotonic() < deadline and first is None and proc.poll() is None:
        for j in sweep.spec.jobs[:6]:
            rec = M.read_record(out, j.id)
            if rec is not None and rec["status"] == "done":
                first = j.id
                break
        time.sleep(0.05)
    assert first is not None, proc.communicate()[1][-2000:]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    assert "interrupted" in err and "Traceback" not in err
    rows = _rows(out)
    done = [r for r in rows if r["status"] == "done"]
    assert first in {r["id"] for r in done} and len(done) < 6  # jobs were left when it stopped
    finished = [r for r in rows if r["status"] != "pending"]  # done, or failed for good (bad values)
    leftovers = [p for p in out.rglob("*") if p.name.startswith(".") and p.name != ".batch.lock"]
    assert leftovers == []  # no temporary files of a half-written output, no running markers
    # Damage the finished video: the rerun must not trust it, and makes it again, to the same bytes.
    video = out / first / "video.mp4"
    good = video.read_bytes()
    damaged = bytearray(good)
    damaged[len(damaged) // 2] ^= 0xFF
    video.write_bytes(bytes(damaged))
    s = run_batch(sweep.dir / "sweep.toml", out, workers=2, progress=False)
    assert s.skipped == len(finished) - 1 and s.done + s.failed + s.skipped == 8
    assert video.read_bytes() == good
    assert f"{first} " in (log := (out / "batch.log").read_text()) and "has changed since it was written" in log
    # One worker on two threads made the same bytes as two workers on one thread each.
    assert [r["video_sha256"] for r in _rows(out)] == [r["video_sha256"] for r in _rows(sweep.out)]


def test_a_job_writes_the_ply_sequence_tracks_and_flow_it_is_asked_for(tmp_path):
    from physmotion_core.batch.job import run_job

    _ball(tmp_path / "ball.png")
    (tmp_path / "o.toml").write_text('[batch]\nimages = ["ball.png"]\n[defaults]\nframes = 3\ngrid_res = 8\n'
                                     'models = "none"\nground = "none"\ndevice = "cpu"\nforce = [20, 0, 0]\n'
                                     '[outputs]\nply = "sequence"\ntracks = true\ntracks_points = 16\nflow = true\n')
    spec = load_spec(tmp_path / "o.toml")
    job = spec.jobs[0]
    task = {"id": job.id, "settings": job.settings, "attempt": 1, "outputs": spec.outputs, "image_path": str(job.image)}
    rec = run_job(task, tmp_path / job.id)
    assert rec["status"] == "done", rec.get("error")
    assert sorted(rec["files"]) == ["flow.npz", "ply/frame_00000.ply", "ply/frame_00001.ply", "ply/frame_00002.ply",
                                    "tracks.npz", "video.mp4"]
    rec["id"] = job.id
    assert M.verify(tmp_path, rec)[0]
    tracks = np.load(tmp_path / job.id / "tracks.npz")
    assert tracks["uv"].shape[:2] == (3, 16) and tracks["visible"][0].all()
    flow = np.load(tmp_path / job.id / "flow.npz")
    assert flow["flow"].shape == (2, 64, 80, 2) and flow["valid"].any()
    assert abs(flow["flow"][0][flow["valid"][0]][:, 0].mean()) > 0  # the push moves the ball in x


def test_comfy_executor_sends_one_prompt_per_job_with_the_spec_overrides(tmp_path):
    from test_comfy_client import FakeComfy

    _ball(tmp_path / "ball.png")
    wf = ROOT / "example_workflows" / "api" / "push_a_jelly.json"
    (tmp_path / "c.toml").write_text(f"""
[batch]
images = ["ball.png"]
[comfy]
workflow = "{wf.as_posix()}"
[comfy.map]
material = "PhysMotionMaterial.preset"
force = ["PhysMotionForce.fx", "PhysMotionForce.fy", "PhysMotionForce.fz"]
[defaults]
force = [5, 0, 0]
[axes]
material = ["jelly", "rubber"]
"PhysMotionMPMSimulate.cfl" = [0.3]
""")
    fake = FakeComfy()
    try:
        s = run_batch(tmp_path / "c.toml", tmp_path / "out", comfy=fake.url, progress=False)
    finally:
        fake.close()
    assert (s.executor, s.done, s.failed) == ("comfy", 2, 0)
    prompts = sorted(fake.prompts.values(), key=lambda p: p["4"]["inputs"]["preset"])
    assert [p["4"]["inputs"]["preset"] for p in prompts] == ["jelly", "rubber"]
    assert all(p["6"]["inputs"]["fx"] == 5 and p["7"]["inputs"]["cfl"] == 0.3 for p in prompts)
    assert all(p["1"]["inputs"]["image"] == "ball.png" for p in prompts)
    rows = _rows(tmp_path / "out")
    assert [r["status"] for r in rows] == ["done", "done"]
    for r in rows:
        assert (tmp_path / "out" / r["video"]).read_bytes() == b"PhysMotion/push_a_jelly_00001.mp4"
    # An unreachable server is an infrastructure fault: retried, then recorded as such.
    s = run_batch(tmp_path / "c.toml", tmp_path / "out2", comfy="http://127.0.0.1:9", retries=1, progress=False)
    assert (s.failed, s.retried) == (2, 2)
    assert all(r["error"]["kind"] == "infrastructure" for r in _rows(tmp_path / "out2"))
