"""Device-side step control and graph replay of the substep loop (MPMSolver.advance).

The time step, clock and checks live on the device, so a launch of many substeps needs no host
round trip and can be captured as a graph (``wp.capture_while``) once and replayed. Warp captures
and replays graphs on the CPU too, so the same code path that runs on CUDA is checked here:
replaying must give exactly the eager launches' numbers (same kernels, same order: tolerance 0),
the grid span a launch works on must not change any result (nodes outside the particles' stencils
carry no mass: tolerance 0), and escaping particles must be caught on the device before any kernel
writes outside the grid.
"""

import re

import numpy as np
import pytest
import torch

from physmotion_core.errors import SimulationError
from physmotion_core.sim import mpm, simulate
from physmotion_core.types import (Anchor, Conditions, Force, Gaussians, Ground, InitialVelocity, Material, Region,
                                   SimSettings, Torque)


def block(n=6, size=0.1, bottom=0.02):
    ax = torch.linspace(-size / 2, size / 2, n)
    g = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    g[:, 1] += size / 2 + bottom
    return Gaussians.from_rgb(g, torch.full((len(g), 3), 0.5), torch.full((len(g), 3), size / n / 2),
                              torch.full((len(g),), 0.9))


# A push on the left half during the first frames, then a twist: the force schedule changes mid-run.
SCENE = Conditions([Force((1.0, 0.0, 0.0), Region("box", lo=(-1, -1, -1), hi=(0, 1, 1)), 0.0, 0.06),
                    Torque((0.0, 0.002, 0.0), Region.whole(), 0.04, 0.12),
                    Ground(0.0, "friction", 0.4)])


def run(material="jelly", graph="off", frames=6, conditions=SCENE, **kw):
    st = SimSettings(frames=frames, fps=24, device="cpu", grid_res=8, graph=graph, **kw)
    return simulate(block(), Material.preset(material), conditions, st)


@pytest.mark.parametrize("material", ["jelly", "rigid"])
def test_graph_replay_is_bit_identical_to_eager_launches(material):
    eager = run(material, "off")
    graph = run(material, "on")
    assert graph.stats["graph"] and not eager.stats["graph"]
    assert graph.stats["graph_captures"] >= 1
    assert torch.equal(eager.x, graph.x) and torch.equal(eager.F, graph.F)
    assert eager.stats["substeps"] == graph.stats["substeps"]
    assert eager.stats["energy"] == graph.stats["energy"]
    # The host reads the device state once per launch, not once per substep.
    assert graph.stats["launches"] < graph.stats["substeps"] / 2
    # Captured graphs are reused: far fewer captures than launches.
    assert graph.stats["graph_captures"] <= graph.stats["launches"] / 2 + 2


def test_device_step_control_matches_the_host_cfl_rule():
    """plan_step computes dt on the device; stable_dt() is the same rule on the host."""
    from physmotion_core.sim import fill_particles
    from physmotion_core.sim.mpm import Domain, MPMSolver

    p = fill_particles(block(), 0.1 / 16)
    dom = Domain.around(p.x.min(0), p.x.max(0), 0.1 / 8, 1.0, None)
    solver = MPMSolver(p.x, p.volume, np.zeros(len(p.x), int), [Material.preset("rubber")], dom)
    expected = solver.stable_dt()
    solver.advance(1.5 * expected)
    # One full CFL step then the remaining half: a device dt off by more than 25 % either way would
    # take 1 or 3 substeps.
    assert solver.substeps == 2
    assert solver.dt_max == pytest.approx(expected, rel=1e-6)
    assert solver.t == 1.5 * expected  # the clock lands exactly on the end
    # A cap from the host (frame_dt / min_substeps) bounds every step.
    solver.set_limits(max_dt=expected / 4)
    solver.advance(solver.t + expected)
    assert solver.substeps == 6


def test_grid_span_of_a_launch_does_not_change_the_result(monkeypatch):
    """A thrown block keeps outgrowing its launch's grid span (the host widens it); the result is
    exactly that of a run whose span is the whole domain from the start."""
    throw = Conditions([InitialVelocity((2.0, 1.5, 0.0), (0.0, 0.0, 4.0)), Ground(0.0, "slip")])
    a = run("jelly", "off", frames=8, conditions=throw, domain_margin=3.0)
    monkeypatch.setattr(mpm, "SPAN_QUANTUM", 100_000)  # spans round out to the whole domain
    b = run("jelly", "off", frames=8, conditions=throw, domain_margin=3.0)
    assert torch.equal(a.x, b.x)
    moved = float((a.x[-1].mean(0) - a.x[0].mean(0)).norm())
    assert moved > 0.2  # it really travelled across many cells (dx = 0.0125 m)


