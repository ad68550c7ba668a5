"""The compiled grid max-flow (``segment.gridflow``) and GrabCut on it, against independent answers:
every labelling of a tiny grid (brute force) for the cut, and OpenCV's own ``cv2.grabCut`` for GrabCut."""

import itertools
import logging

import cv2
import numpy as np
import pytest

from physmotion_core.segment import classic as C
from physmotion_core.segment.gridflow import GrabCutGraph, GridCut

FORWARD = ((1, 0), (1, 1), (0, 1), (-1, 1))  # right, down-right, down, down-left


def cut_cost(lab, links, source, sink) -> float:
    """The cost of a labelling (True: source side): the source links of the sink side, the sink links of the
    source side, and every neighbour link between the two sides."""
    h, w = lab.shape
    c = float(source[~lab].sum() + sink[lab].sum())
    for (dx, dy), link in zip(FORWARD, links):
        for y in range(h):
            for x in range(w):
                X, Y = x + dx, y + dy
                if 0 <= X < w and 0 <= Y < h and lab[y, x] != lab[Y, X]:
                    c += float(link[y, x])
    return c


def brute_force(links, source, sink):
    """(the least cost, every labelling that reaches it) over all 2^n labellings."""
    h, w = source.shape
    costs = []
    for bits in itertools.product([False, True], repeat=h * w):
        lab = np.array(bits).reshape(h, w)
        costs.append((cut_cost(lab, links, source, sink), lab))
    best = min(c for c, _ in costs)
    return best, [lab for c, lab in costs if c <= best + 1e-9]


def random_problem(rng, h, w):
    links = [rng.uniform(0, 3, (h, w)) * (rng.random((h, w)) < 0.8) for _ in range(4)]
    return links


def terminals(rng, h, w):
    return (rng.uniform(0, 5, (h, w)) * (rng.random((h, w)) < 0.7),
            rng.uniform(0, 5, (h, w)) * (rng.random((h, w)) < 0.7))


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (3, 1), (2, 3), (3, 3), (3, 4)])
def test_the_cut_is_the_smallest_minimum_cut_of_every_labelling(shape):
    """On grids small enough to try every labelling: the cut costs the least any labelling costs (within
    1e-9), and it is the smallest such set: inside every labelling of that cost. The flow pushed equals it."""
    rng = np.random.default_rng(sum(shape))
    h, w = shape
    for _ in range(6):
        links = random_problem(rng, h, w)
        source, sink = terminals(rng, h, w)
        got = GridCut(*links).solve(source, sink)
        best, optimal = brute_force(links, source, sink)
        assert cut_cost(got, links, source, sink) == pytest.approx(best, abs=1e-9)
        assert all((got <= lab).all() for lab in optimal)


def test_a_solve_that_starts_from_the_last_flow_gives_the_fresh_cut():
    """Solving again with new terminal links, from the flow the last solve left (the GrabCut iterations), gives
    the cut a fresh graph gives, and that is optimal (brute force), through several changes, including a
    terminal link that shrinks below the flow already pushed through it."""
    rng = np.random.default_rng(5)
    h, w = 3, 4
    links = random_problem(rng, h, w)
    kept = GridCut(*links)
    for step in range(6):
        source, sink = terminals(rng, h, w)
        if step == 3:
            source, sink = source * 0.1, sink * 0.1  # far less than what flowed before
        got = kept.solve(source, sink)
        fresh = GridCut(*links).solve(source, sink)
        assert np.array_equal(got, fresh)
        best, optimal = brute_force(links, source, sink)
        assert cut_cost(got, links, source, sink) == pytest.approx(best, abs=1e-9)


