"""Minimum s-t cuts on an 8-connected pixel grid that keep their flow between solves (GrabCut's graph).

GrabCut (Rother et al., SIGGRAPH 2004) cuts the same graph once per iteration: the links between
neighbouring pixels depend only on the photo and stay; only each pixel's links to the two terminals
change with the colour models. OpenCV builds the graph and pushes all of its flow again every iteration,
which on a low-contrast photo is most of a click's time (on the astronaut at 640 px, two cores, an
iteration with every pixel undecided took 1.2-1.7 s, with every pixel fixed 0.09 s). Here the residual graph is kept: a new iteration changes the terminal
links by their difference (Kohli and Torr, "Efficiently solving dynamic Markov random fields using graph
cuts", ICCV 2005: adding the same amount to both terminal links of a pixel changes every cut by that
amount, so only the difference of the two matters and a pushed flow never has to be taken back), and the
max-flow continues from there.

The max-flow is Boykov and Kolmogorov's augmenting-path algorithm (PAMI 2004): two search trees, one
from each terminal, grow until they touch, the path is augmented, and the nodes cut off from their tree
look for a new parent. It is written for the implicit grid (edge ``d`` of pixel ``p`` leads to
``p + (DX[d], DY[d])``, its reverse is edge ``(d + 4) % 8`` of that pixel) and compiled with Warp for
the CPU, one thread. The cut it returns is the set of pixels reachable from the source in the final
residual graph: the smallest minimum cut, which does not depend on the order of the augmentations nor
on the flow a solve started from, so a dynamic solve gives the same labels as a fresh one (up to
rounding where two cuts cost the same).
"""

# No "from __future__ import annotations": Warp reads the kernel's annotations, which name the local `wp`.

import numpy as np

from ..warp_build import built_once

#: Pixel offsets of the 8 edges of a pixel: right, down-right, down, down-left, left, up-left, up, up-right.
DX = (1, 1, 0, -1, -1, -1, 0, 1)
DY = (0, 1, 1, 1, 0, -1, -1, -1)


