"""The anchor's passes run over the anchored particles' part of the grid only (MPMSolver._anchor_span), and
grid_update reads the anchored-mass accumulators only there. Elsewhere no node is held or next to a held one,
so the result must be bit for bit the one of passes over the whole span; a held particle that would leave the
anchor's span ends the launch (kernels.track_anchored) and the host finds the spans again.

Each scene runs three ways through ``simulate()``: as shipped, with the anchor's span forced to the whole
launch span (what the passes covered before), and with the tightest span the check allows (the held
particles' stencils and one node around them, no room for travel, so a moving anchor outgrows it every few
substeps). Positions and F must be identical in all three.
"""

import numpy as np
import pytest

import physmotion_core.sim.mpm as mpm
from physmotion_core.sim.simulate import simulate
from physmotion_core.types import Anchor, Conditions, Force, Gravity, Material, Region, SimSettings
from physmotion_core.validate.stress import gaussian_box


def _whole(self, horizon):
    return self._span


def _tight(self, horizon):
    d = self.domain
    xa = self.x.numpy()[self._held].astype(np.float64)
    lo = np.floor((xa.min(0) - d.origin) / d.dx - 0.5).astype(np.int64) - 1
    hi = np.floor((xa.max(0) - d.origin) / d.dx - 0.5).astype(np.int64) + 3
    (slo, shi) = self._span
    lo = tuple(int(max(a, s)) for a, s in zip(lo, slo))
    hi = tuple(int(min(a, s)) for a, s in zip(hi, shi))
    return lo, hi


def _runs(monkeypatch, run):
    spans, out = {}, {}
    for mode, fn in (("shipped", mpm.MPMSolver._anchor_span), ("whole", _whole), ("tight", _tight)):
        seen = []

        def record(self, horizon, fn=fn, seen=seen):
            s = fn(self, horizon)
            seen.append((s, self._span))
            return s

        monkeypatch.setattr(mpm.MPMSolver, "_anchor_span", record)
        out[mode] = run()
        spans[mode] = seen
    return out, spans


def _nodes(span):
    return int(np.prod([h - l + 1 for l, h in zip(*span)]))


def test_hanging_bar_is_the_same_over_the_anchors_span(monkeypatch):
    def run():
        g = gaussian_box((-0.1, 0.0, -0.1), (0.1, 1.1, 0.1), (9, 45, 9))
        mat = Material(name="elastic", model="fixed_corotated", E=1e5, nu=0.0, density=1000.0, damping=15.0)
        r = simulate(g, mat, Conditions([Anchor(Region("box", lo=(-1, 1.0, -1), hi=(1, 5, 1))),
                                         Gravity((0, -9.81, 0))]),
                     SimSettings(frames=10, fps=60, grid_res=10, device="cpu", rest_speed=0.0), record_all=True)
        return r.x.numpy(), r.F.numpy()

    out, spans = _runs(monkeypatch, run)
    for mode in ("whole", "tight"):
        assert np.array_equal(out["shipped"][0], out[mode][0]), mode
        assert np.array_equal(out["shipped"][1], out[mode][1]), mode
    # The anchor holds the top 10 cm of 1.1 m: its span is a small part of the launch's.
    a, s = spans["shipped"][0]
    assert _nodes(a) < 0.5 * _nodes(s), (a, s)


@pytest.mark.parametrize("threads", [1, 2])
def test_moving_anchor_outgrows_its_span_and_nothing_changes(monkeypatch, threads):
    """A held face driven at 0.6 m/s, released at 0.2 s, a force on the far side, under gravity: with the
    tight span the held particles leave it again and again (each time a new launch with new spans)."""

    def run():
        g = gaussian_box((0.0, 0.2, 0.0), (0.16, 0.36, 0.16), (9, 9, 9))
        mat = Material(name="jelly", model="fixed_corotated", E=2e4, nu=0.3, density=1000.0)
        r = simulate(g, mat, Conditions([
            Anchor(Region("box", lo=(-1, -1, -1), hi=(0.04, 5, 5)), velocity=(0.0, 0.6, 0.0), t_end=0.2),
            Force((2.0, 0.0, 0.0), Region("box", lo=(0.12, -1, -1), hi=(1, 5, 5)), t_end=0.15),
            Gravity((0, -9.81, 0))]),
            SimSettings(frames=12, fps=40, grid_res=12, device="cpu", cpu_threads=threads), record_all=True)
        return r.x.numpy(), r.F.numpy()

    out, spans = _runs(monkeypatch, run)
    for mode in ("whole", "tight"):
        assert np.array_equal(out["shipped"][0], out[mode][0]), mode
        assert np.array_equal(out["shipped"][1], out[mode][1]), mode
    assert len(spans["tight"]) > len(spans["shipped"]) + 3, (len(spans["tight"]), len(spans["shipped"]))
    # The body really moved: the held face rose by about 0.6 m/s x 0.2 s.
    x = out["shipped"][0]
    held = x[0, :, 0] < 0.04
    rise = float(x[8, held, 1].mean() - x[0, held, 1].mean())
    assert 0.10 < rise < 0.13, rise
