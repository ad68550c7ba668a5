"""The CPU runs p2g, grid_update and g2p on several threads (MPMSolver.chunks / threads).

Warp runs a CPU kernel on one thread and its CPU atomics are plain adds, so the solver splits the
particles into chunks with their own grid-accumulator layers and reduction rows. The split depends
on the scene only, never on the thread count, so the thread count cannot change a single bit
(tolerance 0). Against one unsplit pass the sums only run in another order: float32 round-off.
"""

import gc
import threading
import time

import numpy as np
import pytest
import torch
from warp._src.context import Launch

from physmotion_core.errors import InputError
from physmotion_core.sim import mpm, simulate
from physmotion_core.sim.mpm import Domain, MPMSolver, cpu_chunks, cpu_threads
from physmotion_core.types.material import material_preset
from physmotion_core.types import Anchor, Conditions, Force, Gaussians, Ground, Material, SimSettings, Torque
from physmotion_core.validate.harness import lattice as lattice_points

from test_materials import box, lattice

# A jelly pushed on its left half, twisted, held on its right edge, with a rigid cube dropped on it:
# every kernel of a substep runs (anchors fill grid_fix, torques, rigid bodies), and about 14k
# particles make 3 chunks of 4096 (the chunk size is fixed here, see chunk_size), so 2 threads split
# them unevenly.
SCENE = Conditions([Force((0.5, 0.0, 0.0), box((-1, -1, -1), (0, 0.11, 1)), 0.0, 0.05),
                    Torque((0.0, 0.001, 0.0), box((-1, -1, -1), (1, 0.11, 1)), 0.0, 0.08),
                    Anchor(box((0.045, -1, -1), (1, 0.11, 1))), Ground(0.0, "friction", 0.4)])


@pytest.fixture(autouse=True)
def chunk_size(monkeypatch):
    """The scenes here are sized for 3 chunks of this many particles, whatever the default."""
    monkeypatch.setattr(mpm, "MIN_CHUNK_PARTICLES", 4096)


def scene() -> Gaussians:
    jelly = lattice((-0.06, 0.0, -0.06), (0.06, 0.1, 0.06), (12, 10, 12), 0)
    cube = lattice((-0.02, 0.13, -0.02), (0.02, 0.17, 0.02), (5, 5, 5), 1)
    return Gaussians.cat([jelly, cube])


def run(threads: int, graph: str = "off", frames: int = 3):
    st = SimSettings(frames=frames, fps=24, device="cpu", grid_res=16, cpu_threads=threads, rest_speed=0, graph=graph)
    return simulate(scene(), [Material.preset("jelly"), Material.preset("rigid")], SCENE, st, record_all=True)


def test_thread_count_does_not_change_a_bit(monkeypatch):
    monkeypatch.setattr(mpm, "MIN_SLAB_NODES", 1)  # grid_update in slabs too, however small the span
    one, two, three = run(1), run(2), run(3)
    assert one.stats["cpu_chunks"] == 3
    assert (one.stats["threads"], two.stats["threads"]) == (1, 2)
    for other in (two, three):
        assert torch.equal(one.x, other.x) and torch.equal(one.F, other.F)
        assert one.stats["substeps"] == other.stats["substeps"]
        assert one.stats["energy"] == other.stats["energy"]


def test_chunked_run_matches_one_unsplit_pass_to_round_off(monkeypatch):
    """Same kernels, sums in another order: the difference is float32 round-off (~1e-8 m per
    substep on a 0.1 m scene) accumulated over ~100 substeps; 1e-6 m leaves a margin of 10."""
    chunked = run(2)
    monkeypatch.setattr(mpm, "MIN_CHUNK_PARTICLES", 10 ** 9)
    single = run(2)
    assert chunked.stats["substeps"] == single.stats["substeps"]
    assert float((chunked.x - single.x).abs().max()) < 1e-6


def test_graph_replay_of_a_chunked_run_is_bit_identical_to_the_threaded_run():
    """A captured graph replays the chunks one after another; the threads run them at once."""
    eager = run(2, "off", frames=2)
    graph = run(2, "on", frames=2)
    assert graph.stats["graph"] and graph.stats["graph_captures"] >= 1
    assert torch.equal(eager.x, graph.x) and torch.equal(eager.F, graph.F)


