"""``warp_build.built_once``: the lazy, once-per-process build of a module's Warp kernels."""

from __future__ import annotations

import threading

import pytest

from physmotion_core.warp_build import built_once


def test_builds_once_with_warp_and_returns_the_same_result_to_every_caller():
    calls = []

    @built_once
    def build(wp):
        calls.append(wp)
        return object()

    results = []
    threads = [threading.Thread(target=lambda: results.append(build())) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and calls[0].__name__ == "warp"  # the warp module, imported and initialised
    assert len(results) == 8 and all(r is results[0] for r in results)
    assert build() is results[0] and len(calls) == 1
    assert build.__name__ == "build"


def test_a_failed_build_is_tried_again():
    tries = []

    @built_once
    def build(wp):
        tries.append(1)
        if len(tries) == 1:
            raise RuntimeError("first build fails")
        return "built"

    with pytest.raises(RuntimeError, match="first build fails"):
        build()
    assert build() == "built" and build() == "built" and len(tries) == 2
