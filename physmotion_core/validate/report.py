"""Markdown tables for the accuracy suite."""

from __future__ import annotations

from .harness import CaseResult


def _cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _fmt(value: float, absolute: bool) -> str:
    if absolute:
        return f"{value:+.2g}"
    return f"{value:+.2%}" if abs(value) >= 1e-3 else f"{value:+.1e}"


def cases_markdown(results: list[CaseResult], machine: str) -> str:
    passed = sum(r.passed for r in results)
    lines = [f"{passed} of {len(results)} comparisons within tolerance. Machine: {machine}.", "",
             "| case | quantity | measured | expected | error | tolerance | why this tolerance | s |",
             "|---|---|---:|---:|---:|---:|---|---:|"]
    for r in results:
        tol = f"{r.tolerance:.2g}" if r.absolute else (f"{r.tolerance:.2%}" if r.tolerance >= 1e-3
                                                         else f"{r.tolerance:.0e}")
        mark = "" if r.passed else " **(fail)**"
        lines.append(f"| {_cell(r.name)}{mark} | {_cell(r.quantity)} | {r.measured:.5g} | {r.expected:.5g} | "
                     f"{_fmt(r.error, r.absolute)} | {tol} | {_cell(r.why)} | {r.seconds:.1f} |")
    return "\n".join(lines)