def test_chunks_run_on_the_worker_threads_and_cover_every_particle_once(monkeypatch):
    x, vol = lattice_points((0.0, 0.3, 0.0), (0.25, 0.55, 0.25), 0.25 / 26)
    dom = Domain.around(x.min(0), x.max(0), 0.25 / 13, 0.5, None)
    solver = MPMSolver(x, vol, np.zeros(len(x), np.int64), [material_preset("jelly")], dom, device="cpu", threads=2)
    assert solver.chunks == len(x) // mpm.MIN_CHUNK_PARTICLES and solver.threads == 2
    starts = [a for a, _ in solver._chunk_ranges]
    counts = [c for _, c in solver._chunk_ranges]
    assert starts[0] == 0 and sum(counts) == len(x) and all(s + c == t for s, c, t in
                                                           zip(starts, counts, starts[1:] + [len(x)]))
    seen: dict = {}
    replay = Launch.launch

    def recording(cmd, *a, **kw):  # the thread of every launch command's replay
        seen.setdefault(cmd.kernel.key, set()).add(threading.get_ident())
        return replay(cmd, *a, **kw)

    monkeypatch.setattr(Launch, "launch", recording)
    for _ in range(3):
        solver.substep(1e-4)
    main = threading.get_ident()
    for key in ("p2g", "g2p"):  # the calling thread takes the last chunk, a worker the others
        assert main in seen[key] and len(seen[key]) >= 2, (key, seen)
    # A span this small (under MIN_SLAB_NODES) is not worth handing to another thread.
    assert seen["grid_update"] == seen["plan_step"] == {main}
    # Free fall, no contact yet: every particle has the same velocity -g t.
    v = solver.velocities()
    assert np.allclose(v[:, 1], -9.81 * 3e-4, rtol=1e-4) and np.abs(v[:, [0, 2]]).max() < 1e-6