@built_once
def _build(wp):
    FREE = wp.constant(-1)
    TERMINAL = wp.constant(-2)
    ORPHAN = wp.constant(-3)

    @wp.func
    def neighbour(p: int, d: int, w: int, h: int, dx: wp.array(dtype=wp.int32), dy: wp.array(dtype=wp.int32)):
        x = p % w + dx[d]
        y = p / w + dy[d]
        r = int(-1)
        if x >= 0 and x < w and y >= 0 and y < h:
            r = y * w + x
        return r

    @wp.func
    def inside(x: int, y: int, d: int, w: int, h: int, dx: wp.array(dtype=wp.int32), dy: wp.array(dtype=wp.int32)):
        xx = x + dx[d]
        yy = y + dy[d]
        return xx >= 0 and xx < w and yy >= 0 and yy < h

    @wp.func
    def orphan_front(node: int, parent: wp.array(dtype=wp.int32), orphans: wp.array(dtype=wp.int32), head: int,
                     ring: int):
        # mark ``node`` an orphan and put it at the front of the orphan ring; returns the new front
        parent[node] = ORPHAN
        front = (head + ring - 1) % ring
        orphans[front] = node
        return front

    @wp.kernel(enable_backward=False)
    def maxflow(cap: wp.array(dtype=wp.float64), tr: wp.array(dtype=wp.float64), parent: wp.array(dtype=wp.int32),
                pdir: wp.array(dtype=wp.int32), tree: wp.array(dtype=wp.int32), ts: wp.array(dtype=wp.int32),
                dist: wp.array(dtype=wp.int32), queue: wp.array(dtype=wp.int32), inq: wp.array(dtype=wp.int32),
                orphans: wp.array(dtype=wp.int32), dx: wp.array(dtype=wp.int32), dy: wp.array(dtype=wp.int32),
                w: int, h: int, flow: wp.array(dtype=wp.float64)):
        # parent[p]: the node p hangs from in its tree, or FREE / TERMINAL (a root) / ORPHAN; pdir[p]: the
        # direction of the edge from p to its parent
        n = w * h
        ring = n + 1
        zero = wp.float64(0.0)
        qh = int(0)
        qt = int(0)
        # every pixel with a residual terminal link roots a tree (source: tr > 0, sink: tr < 0)
        for p in range(n):
            ts[p] = 0
            inq[p] = 0
            if tr[p] != zero:
                parent[p] = TERMINAL
                tree[p] = 0
                if tr[p] < zero:
                    tree[p] = 1
                dist[p] = 1
                queue[qt] = p
                qt = qt + 1
                inq[p] = 1
            else:
                parent[p] = FREE
        clock = int(0)
        total = wp.float64(0.0)
        cur = int(-1)
        oh = int(0)
        ot = int(0)
        while True:
            if cur >= 0:
                if parent[cur] == FREE:
                    cur = -1
            if cur < 0:
                while qh != qt and cur < 0:
                    a = queue[qh]
                    qh = (qh + 1) % ring
                    inq[a] = 0
                    if parent[a] != FREE:
                        cur = a
                if cur < 0:
                    break
            i = cur
            t = tree[i]
            xi = i % w
            yi = i / w
            # grow the tree of i by its free neighbours; stop at a neighbour of the other tree
            fa = int(-1)
            fd = int(-1)
            for d in range(8):
                if fa < 0 and inside(xi, yi, d, w, h, dx, dy):
                    j = i + dy[d] * w + dx[d]
                    rd = (d + 4) % 8
                    r = cap[i * 8 + d]
                    if t == 1:
                        r = cap[j * 8 + rd]
                    if r > zero:
                        if parent[j] == FREE:
                            tree[j] = t
                            parent[j] = i
                            pdir[j] = rd
                            ts[j] = ts[i]
                            dist[j] = dist[i] + 1
                            if inq[j] == 0:
                                queue[qt] = j
                                qt = (qt + 1) % ring
                                inq[j] = 1
                        elif tree[j] != t:
                            if t == 0:
                                fa = i
                                fd = d
                            else:
                                fa = j
                                fd = rd
                        elif ts[j] <= ts[i] and dist[j] > dist[i]:
                            parent[j] = i
                            pdir[j] = rd
                            ts[j] = ts[i]
                            dist[j] = dist[i] + 1
            if fa < 0:
                cur = -1
                continue
            clock = clock + 1
            fb = fa + dy[fd] * w + dx[fd]
            # the bottleneck of source -> fa -> fb -> sink
            bn = cap[fa * 8 + fd]
            b = fa
            while parent[b] != TERMINAL:
                c = parent[b]
                bn = wp.min(bn, cap[c * 8 + (pdir[b] + 4) % 8])
                b = c
            bn = wp.min(bn, tr[b])
            b = fb
            while parent[b] != TERMINAL:
                bn = wp.min(bn, cap[b * 8 + pdir[b]])
                b = parent[b]
            bn = wp.min(bn, -tr[b])
            # push it; a saturated edge makes the node below it an orphan. Orphans go to the front of
            # their list, so those nearest the root are adopted first (their subtrees can hang on them).
            cap[fa * 8 + fd] = cap[fa * 8 + fd] - bn
            cap[fb * 8 + (fd + 4) % 8] = cap[fb * 8 + (fd + 4) % 8] + bn
            b = fa
            while parent[b] != TERMINAL:
                c = parent[b]
                e = pdir[b]
                cap[b * 8 + e] = cap[b * 8 + e] + bn
                up = c * 8 + (e + 4) % 8
                cap[up] = cap[up] - bn
                if cap[up] <= zero:
                    oh = orphan_front(b, parent, orphans, oh, ring)
                b = c
            tr[b] = tr[b] - bn
            if tr[b] <= zero:
                oh = orphan_front(b, parent, orphans, oh, ring)
            b = fb
            while parent[b] != TERMINAL:
                c = parent[b]
                e = pdir[b]
                cap[c * 8 + (e + 4) % 8] = cap[c * 8 + (e + 4) % 8] + bn
                cap[b * 8 + e] = cap[b * 8 + e] - bn
                if cap[b * 8 + e] <= zero:
                    oh = orphan_front(b, parent, orphans, oh, ring)
                b = c
            tr[b] = tr[b] + bn
            if tr[b] >= zero:
                oh = orphan_front(b, parent, orphans, oh, ring)
            total = total + bn
            # adopt the orphans: a new parent in the same tree whose path still reaches the terminal
            while oh != ot:
                o = orphans[oh]
                oh = (oh + 1) % ring
                to = tree[o]
                xo = o % w
                yo = o / w
                best = int(-1)
                dmin = int(2147483647)
                for d in range(8):
                    if inside(xo, yo, d, w, h, dx, dy):
                        j = o + dy[d] * w + dx[d]
                        r = cap[j * 8 + (d + 4) % 8]
                        if to == 1:
                            r = cap[o * 8 + d]
                        if r > zero and parent[j] != FREE and tree[j] == to:
                            k = j
                            dd = int(0)
                            ok = int(0)
                            while True:
                                if ts[k] == clock:
                                    dd = dd + dist[k]
                                    ok = 1
                                    break
                                pk = parent[k]
                                dd = dd + 1
                                if pk == TERMINAL:
                                    ts[k] = clock
                                    dist[k] = 1
                                    ok = 1
                                    break
                                if pk == ORPHAN:
                                    break
                                k = pk
                            if ok == 1:
                                if dd < dmin:
                                    dmin = dd
                                    best = d
                                k = j
                                while ts[k] != clock:
                                    ts[k] = clock
                                    dist[k] = dd
                                    dd = dd - 1
                                    k = parent[k]
                if best >= 0:
                    parent[o] = o + dy[best] * w + dx[best]
                    pdir[o] = best
                    ts[o] = clock
                    dist[o] = dmin + 1
                else:
                    parent[o] = FREE
                    for d in range(8):
                        if inside(xo, yo, d, w, h, dx, dy):
                            j = o + dy[d] * w + dx[d]
                            if parent[j] != FREE and tree[j] == to:
                                r = cap[j * 8 + (d + 4) % 8]
                                if to == 1:
                                    r = cap[o * 8 + d]
                                if r > zero and inq[j] == 0:
                                    queue[qt] = j
                                    qt = (qt + 1) % ring
                                    inq[j] = 1
                                if parent[j] == o:
                                    parent[j] = ORPHAN
                                    orphans[ot] = j
                                    ot = (ot + 1) % ring
        flow[0] = flow[0] + total

    @wp.kernel(enable_backward=False)
    def nlinks(img: wp.array(dtype=wp.uint8), w: int, h: int, beta: wp.float64, gamma: wp.float64,
               gamma_diag: wp.float64, dx: wp.array(dtype=wp.int32), dy: wp.array(dtype=wp.int32),
               cap: wp.array(dtype=wp.float64)):
        # GrabCut's smoothness term: gamma exp(-beta |colour step|^2), gamma / sqrt(2) on the diagonals
        p = wp.tid()
        for d in range(8):
            q = neighbour(p, d, w, h, dx, dy)
            c = wp.float64(0.0)
            if q >= 0:
                s = wp.float64(0.0)
                for k in range(3):
                    diff = wp.float64(int(img[p * 3 + k]) - int(img[q * 3 + k]))
                    s = s + diff * diff
                g = gamma
                if d % 2 == 1:
                    g = gamma_diag
                c = g * wp.exp(-beta * s)
            cap[p * 8 + d] = c

    @wp.func
    def density(k: int, c0: wp.float64, c1: wp.float64, c2: wp.float64, coef: wp.array(dtype=wp.float64),
                mean: wp.array(dtype=wp.float64), inv: wp.array(dtype=wp.float64), det: wp.array(dtype=wp.float64)):
        # one Gaussian of a colour model, unweighted and without the 2 pi factor, as OpenCV's GMM has it
        res = wp.float64(0.0)
        if coef[k] > wp.float64(0.0):
            d0 = c0 - mean[k * 3]
            d1 = c1 - mean[k * 3 + 1]
            d2 = c2 - mean[k * 3 + 2]
            i = k * 9
            mult = (d0 * (d0 * inv[i] + d1 * inv[i + 3] + d2 * inv[i + 6])
                    + d1 * (d0 * inv[i + 1] + d1 * inv[i + 4] + d2 * inv[i + 7])
                    + d2 * (d0 * inv[i + 2] + d1 * inv[i + 5] + d2 * inv[i + 8]))
            res = wp.float64(1.0) / wp.sqrt(det[k]) * wp.exp(wp.float64(-0.5) * mult)
        return res

    @wp.kernel(enable_backward=False)
    def assign(img: wp.array(dtype=wp.uint8), labels: wp.array(dtype=wp.uint8), coef: wp.array(dtype=wp.float64),
               mean: wp.array(dtype=wp.float64), inv: wp.array(dtype=wp.float64), det: wp.array(dtype=wp.float64),
               comp: wp.array(dtype=wp.int32)):
        # each pixel's most likely Gaussian in the model of its side (background: labels 0 and 2)
        p = wp.tid()
        c0 = wp.float64(img[p * 3])
        c1 = wp.float64(img[p * 3 + 1])
        c2 = wp.float64(img[p * 3 + 2])
        m = int(5)
        if labels[p] == wp.uint8(0) or labels[p] == wp.uint8(2):
            m = 0
        best = int(0)
        top = wp.float64(0.0)
        for ci in range(5):
            v = density(m + ci, c0, c1, c2, coef, mean, inv, det)
            if v > top:
                best = ci
                top = v
        comp[p] = m + best

    @wp.kernel(enable_backward=False)
    def accumulate(img: wp.array(dtype=wp.uint8), comp: wp.array(dtype=wp.int32), n: int,
                   stats: wp.array(dtype=wp.float64)):
        # per Gaussian (10): count, colour sums (3), products (9); integers, so exact in any order
        for p in range(n):
            k = comp[p] * 13
            c0 = wp.float64(img[p * 3])
            c1 = wp.float64(img[p * 3 + 1])
            c2 = wp.float64(img[p * 3 + 2])
            stats[k] = stats[k] + wp.float64(1.0)
            stats[k + 1] = stats[k + 1] + c0
            stats[k + 2] = stats[k + 2] + c1
            stats[k + 3] = stats[k + 3] + c2
            stats[k + 4] = stats[k + 4] + c0 * c0
            stats[k + 5] = stats[k + 5] + c0 * c1
            stats[k + 6] = stats[k + 6] + c0 * c2
            stats[k + 7] = stats[k + 7] + c1 * c0
            stats[k + 8] = stats[k + 8] + c1 * c1
            stats[k + 9] = stats[k + 9] + c1 * c2
            stats[k + 10] = stats[k + 10] + c2 * c0
            stats[k + 11] = stats[k + 11] + c2 * c1
            stats[k + 12] = stats[k + 12] + c2 * c2

    @wp.kernel(enable_backward=False)
    def tlinks(img: wp.array(dtype=wp.uint8), labels: wp.array(dtype=wp.uint8), coef: wp.array(dtype=wp.float64),
               mean: wp.array(dtype=wp.float64), inv: wp.array(dtype=wp.float64), det: wp.array(dtype=wp.float64),
               lam: wp.float64, first: int, last: wp.array(dtype=wp.float64), tr: wp.array(dtype=wp.float64)):
        # the terminal links (source: -log p_background, sink: -log p_object; a sure pixel: lambda to its
        # side), kept as their difference; a later solve adds its change to the residual
        p = wp.tid()
        lab = labels[p]
        diff = wp.float64(0.0)
        if lab == wp.uint8(0):
            diff = -lam
        elif lab == wp.uint8(1):
            diff = lam
        else:
            c0 = wp.float64(img[p * 3])
            c1 = wp.float64(img[p * 3 + 1])
            c2 = wp.float64(img[p * 3 + 2])
            pb = wp.float64(0.0)
            pf = wp.float64(0.0)
            for ci in range(5):
                pb = pb + coef[ci] * density(ci, c0, c1, c2, coef, mean, inv, det)
            for ci in range(5):
                pf = pf + coef[5 + ci] * density(5 + ci, c0, c1, c2, coef, mean, inv, det)
            # a colour no Gaussian of a model explains has probability 0 under it: a large finite cost
            # instead of OpenCV's infinity (which is NaN when both are 0)
            big = wp.float64(1.0e12)
            src = big
            if pb > wp.float64(0.0):
                src = wp.min(-wp.log(pb), big)
            snk = big
            if pf > wp.float64(0.0):
                snk = wp.min(-wp.log(pf), big)
            diff = src - snk
        if first != 0:
            tr[p] = diff
        else:
            tr[p] = tr[p] + (diff - last[p])
        last[p] = diff

    @wp.kernel(enable_backward=False)
    def relabel(parent: wp.array(dtype=wp.int32), tree: wp.array(dtype=wp.int32), labels: wp.array(dtype=wp.uint8)):
        # the undecided pixels on the source side of the cut are probably object (3), the rest background (2)
        p = wp.tid()
        lab = labels[p]
        if lab == wp.uint8(2) or lab == wp.uint8(3):
            if parent[p] != FREE and tree[p] == 0:
                labels[p] = wp.uint8(3)
            else:
                labels[p] = wp.uint8(2)

    # compile and load now, under ``built_once``'s lock: a click's two threads launch these at once
    wp.load_module(device="cpu")
    return wp, maxflow, nlinks, assign, accumulate, tlinks, relabel




