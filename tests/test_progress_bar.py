"""The CLI's text progress bar: one redrawn line on a terminal, a few whole lines in a log, and never a
message glued to the end of a bar."""

from __future__ import annotations

import io
import logging

import pytest

from physmotion_core import progress as P


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def no_open_bar():
    P._OPEN.clear()
    yield
    P._OPEN.clear()


def test_a_bar_in_a_log_prints_the_start_each_quarter_and_the_end_once():
    out = io.StringIO()
    bar = P.TextBar("simulate", stream=out)
    assert not bar.live
    for d in range(0, 101):
        bar(d, 100)
    bar(100, 100)  # a second "done" adds nothing
    lines = out.getvalue().split("\n")
    assert lines[-1] == "" and "\r" not in out.getvalue()
    pct = [float(line.split("]")[1].split("%")[0]) for line in lines[:-1]]
    assert pct == [0.0, 25.0, 50.0, 75.0, 100.0]
    # coarse steps (a 3-frame render): each call that crosses a quarter gets its line, and the end
    out = io.StringIO()
    bar = P.TextBar("render", stream=out)
    for d in (1, 2, 3):
        bar(d, 3)
    assert [line.split("]")[1].split("%")[0].strip() for line in out.getvalue().splitlines()] == ["33.3", "66.7", "100.0"]


def test_a_bar_on_a_terminal_redraws_one_line_and_a_message_starts_a_new_one():
    term = Terminal()
    bar = P.TextBar("simulate", stream=term)
    assert bar.live
    bar(0, 10)
    bar(3, 10)
    assert term.getvalue().count("\r") == 2 and "\n" not in term.getvalue()
    P.end_line()  # what the CLI does before it prints the forecast
    term.write("object: jelly, 1 kg\n")
    bar(10, 10)
    lines = term.getvalue().split("\n")
    assert lines[1] == "object: jelly, 1 kg" and lines[0].endswith("30.0%    0.0s")
    assert "100.0%" in lines[2] and lines[-1] == ""
    P.end_line()  # nothing open any more: no empty line
    assert term.getvalue().endswith("100.0%    0.0s\n")


def test_a_second_bar_does_not_continue_the_first_ones_line():
    term = Terminal()
    first, second = P.TextBar("segment", stream=term), P.TextBar("lift", stream=term)
    first(2, 10)  # left unfinished
    second(1, 4)
    assert term.getvalue().split("\n")[1].startswith("\rlift")


def test_the_cli_ends_a_bar_line_before_a_log_record(monkeypatch, capsys):
    """``physmotion`` puts a filter on the logging handlers that ends an open bar's line first."""
    from physmotion_core import cli

    term = Terminal()
    handler = logging.StreamHandler(term)
    handler.addFilter(cli._ending_bar_lines)
    log = logging.getLogger("physmotion.test_bar")
    log.addHandler(handler)
    log.propagate = False
    try:
        bar = P.TextBar("simulate", stream=term)
        bar(1, 4)
        log.warning("the grid is coarse")
        assert term.getvalue().split("\n")[1] == "the grid is coarse"
        # and the CLI installs the filter on the root logger's handlers
        root = logging.getLogger()
        monkeypatch.setattr(root, "handlers", [logging.StreamHandler(io.StringIO())])
        assert cli.main(["validate", "--list"]) == 0
        assert any(f is cli._ending_bar_lines for f in root.handlers[0].filters)
    finally:
        log.removeHandler(handler)