def test_a_larger_grid_cut_matches_an_independent_max_flow():
    """A 24 x 30 grid against scipy's max-flow (integer capacities) on the same graph: the same flow value,
    and the cut's cost equals it (max-flow min-cut)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_flow

    rng = np.random.default_rng(11)
    h, w = 24, 30
    links = [rng.integers(0, 20, (h, w)).astype(float) for _ in range(4)]
    source = rng.integers(0, 40, (h, w)).astype(float)
    sink = rng.integers(0, 40, (h, w)).astype(float)
    n = h * w
    s, t = n, n + 1
    rows, cols, caps = [], [], []
    for (dx, dy), link in zip(FORWARD, links):
        for y in range(h):
            for x in range(w):
                X, Y = x + dx, y + dy
                if 0 <= X < w and 0 <= Y < h and link[y, x] > 0:
                    a, b = y * w + x, Y * w + X
                    rows += [a, b]
                    cols += [b, a]
                    caps += [int(link[y, x])] * 2
    for p in range(n):
        if source.flat[p] > 0:
            rows.append(s), cols.append(p), caps.append(int(source.flat[p]))
        if sink.flat[p] > 0:
            rows.append(p), cols.append(t), caps.append(int(sink.flat[p]))
    graph = csr_matrix((np.array(caps, np.int32), (rows, cols)), shape=(n + 2, n + 2))
    expected = maximum_flow(graph, s, t).flow_value
    g = GridCut(*links)
    got = g.solve(source, sink)
    # the flow through pixels with both links is pushed straight through: the cut's cost is the max-flow
    assert cut_cost(got, links, source, sink) == pytest.approx(expected, abs=1e-6)
    assert 0 < got.sum() < n


def _started(bgr, box, seed):
    """Labels (outside ``box``, given as fractions of the width and height, certain background; inside it
    probably object) and OpenCV's first colour models (its seeded k-means, no iteration)."""
    h, w = bgr.shape[:2]
    labels = np.full((h, w), cv2.GC_BGD, np.uint8)
    labels[int(box[1] * h):int(box[3] * h), int(box[0] * w):int(box[2] * w)] = cv2.GC_PR_FGD
    labels[:1], labels[-1:], labels[:, :1], labels[:, -1:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(seed)
    cv2.grabCut(bgr, labels, None, bgd, fgd, 0, cv2.GC_INIT_WITH_MASK)
    return labels, bgd, fgd


def _photo(name="coffee", side=160):
    import skimage.data

    im = getattr(skimage.data, name)()
    h, w = im.shape[:2]
    s = side / max(h, w)
    small = cv2.resize(im, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small[:, :, ::-1])


@pytest.mark.parametrize("name,box", [("coffee", (0.1, 0.02, 0.85, 0.95)), ("astronaut", (0.0, 0.0, 0.75, 1.0)),
                                      ("rocket", (0.44, 0.26, 0.56, 0.99))])
def test_grabcut_on_the_kept_flow_is_opencvs_grabcut_bit_for_bit(name, box):
    """Five GrabCut iterations on ``GrabCutGraph`` against ``cv2.grabCut`` with five, from the same first
    colour models (OpenCV's k-means, seeded): the same labels and the same colour models, bit for bit,
    after every iteration, on real photos."""
    bgr = _photo(name)
    labels, bgd, fgd = _started(bgr, box, 7)
    a, ab, af = labels.copy(), bgd.copy(), fgd.copy()
    b, bb, bf = labels.copy(), bgd.copy(), fgd.copy()
    graph = GrabCutGraph(bgr)
    for _ in range(5):
        cv2.grabCut(bgr, a, None, ab, af, 1, cv2.GC_EVAL)
        graph.iterate(b, bb, bf)
        assert np.array_equal(a, b) and np.array_equal(ab, bb) and np.array_equal(af, bf)
    assert (a == cv2.GC_PR_FGD).any() and (a == cv2.GC_PR_BGD).any()  # it did cut


def test_new_sure_pixels_between_iterations_give_opencvs_cut():
    """The box-tightness rounds mark new sure-object pixels and iterate again on the same graph: the labels
    and models stay OpenCV's."""
    bgr = _photo("rocket")
    h, w = bgr.shape[:2]
    labels, bgd, fgd = _started(bgr, (0.44, 0.26, 0.56, 0.99), 3)
    a, ab, af = labels.copy(), bgd.copy(), fgd.copy()
    b, bb, bf = labels.copy(), bgd.copy(), fgd.copy()
    graph = GrabCutGraph(bgr)
    for it in range(4):
        if it == 2:
            for m in (a, b):
                m[h // 4, w // 2 - 2:w // 2 + 2] = cv2.GC_FGD
                m[h - 10, int(0.45 * w):int(0.45 * w) + 3] = cv2.GC_BGD
        cv2.grabCut(bgr, a, None, ab, af, 1, cv2.GC_EVAL)
        graph.iterate(b, bb, bf)
        assert np.array_equal(a, b) and np.array_equal(ab, bb) and np.array_equal(af, bf)


def test_segment_falls_back_to_opencv_with_a_warning_and_the_same_mask(monkeypatch, caplog):
    """When the compiled engine cannot be built (a broken Warp install), GrabCut runs on OpenCV: a warning,
    and the same mask as the engine gives."""
    import physmotion_core.segment.gridflow as gf

    img = np.ascontiguousarray(_photo("coffee", 200)[:, :, ::-1])
    box = (25, 10, 170, 125)
    want = C.grabcut(img, box=box)

    def broken(*a, **k):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(gf, "GrabCutGraph", broken)
    monkeypatch.setattr(C, "_engine_failed", [])
    with caplog.at_level(logging.WARNING):
        got = C.grabcut(img, box=box)
    assert np.array_equal(got, want)
    assert any("max-flow is not available" in r.getMessage() for r in caplog.records)
    monkeypatch.setattr(C, "GRABCUT_ENGINE", "opencv")
    monkeypatch.setattr(C, "_engine_failed", [])
    assert np.array_equal(C.grabcut(img, box=box), want)