#: GrabCut's constants, as OpenCV has them: the smoothness weight, the weight of a sure pixel's terminal
#: link (9 gamma), and gamma / sqrt(2) on the diagonals, with sqrt(2) in single precision as OpenCV computes it.
GAMMA = 50.0
LAMBDA = 9.0 * GAMMA
GAMMA_DIAG = GAMMA / float(np.sqrt(np.float32(2.0)))


def _beta(bgr: np.ndarray) -> float:
    """1 / (2 mean |colour step|^2) over the left, up-left, up and up-right neighbours (0 on a flat image)."""
    x = bgr.astype(np.int64)
    h, w = x.shape[:2]
    total = int((((x[:, 1:] - x[:, :-1]) ** 2).sum()) + (((x[1:, 1:] - x[:-1, :-1]) ** 2).sum())
                + (((x[1:] - x[:-1]) ** 2).sum()) + (((x[1:, :-1] - x[:-1, 1:]) ** 2).sum()))
    if total <= 0:
        return 0.0
    return 1.0 / (2.0 * float(total) / (4 * w * h - 3 * w - 3 * h + 2))


def _inverse_and_det(c: list, fix: float) -> tuple[list, float]:
    """A 3x3 covariance's inverse (row-major, [r][c]) and determinant; a nearly singular one (det <= 1e-6)
    gets ``fix`` added to its diagonal first, in place, as OpenCV's GMM does."""
    det = c[0] * (c[4] * c[8] - c[5] * c[7]) - c[1] * (c[3] * c[8] - c[5] * c[6]) + c[2] * (c[3] * c[7] - c[4] * c[6])
    if det <= 1e-6 and fix > 0:
        c[0] += fix
        c[4] += fix
        c[8] += fix
        det = c[0] * (c[4] * c[8] - c[5] * c[7]) - c[1] * (c[3] * c[8] - c[5] * c[6]) + c[2] * (c[3] * c[7] - c[4] * c[6])
    if not det > np.finfo(np.float64).eps:  # what OpenCV asserts
        raise ValueError("a colour model's covariance is singular (GrabCut cannot go on)")
    r = 1.0 / det
    inv = [(c[4] * c[8] - c[5] * c[7]) * r, -(c[1] * c[8] - c[2] * c[7]) * r, (c[1] * c[5] - c[2] * c[4]) * r,
           -(c[3] * c[8] - c[5] * c[6]) * r, (c[0] * c[8] - c[2] * c[6]) * r, -(c[0] * c[5] - c[2] * c[3]) * r,
           (c[3] * c[7] - c[4] * c[6]) * r, -(c[0] * c[7] - c[1] * c[6]) * r, (c[0] * c[4] - c[1] * c[3]) * r]
    return inv, det