def test_chunk_count_depends_on_the_particle_count_only(monkeypatch):
    assert cpu_chunks(1000, "cpu") == 1
    assert cpu_chunks(3 * mpm.MIN_CHUNK_PARTICLES + 5, "cpu") == 3
    assert cpu_chunks(10 ** 7, "cpu") == mpm.MAX_CPU_CHUNKS
    assert cpu_chunks(10 ** 7, "cuda:0") == 1  # CUDA atomics are real: one chunk, one layer
    for threads in ("1", "7"):
        monkeypatch.setenv("PHYSMOTION_CPU_THREADS", threads)
        assert cpu_threads(0) == int(threads)
        assert cpu_chunks(10 ** 7, "cpu") == mpm.MAX_CPU_CHUNKS
    assert cpu_threads(5) == 5  # an explicit setting wins over the environment
    # Layers: one per chunk while they fit the budget, else the most of 2, 4, 8 that fit, else one.
    assert mpm.layer_count(16, mpm.CHUNK_GRID_BUDGET // (16 * mpm.LAYER_BYTES)) == 16
    assert mpm.layer_count(16, mpm.CHUNK_GRID_BUDGET // (16 * mpm.LAYER_BYTES) + 1) == 8
    assert mpm.layer_count(16, mpm.CHUNK_GRID_BUDGET // (3 * mpm.LAYER_BYTES)) == 2
    assert mpm.layer_count(16, mpm.CHUNK_GRID_BUDGET // (2 * mpm.LAYER_BYTES) + 1) == 1
    assert mpm.layer_count(13, mpm.CHUNK_GRID_BUDGET // (13 * mpm.LAYER_BYTES) + 1) == 8
    # Contiguous runs of chunks share a layer, every layer gets chunks.
    assert [mpm.layer_of_chunk(c, 16, 8) for c in range(16)] == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7]
    assert sorted(set(mpm.layer_of_chunk(c, 13, 8) for c in range(13))) == list(range(8))


def test_memory_estimate_bounds_the_layers():
    nodes = 50 ** 3
    one = mpm.estimate_bytes(10 ** 5, (50, 50, 50), 1, 0, chunks=1)["device"]
    eight = mpm.estimate_bytes(10 ** 5, (50, 50, 50), 1, 0, chunks=8)["device"]
    assert eight - one == 7 * nodes * mpm.LAYER_BYTES  # 8 layers over the whole domain fit the budget
    big = (400, 400, 400)  # 64 M nodes: one layer over it is more than the budget
    assert (mpm.estimate_bytes(10 ** 5, big, 1, 0, chunks=16)["device"]
            == mpm.estimate_bytes(10 ** 5, big, 1, 0, chunks=1)["device"])


def falling_cube(threads=2, side=24, cells=12, margin=2.0):
    x, vol = lattice_points((0.0, 0.3, 0.0), (0.25, 0.55, 0.25), 0.25 / side)
    dom = Domain.around(x.min(0), x.max(0), 0.25 / cells, margin, None)
    return MPMSolver(x, vol, np.zeros(len(x), np.int64), [material_preset("jelly")], dom, device="cpu",
                     threads=threads)


def test_layers_cover_the_span_and_follow_it_as_it_grows():
    s = falling_cube()
    assert s.chunks == 3
    s.substep(1e-4)
    dims = np.asarray(s.domain.dims)
    layer_dims = np.asarray(s.grid_m.shape[1:])
    assert s.grid_m.shape[0] == s.layers == s.chunks
    assert np.prod(layer_dims) < 0.5 * np.prod(dims)  # far less than the domain (2 sizes of room)
    lo, hi = np.asarray(s._span[0]), np.asarray(s._span[1])
    assert np.all(np.asarray(s._layer_lo) <= lo) and np.all(hi <= np.asarray(s._layer_hi))
    # Fall 0.3 s: the span moves down and the layers are reallocated to follow it.
    s.advance(0.3)
    assert s.layer_reallocations >= 1
    lo, hi = np.asarray(s._span[0]), np.asarray(s._span[1])
    assert np.all(np.asarray(s._layer_lo) <= lo) and np.all(hi <= np.asarray(s._layer_hi))
    # Free fall without contact: every particle drops by the same g t²/2, plus symplectic Euler's
    # lead of at most g t dt_max / 2 (x is advanced with the velocity at the end of each step).
    drop = falling_cube().positions()[:, 1] - s.positions()[:, 1]
    g = 9.81
    assert np.ptp(drop) < 1e-5
    assert 0.5 * g * s.t ** 2 - 1e-5 <= drop.mean() <= 0.5 * g * s.t ** 2 + 0.5 * g * s.t * s.dt_max + 1e-5


def test_a_span_over_the_budget_gets_one_layer_and_the_unsplit_result(monkeypatch):
    """Chunks taking turns on one layer add in particle order, exactly as one pass does: tolerance 0."""
    monkeypatch.setattr(mpm, "CHUNK_GRID_BUDGET", 1)
    few = falling_cube()
    few.advance(0.05)
    assert few.chunks == 3 and few.layers == 1
    monkeypatch.setattr(mpm, "MIN_CHUNK_PARTICLES", 10 ** 9)
    one = falling_cube()
    one.advance(0.05)
    assert one.chunks == 1
    assert np.array_equal(few.positions(), one.positions()) and np.array_equal(few.velocities(), one.velocities())


@pytest.mark.parametrize("value", [-1, 2.5, "4", 5000])
def test_bad_thread_counts_are_refused_with_the_range(value):
    with pytest.raises(InputError, match=r"cpu_threads must be an integer in \[0, 1024\]"):
        SimSettings(cpu_threads=value).validate()


def test_bad_thread_environment_is_refused(monkeypatch):
    monkeypatch.setenv("PHYSMOTION_CPU_THREADS", "many")
    with pytest.raises(InputError, match="PHYSMOTION_CPU_THREADS must be a positive integer"):
        cpu_threads(0)


def test_worker_threads_end_with_their_run():
    """A long ComfyUI session runs many simulations: each run's pool must go with its solver."""
    before = threading.active_count()
    for _ in range(3):
        r = run(2, frames=1)
        assert r.stats["cpu_chunks"] == 3
    deadline = time.monotonic() + 5.0
    while threading.active_count() > before and time.monotonic() < deadline:
        gc.collect()
        time.sleep(0.05)
    assert threading.active_count() == before


def test_chunks_sharing_layers_give_the_same_bits_on_any_thread_count(monkeypatch):
    """A span too large for a layer per chunk gets fewer layers (here 2 for 3 chunks): the chunks of a layer
    scatter in chunk order whichever thread runs them, the layers fill concurrently, so 1, 2 and 3 threads
    give the same bits (tolerance 0); against one unsplit pass the sums run in another order (round-off)."""
    probe = falling_cube()
    probe.substep(1e-4)
    nodes = int(np.prod(probe.grid_m.shape[1:]))
    # room for 2.5 layers: not the 3 the chunks would take, but 2
    monkeypatch.setattr(mpm, "CHUNK_GRID_BUDGET", int(2.5 * nodes * mpm.LAYER_BYTES))
    runs = []
    for threads in (1, 2, 3):
        s = falling_cube(threads=threads)
        s.advance(0.05)
        assert s.chunks == 3 and s.layers == 2 and s.grid_m.shape[0] == 2
        runs.append(s)
    for other in runs[1:]:
        assert np.array_equal(runs[0].positions(), other.positions())
        assert np.array_equal(runs[0].velocities(), other.velocities())
        assert runs[0].substeps == other.substeps
    monkeypatch.setattr(mpm, "MIN_CHUNK_PARTICLES", 10 ** 9)
    one = falling_cube()
    one.advance(0.05)
    assert one.chunks == 1 and one.substeps == runs[0].substeps
    assert np.abs(one.positions() - runs[0].positions()).max() < 1e-6
