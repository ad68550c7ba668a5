"""What a long simulation tells the user while it runs: the progress bar moves within a frame (a stiff material's
frame can take minutes), says how long is left, and a run whose pace says it will take minutes or hours says so
once, with what sets its step and what makes it quicker."""

from __future__ import annotations

import importlib
import io
import logging

import numpy as np
import pytest

from physmotion_core import progress as P
from physmotion_core.types import Conditions, Ground, SimSettings
from physmotion_core.types.material import material_preset

S = importlib.import_module("physmotion_core.sim.simulate")  # the module (the package's ``simulate`` is the function)


def block(n=7, size=0.1):
    import torch

    from physmotion_core.types import Gaussians

    g = np.stack(np.meshgrid(*[np.linspace(0.0, size, n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    g[:, [0, 2]] -= size / 2
    means = torch.tensor(g, dtype=torch.float32)
    return Gaussians.from_rgb(means, torch.full((len(g), 3), 0.5), torch.full((len(g), 3), size / (n - 1) / 2),
                              torch.full((len(g),), 0.9))


def run(material, frames=4, progress=None):
    return S.simulate(block(), material, Conditions([Ground(0.0, "friction", 0.5)]),
                      SimSettings(frames=frames, fps=24, grid_res=10, domain_margin=2.0, rest_speed=0.0, device="cpu"),
                      progress=progress)


def test_progress_moves_within_a_frame_by_the_simulated_time(monkeypatch):
    """A stiff block's frame takes many launches (LAUNCH_SECONDS shortened here): the progress reported goes up
    within each frame, in step with the solver's clock, and ends at its total."""
    monkeypatch.setattr(S, "LAUNCH_SECONDS", 0.002)
    monkeypatch.setattr(S.Throttle, "__init__", lambda self, fn, interval=0.1: (
        setattr(self, "fn", fn), setattr(self, "interval", 0.0), setattr(self, "_last", 0.0))[0])
    calls = []
    res = run(material_preset("rubber", E=1.0e7), frames=3, progress=lambda d, t, preview=None: calls.append((d, t)))
    totals = {t for _, t in calls}
    assert totals == {2 * S.PROGRESS_PER_FRAME}
    done = [d for d, _ in calls]
    assert done == sorted(done) and done[-1] == 2 * S.PROGRESS_PER_FRAME
    within = {d for d in done if d % S.PROGRESS_PER_FRAME}
    assert len(within) >= 6, done  # several values inside the frames, not only at their ends
    assert res.stats["substeps"] > 30


def test_a_run_whose_pace_says_minutes_says_so_once_with_the_cause(monkeypatch, caplog):
    """The forecast: the wall time so far scaled by the simulated time left; said once, as a warning naming what
    sets the step (a stiff material's wave speed on the grid) and what makes the run quicker. A quick run (the
    thresholds as shipped) says nothing."""
    caplog.set_level(logging.WARNING, logger="physmotion.sim")
    run(material_preset("jelly"), frames=3)
    assert not [r for r in caplog.records if "pace" in r.getMessage()]
    monkeypatch.setattr(S, "PACE_CHECK_S", 0.0)
    monkeypatch.setattr(S, "PACE_WARN_S", 0.0)
    monkeypatch.setattr(S, "LAUNCH_SECONDS", 0.002)
    caplog.clear()
    run(material_preset("rubber", E=1.0e7), frames=2)
    said = [r.getMessage() for r in caplog.records if "pace" in r.getMessage()]
    assert len(said) == 1, said
    msg = said[0]
    assert "At the pace so far this simulation takes about" in msg
    assert "carries waves at" in msg and "on a grid of dx=" in msg  # what sets the step
    assert "quality draft" in msg and "lower E" in msg and "rigid material" in msg and "object height" in msg


def test_the_forecast_scales_the_wall_time_by_the_simulated_time_left(monkeypatch, caplog):
    """Checked against a clock and a solver clock that we drive: 4 s of wall time for 1/10 of the simulated time
    forecasts 40 s in all."""
    caplog.set_level(logging.WARNING, logger="physmotion.sim")

    class Solver:
        t, substeps = 0.0, 0

    now = [100.0]
    monkeypatch.setattr(S.time, "perf_counter", lambda: now[0])
    solver = Solver()
    ticks = []
    pace = S._Pace(solver, frames=11, frame_dt=0.1, tick=lambda d, t: ticks.append((d, t)), cause="the cause")
    monkeypatch.setattr(S, "PACE_WARN_S", 30.0)
    solver.t, solver.substeps, now[0] = 0.05, 500, 101.0
    pace(1)  # 1 s of wall time: too early to forecast (PACE_CHECK_S)
    assert pace.forecast_s is None and ticks[-1] == (50, 1000)
    solver.t, solver.substeps, now[0] = 0.1, 1000, 104.0
    pace(1)
    assert pace.forecast_s == pytest.approx(40.0)
    (msg,) = [r.getMessage() for r in caplog.records]
    assert "about 40 s" in msg and "in steps of 0.0001 s: the cause" in msg
    solver.t, now[0] = 0.15, 106.0
    pace(2)
    assert len(caplog.records) == 1 and ticks[-1] == (150, 1000)


def test_the_bar_says_how_long_is_left_from_its_pace(monkeypatch):
    """After 1 % and 3 s the bar adds the time left at the pace so far (elapsed x (1 - f) / f), in words; a
    terminal's line is blanked where a longer one was."""
    now = [0.0]
    monkeypatch.setattr(P.time, "monotonic", lambda: now[0])

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    bar = P.TextBar("simulate", stream=term)
    now[0] = 2.0
    bar(50, 100)
    assert term.getvalue().endswith("50.0%    2.0s")  # under ETA_AFTER's 3 s: no estimate yet
    now[0] = 10.0
    bar(25, 1000)
    assert term.getvalue().endswith("2.5%   10.0s, about 6 min left")
    now[0] = 20.0
    bar(1000, 1000)
    last = term.getvalue().split("\r")[-1]
    assert last.startswith("simulate   [####") and "left" not in last
    assert last.rstrip("\n").endswith(" " * len(", about 6 min left"))
    assert P.duration_words(40) == "40 s" and P.duration_words(720) == "12 min" and P.duration_words(12600) == "3.5 h"


def test_the_forecast_before_the_run_counts_the_substeps_the_run_takes(monkeypatch):
    """``steps_line`` (said before the wait when a run is long): its substep count, clip / (cfl dx / c), against
    the substeps a simulation of the same stiff block takes (within 5 %), and silent for a run under
    LONG_RUN_WORK (the jelly block; the rigid material, whose step does not depend on E)."""
    import re

    from physmotion_core import feedback as FB
    from physmotion_core.sim.mpm import resolve_device

    settings = SimSettings(frames=3, fps=24, grid_res=10, domain_margin=2.0, rest_speed=0.0, device="cpu")
    stiff = material_preset("rubber", E=1.0e7)
    facts = FB.body_facts(block(), stiff, settings, Ground(0.0, "friction", 0.5), resolve_device("cpu"))
    clip = (settings.frames - 1) / settings.fps
    assert FB.steps_line(stiff, facts, clip) == ""  # 600-odd particles: a short run
    monkeypatch.setattr(FB, "LONG_RUN_WORK", 1.0)
    line = FB.steps_line(stiff, facts, clip, settings.cfl)
    said = int(re.search(r"about ([\d,]+) substeps", line).group(1).replace(",", ""))
    assert f"of {len(facts.x):,} particles" in line and "rubber carries waves at" in line
    res = S.simulate(block(), stiff, Conditions([Ground(0.0, "friction", 0.5)]), settings)
    assert said == pytest.approx(res.stats["substeps"], rel=0.05), (said, res.stats["substeps"])
    assert FB.steps_line(material_preset("rigid"), facts, clip) == ""
    lines = FB.forecast(Conditions([Ground(0.0, "friction", 0.5)]), facts, stiff, clip_s=clip)
    assert lines[1] == line  # right after the mass and material