class GridCut:
    """A minimum s-t cut on an (h, w) pixel grid, 8-connected, that keeps its flow between solves.

    ``GridCut(right, down_right, down, down_left)``: the capacity (h, w) of the link from each pixel to its
    neighbour in that direction, the same both ways (a link that would leave the grid is ignored).
    ``solve(source, sink)``: each pixel's terminal capacities (h, w) for this solve; returns the pixels on the
    source side (bool (h, w)): the smallest minimum cut. A solve after the first starts from the flow the
    previous one left, with only the change of each pixel's terminal links added."""

    def __init__(self, right=None, down_right=None, down=None, down_left=None, *, shape=None):
        self.wp, self._maxflow, self._nlinks, self._assign, self._accumulate, self._tlinks, self._relabel = _build()
        wp = self.wp
        h, w = shape if shape is not None else np.shape(right)
        self.h, self.w = int(h), int(w)
        n = self.h * self.w
        dev = "cpu"
        i32, f64 = wp.int32, wp.float64
        self._dx = wp.array(np.array(DX, np.int32), dtype=i32, device=dev)
        self._dy = wp.array(np.array(DY, np.int32), dtype=i32, device=dev)
        if right is not None:
            cap = np.zeros((h, w, 8), np.float64)
            for d, link in ((0, right), (1, down_right), (2, down), (3, down_left)):
                link = np.asarray(link, np.float64)
                if link.shape != (h, w):
                    raise ValueError(f"every link array must have the shape {(h, w)}; got {link.shape}")
                ys, ys2 = slice(0, h - DY[d]), slice(DY[d], h)  # DY[d] >= 0 for the four forward links
                xs, xs2 = slice(max(0, -DX[d]), w - max(0, DX[d])), slice(max(0, DX[d]), w + min(0, DX[d]))
                cap[ys, xs, d] = link[ys, xs]
                cap[ys2, xs2, (d + 4) % 8] = link[ys, xs]  # the same link seen from the neighbour
            self._cap = wp.array(cap.reshape(-1), dtype=f64, device=dev)
        else:
            self._cap = wp.zeros(n * 8, dtype=f64, device=dev)
        self._tr = wp.zeros(n, dtype=f64, device=dev)  # residual terminal links: source minus sink
        self._last = wp.zeros(n, dtype=f64, device=dev)  # the terminal links (source minus sink) last solved
        self._parent = wp.zeros(n, dtype=i32, device=dev)
        self._pdir = wp.zeros(n, dtype=i32, device=dev)
        self._tree = wp.zeros(n, dtype=i32, device=dev)
        self._ts = wp.zeros(n, dtype=i32, device=dev)
        self._dist = wp.zeros(n, dtype=i32, device=dev)
        self._queue = wp.zeros(n + 1, dtype=i32, device=dev)
        self._inq = wp.zeros(n, dtype=i32, device=dev)
        self._orphans = wp.zeros(n + 1, dtype=i32, device=dev)
        self._flow = wp.zeros(1, dtype=f64, device=dev)
        self._solved = False

    def _run(self) -> None:
        self.wp.launch(self._maxflow, dim=1, device="cpu",
                       inputs=[self._cap, self._tr, self._parent, self._pdir, self._tree, self._ts, self._dist,
                               self._queue, self._inq, self._orphans, self._dx, self._dy, self.w, self.h, self._flow])
        self._solved = True

    def solve(self, source, sink) -> np.ndarray:
        diff = (np.asarray(source, np.float64) - np.asarray(sink, np.float64)).reshape(-1)
        if diff.size != self.h * self.w:
            raise ValueError(f"the terminal capacities must have the shape {(self.h, self.w)}")
        tr = self._tr.numpy()  # the Warp array's memory (CPU)
        last = self._last.numpy()
        if self._solved:
            tr += diff - last
        else:
            tr[:] = diff
        last[:] = diff
        self._run()
        self.wp.synchronize_device("cpu")
        return ((self._parent.numpy() != -1) & (self._tree.numpy() == 0)).reshape(self.h, self.w)

    @property
    def flow(self) -> float:
        """The flow pushed by all solves so far (the first solve's is its cut's cost)."""
        return float(self._flow.numpy()[0])


