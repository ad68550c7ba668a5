"""Markdown tables for the accuracy suite."""

from __future__ import annotations

from .harness import CaseResult


def cases_markdown(results: list[CaseResult], machine: str) -> str:
    passed = sum(r.passed for r in results)
    lines = [f"{passed} of {len(results)} comparisons within tolerance. Machine: {machine}.", "",
             "| case | quantity | measured | expected | error | tolerance | why this tolerance | s |",
             "|---|---|---:|---:|---:|---:|---|---:|"]
    for r in results:
        err = f"{r.error:+.2g}" if r.absolute else f"{r.error:+.2%}"
        tol = f"{r.tolerance:.2g}" if r.absolute else f"{r.tolerance:.2%}"
        mark = "" if r.passed else " **(fail)**"
        lines.append(f"| {r.name}{mark} | {r.quantity} | {r.measured:.5g} | {r.expected:.5g} | {err} | {tol} | "
                     f"{r.why} | {r.seconds:.1f} |")
    return "\n".join(lines)