def test_span_is_widened_when_particles_outgrow_it():
    from physmotion_core.sim import fill_particles
    from physmotion_core.sim.mpm import Domain, MPMSolver

    p = fill_particles(block(), 0.1 / 16)
    dom = Domain.around(p.x.min(0), p.x.max(0), 0.1 / 8, 3.0, None)
    v0 = np.tile(np.array([[3.0, 0.0, 0.0]], np.float32), (len(p.x), 1))
    solver = MPMSolver(p.x, p.volume, np.zeros(len(p.x), int), [Material.preset("jelly")], dom, v0=v0,
                       gravity=(0, 0, 0))
    solver.advance(0.005)  # the span is sized for 5 ms of travel (about 2 cells) ...
    assert solver.span_changes == 0
    solver.advance(0.05)  # ... so 45 ms more (11 cells) outgrow it; the new span covers the rest
    assert solver.span_changes == 1
    shift = solver.positions().mean(0) - p.x.mean(0)
    assert shift[0] == pytest.approx(3.0 * 0.05, rel=0.02)  # free flight: x moves by v t


def test_escaping_particles_stop_the_run_on_the_device_with_the_frame():
    """A hand (moving anchor) drags part of the block through the wall of its box: walls hold free
    particles but not prescribed ones. The device check stops the launch before p2g writes outside
    the grid, and the error names the frame and the cause."""
    drag = Conditions([Anchor(Region("box", lo=(0.02, -1, -1), hi=(1, 1, 1)), velocity=(0.0, 0.0, 2.0))])
    with pytest.raises(SimulationError, match="left the simulation domain") as err:
        run("rubber", "on", frames=24, conditions=drag, domain_margin=0.5)
    # 0.5 object sizes + 2 cells of room (7.5 cm) at 2 m/s: gone within 40 ms, frame 1 or 2.
    assert 1 <= err.value.frame <= 3


def _cuda_available() -> bool:
    try:
        import warp as wp

        wp.config.quiet = True
        wp.init()
        return wp.is_cuda_available()
    except Exception:  # noqa: BLE001
        return False


@pytest.mark.skipif(not _cuda_available(), reason="needs a CUDA device visible to Warp")
def test_cuda_graph_run_matches_the_cpu_run():
    """On CUDA the launches are captured as CUDA graphs with conditional nodes (when the driver has
    them). Atomic adds in p2g sum in a different order there, so the match is to float32 round-off
    amplified over a few hundred substeps: 1e-4 m on a 10 cm block."""
    st = dict(frames=6, fps=24, grid_res=8)
    cpu = simulate(block(), Material.preset("jelly"), SCENE, SimSettings(device="cpu", graph="off", **st))
    gpu = simulate(block(), Material.preset("jelly"), SCENE, SimSettings(device="cuda:0", graph="auto", **st))
    import warp as wp

    assert gpu.stats["graph"] == bool(wp.is_conditional_graph_supported())
    assert float((cpu.x - gpu.x).abs().max()) < 1e-4
    assert gpu.stats["launches"] < gpu.stats["substeps"] / 2


def _nvrtc_available() -> bool:
    try:
        import warp as wp

        wp.config.quiet = True
        wp.init()
        from warp._src import context

        return bool(context.runtime.toolkit_version) and 90 in context.runtime.nvrtc_supported_archs
    except Exception:  # noqa: BLE001
        return False


@pytest.mark.skipif(not _nvrtc_available(), reason="needs Warp's NVRTC (the CUDA-enabled warp-lang wheel)")
def test_every_kernel_compiles_to_cuda_without_a_gpu(tmp_path):
    """The kernels run on the CPU in this suite; the CUDA build is a separate code path (codegen for
    device functions, atomics, launch bounds). Warp's bundled NVRTC compiles the module ahead of time
    for an H100/H200 (sm_90) with no driver, so a kernel that would only fail to build on a GPU fails
    here. Every kernel must appear as a CUDA entry point in the PTX."""
    import warp as wp

    from physmotion_core.sim import kernels

    paths = wp.compile_aot_module(kernels, arch=90, module_dir=str(tmp_path), use_ptx=True)
    ptx = "".join(p.read_text() for p in paths if str(p).endswith(".ptx"))
    assert ".target sm_90" in ptx
    names = [k.key for k in vars(kernels).values() if isinstance(k, wp.Kernel)]
    assert len(names) >= 10
    missing = [n for n in names if not re.search(rf"\.entry {n}_[0-9a-f]+_cuda_kernel_forward", ptx)]
    assert not missing, f"kernels without a CUDA entry point: {missing}"