class GrabCutGraph(GridCut):
    """GrabCut's iterations on one image (BGR uint8, (h, w, 3)), with the max-flow kept between them.

    ``iterate(labels, bgd_model, fgd_model)`` is one iteration of OpenCV's ``cv2.grabCut`` in ``GC_EVAL``
    mode: ``labels`` (h, w) uint8 (``cv2.GC_BGD`` ... ``GC_PR_FGD``) and the two (1, 65) colour models are
    read and updated in place, with the same colour models (the same arithmetic: per Gaussian the pixels
    nearest by OpenCV's rule, integer sums, the same singular-covariance fix) and the same graph. The cut is
    the smallest minimum cut, where OpenCV's may be another one of the same cost (the labels then differ
    on a few pixels of a tie). Start the models with ``cv2.grabCut(..., iterCount=0, mode=GC_INIT_*)``
    (OpenCV's k-means); calls may change ``labels`` between iterations (new sure pixels)."""

    def __init__(self, bgr: np.ndarray):
        bgr = np.ascontiguousarray(bgr, dtype=np.uint8)
        if bgr.ndim != 3 or bgr.shape[2] != 3:
            raise ValueError(f"GrabCutGraph needs an (h, w, 3) uint8 image; got shape {bgr.shape}")
        super().__init__(shape=bgr.shape[:2])
        wp = self.wp
        self.bgr = bgr
        n = self.h * self.w
        self._img = wp.array(bgr.reshape(-1), dtype=wp.uint8, device="cpu")
        self._comp = wp.zeros(n, dtype=wp.int32, device="cpu")
        wp.launch(self._nlinks, dim=n, device="cpu", inputs=[self._img, self.w, self.h, _beta(bgr), GAMMA, GAMMA_DIAG,
                                                            self._dx, self._dy, self._cap])

    def _model_arrays(self, models: tuple) -> tuple:
        """Warp arrays of both colour models (background's 5 Gaussians, then the object's): weights, means,
        inverse covariances, determinants. The covariances as stored are used as they are (OpenCV's GMM
        constructor: no singular fix)."""
        coef, mean, inv, det = [], [], [], []
        for model in models:
            m = model.reshape(-1)
            for ci in range(5):
                coef.append(float(m[ci]))
                mean.extend(float(v) for v in m[5 + 3 * ci:8 + 3 * ci])
                if m[ci] > 0:
                    i, d = _inverse_and_det([float(v) for v in m[20 + 9 * ci:29 + 9 * ci]], 0.0)
                else:
                    i, d = [0.0] * 9, 1.0
                inv.extend(i)
                det.append(d)
        wp = self.wp
        return tuple(wp.array(np.array(a, np.float64), dtype=wp.float64, device="cpu") for a in (coef, mean, inv, det))

    def _learn(self, models: tuple) -> None:
        """OpenCV's learnGMMs: each model's Gaussians from the pixels assigned to them, written into the
        (1, 65) model arrays (weight, mean, covariance with the singular fix of 0.01)."""
        wp = self.wp
        stats = wp.zeros(10 * 13, dtype=wp.float64, device="cpu")
        wp.launch(self._accumulate, dim=1, device="cpu", inputs=[self._img, self._comp, self.h * self.w, stats])
        st = stats.numpy().reshape(2, 5, 13)
        for side, model in enumerate(models):
            m = model.reshape(-1)
            total = int(st[side, :, 0].sum())
            for ci in range(5):
                n = int(st[side, ci, 0])
                if n == 0:
                    m[ci] = 0.0
                    continue
                inv_n = 1.0 / n
                m[ci] = n / total
                mu = [float(st[side, ci, 1 + k]) * inv_n for k in range(3)]
                cov = [float(st[side, ci, 4 + 3 * r + c]) * inv_n - mu[r] * mu[c] for r in range(3) for c in range(3)]
                _inverse_and_det(cov, 0.01)  # applies the fix to ``cov`` where OpenCV does
                m[5 + 3 * ci:8 + 3 * ci] = mu
                m[20 + 9 * ci:29 + 9 * ci] = cov

    def iterate(self, labels: np.ndarray, bgd_model: np.ndarray, fgd_model: np.ndarray) -> None:
        """One GrabCut iteration (``GC_EVAL``): ``labels`` and the two models are updated in place."""
        wp = self.wp
        dev = "cpu"
        n = self.h * self.w
        if labels.shape != (self.h, self.w) or labels.dtype != np.uint8 or not labels.flags.c_contiguous:
            raise ValueError("labels must be a contiguous (h, w) uint8 array of the image's size")
        models = (bgd_model, fgd_model)
        lab = wp.array(labels.reshape(-1), dtype=wp.uint8, device=dev, copy=False)
        wp.launch(self._assign, dim=n, device=dev, inputs=[self._img, lab, *self._model_arrays(models), self._comp])
        self._learn(models)
        coef, mean, inv, det = self._model_arrays(models)
        wp.launch(self._tlinks, dim=n, device=dev,
                  inputs=[self._img, lab, coef, mean, inv, det, LAMBDA, 0 if self._solved else 1, self._last, self._tr])
        self._run()
        wp.launch(self._relabel, dim=n, device=dev, inputs=[self._parent, self._tree, lab])
        wp.synchronize_device(dev)
