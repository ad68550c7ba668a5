"""Photo-textured rendering: the surface the input camera saw shows the photo's own pixels as it moves.

The splats' colours are a low-resolution copy of the photo (one colour per splat), so a splat render of
frame 0 is visibly not the photo, and the object's detail is lost the moment it moves. Instead, every output
pixel asks which point of the object it shows, where that point was at rest (frame 0) and where the photo
shows it, and reads the photo there:

* A frame whose splats all go back to rest by one affine map x -> A x + b (a rigid body, a still frame:
  ``controls._one_map`` on ``controls._flow_maps``, A = R L_0 L_t^-1 Rᵀ of the deformation each splat follows,
  in camera coordinates) needs no channel for it: the rendered surface point (depth times the pixel's ray)
  taken back by the map, X_0 = A (depth · r) + b, projected through the camera that took the photo, is the
  photo coordinate. Exact.
* Otherwise (deforming material) each splat carries Δ_i, from where its centre is now to where the photo
  shows its centre at rest (photo pixels), composited like colour over the seen splats: the pixel p reads the
  photo at p + Σ w s Δ / Σ w s. Exact for translation; for deformation the interpolated displacement field is
  first order in the splat size (its error is the local strain times the distance from p to the blended
  centre, a fraction of a pixel). Two channels instead of the nine an exact 3D map needs
  (``controls._flow_features``), so the compiled compositor keeps its vectorised path: the texture costs
  little more than the splat render.
* The photo is sampled there bicubically (Keys' cubic, a = -0.75, at the exact coordinate; exact at frame 0: the
  maps are the identity and the coordinate is the pixel's own centre; a surface moved by a fraction of a pixel
  keeps its detail).
* Where the frame magnifies the photo (a surface the photo saw at a grazing angle, turned toward the camera: a few
  photo pixels would be stretched over many, the streaks of a spinning body's side), the photo's share fades to
  the splats' own colours: by the smallest singular value of the photo coordinates' Jacobian with respect to the
  pixel position (``PHOTO_STRETCH``), spread over a few pixels (``STRETCH_SPREAD``).
* The per-pixel passes (photo coordinates, stretch, sampling, blending) run compiled on the CPU
  (``_warp_shade``: Warp, the blend and stretch loops in C++), with their tensor twin in ``shade(compiled=False)``
  as the fallback; the two agree to float32 round-off.
* Which splats the photo saw ("seen", per Gaussian, in [0, 1]) comes from a depth test in the input view at
  rest (``seen_weights``): a splat whose centre lies on the rendered front surface was photographed, one
  behind it (the back, a hidden side, the inside a tear opens) was not. It is composited as a channel too
  (and the Δ channels are weighted by it, so the photo coordinate comes from seen splats only); a pixel
  shows the photo in proportion to the seen splats' share of it and the splats' own colours for the rest,
  so photo and Gaussian colours meet across the splats' own soft footprints, with no seam.
* Coverage follows the photo's matte for the seen part: alpha = s·m(uv_0) + (1 − s)·alpha_splats, and the
  photo's colour is its premultiplied foreground (the matting equation solved with the inpainted background,
  ``make_photo_texture``), so frame 0 composited over that background is the photo itself, soft edge included.
  Well inside the splats' silhouette their own coverage is a floor (no hole where a rim turned toward the camera
  reads the matte's edge, ``INTERIOR_PX``), except where the photo coordinate lies outside the matte
  (``OUTSIDE_PX``): a notch narrower than the splats stays open.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..types.camera import Camera
from ..types.gaussians import Gaussians

#: Below this share of splat coverage a pixel's photo coordinate is unreliable (a far splat tail): the photo's
#: weight ramps in linearly up to it.
MIN_COVERAGE = 0.02

#: Where the frame magnifies the photo (its photo coordinates' Jacobian with respect to the pixel position has a
#: smallest singular value under 1 / PHOTO_STRETCH[0]: a surface the photo saw at a grazing angle, turned toward the
#: camera, which the photo holds in a few pixels stretched over many), the photo's share fades to the splats' own
#: colours, wholly at PHOTO_STRETCH[1]: stretched further, the photo's pixels would streak across the surface.
PHOTO_STRETCH = (1.5, 3.0)

#: The stretch fade is spread over this many pixels (the least weight about each pixel): with one rigid map the
#: photo coordinate follows the splats' blended depth, constant over each splat's core, so a surface the photo saw
#: at a grazing angle comes out as splat-sized plateaus of nearly one photo coordinate (the streaks) with steps
#: between them; the fade catches the plateaus, and spread, the steps too.
STRETCH_SPREAD = 3

#: The splats the photo did not see show their own colours low-passed in 3D: averaged over a box of (2
#: UNSEEN_BLUR_CELLS + 1)³ cells of one particle spacing. A lift colours those splats from the photo pixel they
#: project to (the silhouette lift's whole depth column takes that pixel's colour), so a side or back turned into view
#: shows the photo's detail drawn out along the old viewing direction: the streaky seam of a spinning body.
UNSEEN_BLUR_CELLS = 1

#: The splats' coverage is a floor from INTERIOR_PX[1] px inside their silhouette (none within INTERIOR_PX[0]).
INTERIOR_PX = (1.5, 3.5)

#: ... but only where the pixel's photo coordinate lies within OUTSIDE_PX[0] px of the photo's matte (m >= 0.5), and
#: not at all from OUTSIDE_PX[1] px beyond it: there the splats' coverage is their own overshoot past the object's
#: outline at rest (a notch in the outline narrower than the splats, the gap under a horse's jaw or between its
#: legs, comes out filled in the splat render), which the photo says is background, frame 0 included.
OUTSIDE_PX = (1.5, 3.0)

#: Largest photo-coordinate error (px) accepted from reading a frame's motion back to rest as one rigid map.
ONE_MAP_TOLERANCE_PX = 0.01

#: The seen test renders the rest pose at most this long side (it compares depths, which are smooth).
SEEN_MAX_SIDE = 320


@dataclass
class PhotoTexture:
    """The photo as a texture: ``premult`` (H,W,3) its premultiplied foreground, ``matte`` (H,W) the object's
    soft coverage, ``camera`` the camera that took it (the lift's input camera: the Gaussians line up with the
    photo through it), ``seen`` (N,) per-Gaussian seen weights once computed (``seen_weights``)."""

    premult: torch.Tensor
    matte: torch.Tensor
    camera: Camera
    seen: Optional[torch.Tensor] = None

    @property
    def height(self) -> int:
        return int(self.matte.shape[0])

    @property
    def width(self) -> int:
        return int(self.matte.shape[1])


def _as_hw3(x: torch.Tensor, what: str) -> torch.Tensor:
    x = torch.as_tensor(x)
    if x.ndim == 4 and x.shape[0] == 1:
        x = x[0]
    if x.ndim != 3 or x.shape[-1] < 3:
        raise InputError(f"the {what} must be one image (H,W,3); got shape {tuple(x.shape)}")
    return x[..., :3].detach().float().cpu()


def make_photo_texture(photo: torch.Tensor, matte: torch.Tensor, camera: Camera,
                       background: Optional[torch.Tensor] = None) -> PhotoTexture:
    """The texture of ``photo`` (H,W,3 in 0..1) for the object covered by ``matte`` (H,W, soft or hard).

    With the ``background`` the object was cut from (the inpainted one it will be composited over), the
    foreground is unmixed by the matting equation, I = m F + (1 − m) B, so a soft edge pixel keeps only the
    object's share of its colour and frame 0 composited over B gives back I exactly; without it the photo's
    colours are taken as they are (I m)."""
    img = _as_hw3(photo, "photo")
    m = torch.as_tensor(matte).detach().float().cpu()
    if m.ndim == 3 and m.shape[0] == 1:
        m = m[0]
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(img.shape[:2]):
        raise InputError(f"the matte {tuple(m.shape)} does not match the photo {tuple(img.shape[:2])}: give the "
                         "object's mask at the photo's size")
    if (camera.width, camera.height) != (img.shape[1], img.shape[0]):
        camera = camera.resized(int(img.shape[1]), int(img.shape[0]))
    m = m.clamp(0.0, 1.0)
    if background is not None:
        bg = _as_hw3(background, "background")
        if bg.shape != img.shape:
            bg = torch.nn.functional.interpolate(bg.permute(2, 0, 1)[None], size=tuple(img.shape[:2]),
                                                 mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
        premult = torch.minimum((img - (1.0 - m)[..., None] * bg).clamp_min(0.0), m[..., None].expand_as(img))
    else:
        premult = img * m[..., None]
    return PhotoTexture(premult=premult.contiguous(), matte=m.contiguous(), camera=camera)


def seen_weights(gaussians: Gaussians, camera: Camera, *, backend: str = "auto") -> torch.Tensor:
    """(N,) in [0, 1]: how surely the camera that took the photo saw each Gaussian (its rest pose).

    A depth test against the rest render in that view, for any lift: the splat's centre, projected, must land
    on the object (alpha > 0.3) and lie no deeper than the rendered (expected) depth there plus a tolerance
    of its own depth extent (2 σ along the ray) and 1 % of the depth; the weight falls to 0 over as much
    again. The front surface of a silhouette lift, LGM's visible splats and a fitted GAUSSIAN's front all pass;
    the back, hidden sides and the inside do not."""
    from .rasterize import rasterize

    g = gaussians.to("cpu") if gaussians.means.device.type != "cpu" else gaussians
    n = g.means.shape[0]
    if n == 0:
        return torch.zeros(0)
    if max(camera.width, camera.height) > SEEN_MAX_SIDE:  # the depth test needs no more: a quarter of the pixels
        f = SEEN_MAX_SIDE / max(camera.width, camera.height)
        camera = camera.resized(max(1, round(camera.width * f)), max(1, round(camera.height * f)))
    with torch.no_grad():
        out = rasterize(g, camera, backend=backend)
        D, A = out.depth.float(), out.alpha.float()
        w2c = camera.w2c_opencv().double()
        R = w2c[:3, :3]
        mc = g.means.double() @ R.T + w2c[:3, 3]
        z = mc[:, 2]
        u = camera.fx * mc[:, 0] / z.clamp_min(1e-9) + camera.cx
        v = camera.fy * mc[:, 1] / z.clamp_min(1e-9) + camera.cy
        H, W = D.shape
        ix, iy = torch.floor(u).long(), torch.floor(v).long()
        inside = (z > camera.near) & (ix >= 0) & (ix < W) & (iy >= 0) & (iy < H)
        ixc, iyc = ix.clamp(0, W - 1), iy.clamp(0, H - 1)
        # The farthest covered depth over the 3x3 pixels (lenient at grazing angles and edges), and coverage.
        Dp = torch.nn.functional.pad(torch.where(A > 0.3, D, torch.zeros_like(D))[None, None], (1, 1, 1, 1))
        Dmax = torch.nn.functional.max_pool2d(Dp, 3, stride=1)[0, 0]
        d_front = Dmax[iyc, ixc].double()
        covered = A[iyc, ixc] > 0.3
        cov = g.covariance().double()
        sig_z = torch.einsum("i,nij,j->n", R[2], cov, R[2]).clamp_min(0).sqrt()
        tol = 2.0 * sig_z + 0.01 * d_front
        s = (1.0 - (z - d_front - tol) / tol.clamp_min(1e-9)).clamp(0.0, 1.0)
        s = torch.where(inside & covered & (d_front > 0), s, torch.zeros_like(s))
    return s.float()


def smoothed_colours(means: torch.Tensor, rgb: torch.Tensor, cell: float, half: int = 1) -> torch.Tensor:
    """(N,3): the splats' colours low-passed in 3D: averaged over the (2 ``half`` + 1)³ cells of side ``cell`` about
    each cell (a box filter on a grid of the positions ``means``; at most 2²² cells, coarser when the grid would
    exceed that), read at each splat's position by trilinear interpolation between the cell centres (so the
    colours vary smoothly, without the cells' blocks)."""
    x = means.double()
    lo = x.min(0).values
    ext = (x.max(0).values - lo).clamp_min(1e-12)
    cell = max(float(cell), float(ext.max()) / 256.0, 1e-9)
    while float(torch.prod(torch.floor(ext / cell) + 2 + 2 * half)) > 2 ** 22:
        cell *= 1.25
    f = (x - lo) / cell + half  # cell k's centre at k (cells centred on lo + (k - half) cell)
    idx = torch.floor(f + 0.5).long()
    dims = [int(d) for d in (idx.max(0).values + 2 + half).tolist()]
    flat = (idx[:, 0] * dims[1] + idx[:, 1]) * dims[2] + idx[:, 2]
    grid = torch.zeros(dims[0] * dims[1] * dims[2], 4, dtype=torch.float32)
    grid.index_add_(0, flat, torch.cat([rgb.float(), torch.ones(rgb.shape[0], 1)], 1))
    vol = grid.view(dims[0], dims[1], dims[2], 4).permute(3, 0, 1, 2)[None]
    k = 2 * half + 1
    box = torch.nn.functional.avg_pool3d(vol, k, stride=1, padding=half)[0]  # the same scale for sums and counts
    box = box.permute(1, 2, 3, 0).reshape(-1, 4)
    base = torch.floor(f).long()
    t = (f - base).float()
    acc = torch.zeros(x.shape[0], 4)
    for c in range(8):
        o = [(c >> 2) & 1, (c >> 1) & 1, c & 1]
        wgt = torch.ones(x.shape[0])
        for ax in range(3):
            wgt = wgt * (t[:, ax] if o[ax] else 1.0 - t[:, ax])
        ci = ((base[:, 0] + o[0]) * dims[1] + base[:, 1] + o[1]) * dims[2] + base[:, 2] + o[2]
        acc += wgt[:, None] * box[ci]
    return acc[:, :3] / acc[:, 3:].clamp_min(1e-12)


def texture_features(seen: torch.Tensor, shift: Optional[torch.Tensor]) -> torch.Tensor:
    """The per-Gaussian channels a textured frame composites: s·Δ (2, when each splat has its own map: Δ from
    where its centre is now to where the photo shows it, in photo pixels) and s."""
    s = seen.reshape(-1, 1)
    return s if shift is None else torch.cat([shift * s.to(shift.dtype), s.to(shift.dtype)], 1)


def _to_photo_camera(camera: Camera, photo_camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """(M, c): the render camera's coordinates to the photo camera's, X_p = M X + c (OpenCV axes, float64)."""
    a = camera.w2c_opencv().double()
    b = photo_camera.w2c_opencv().double()
    M = b[:3, :3] @ a[:3, :3].T
    return M, b[:3, 3] - M @ a[:3, 3]


def _render_to_photo_px(camera: Camera, photo_camera: Camera, r: torch.Tensor):
    """The photo-camera pixel coordinates of the render pixels whose rays are ``r`` (…,3), for a render camera that
    is the photo's camera (possibly resized): its intrinsics applied to the ray."""
    return photo_camera.fx * r[..., 0] + photo_camera.cx, photo_camera.fy * r[..., 1] + photo_camera.cy


def _texture_planes(texture: PhotoTexture) -> np.ndarray:
    """(H,W,4) float32: premultiplied colour and matte as one image (made once per texture)."""
    planes = texture.__dict__.get("_planes")
    if planes is None:
        planes = torch.cat([texture.premult, texture.matte[..., None]], -1).contiguous().numpy()
        texture.__dict__["_planes"] = planes
    return planes


def _outside_px(texture: PhotoTexture) -> torch.Tensor:
    """(H,W) float32: each photo pixel's distance (px) to the nearest pixel of the object (matte >= 0.5), 0 on it
    (made once per texture)."""
    out = texture.__dict__.get("_outside")
    if out is None:
        import cv2

        off = (texture.matte.float().cpu().numpy() < 0.5).astype(np.uint8)
        out = torch.from_numpy(cv2.distanceTransform(off, cv2.DIST_L2, 3).astype(np.float32))
        if not bool((off == 0).any()):
            out.fill_(float("inf"))  # no object in the matte: everything is far outside it
        texture.__dict__["_outside"] = out
    return out


def _floor_outside(dist: torch.Tensor, texture: PhotoTexture, u: torch.Tensor, v: torch.Tensor,
                   ok: torch.Tensor) -> torch.Tensor:
    """``dist`` (the splats' interior distance, (bh,bw)) lowered so that the coverage floor fades out where the
    pixel's photo coordinate (u, v) lies outside the photo's matte, by OUTSIDE_PX: the floor's ramp becomes the
    smaller of its own and the one of the distance outside."""
    out = _outside_px(texture)
    PH, PW = out.shape
    shape = dist.shape
    ix = torch.floor(u.reshape(shape)).clamp(0, PW - 1).long()
    iy = torch.floor(v.reshape(shape)).clamp(0, PH - 1).long()
    d = out[iy, ix]
    near = 1.0 - ((d - OUTSIDE_PX[0]) / (OUTSIDE_PX[1] - OUTSIDE_PX[0])).clamp(0.0, 1.0)
    cap = INTERIOR_PX[0] + (INTERIOR_PX[1] - INTERIOR_PX[0]) * near
    return torch.where(ok.reshape(shape).bool(), torch.minimum(dist, cap.float()), dist)


def _keys_weights(t: torch.Tensor) -> list:
    """Keys' cubic convolution weights (a = -0.75, OpenCV's bicubic) of the taps at -1, 0, 1, 2 for fractions
    ``t`` in [0, 1) (float32, in ``_warp_shade.keys``' order of operations)."""
    a = -0.75
    s = t + 1.0
    w0 = ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a
    w1 = ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0
    r = 1.0 - t
    w2 = ((a + 2.0) * r - (a + 3.0)) * r * r + 1.0
    return [w0, w1, w2, 1.0 - w0 - w1 - w2]


def _bicubic(planes: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """(…,4): ``planes`` (H,W,4) sampled at photo coordinates (u, v) (pixel centres at +0.5, float64) with Keys'
    cubic; taps outside the photo read 0."""
    PH, PW = planes.shape[:2]
    mx, my = u - 0.5, v - 0.5
    fx, fy = torch.floor(mx), torch.floor(my)
    inside = (fx > -3.0) & (fx < PW + 1) & (fy > -3.0) & (fy < PH + 1)
    wx = _keys_weights((mx - fx).float())
    wy = _keys_weights((my - fy).float())
    ix = fx.clamp(-3.0, PW + 1).long()
    iy = fy.clamp(-3.0, PH + 1).long()
    flat = planes.reshape(-1, 4)
    out = torch.zeros(u.shape + (4,), dtype=torch.float32)
    for j in range(4):
        yy = iy - 1 + j
        oky = (yy >= 0) & (yy < PH) & inside
        row = torch.zeros_like(out)
        for k in range(4):
            xx = ix - 1 + k
            ok = oky & (xx >= 0) & (xx < PW)
            tap = flat[(yy.clamp(0, PH - 1) * PW + xx.clamp(0, PW - 1)).reshape(-1)].reshape(out.shape)
            row = row + torch.where(ok[..., None], wx[k][..., None] * tap, torch.zeros_like(tap))
        out = out + wy[j][..., None] * row
    return out


def _derivative(c: torch.Tensor, ok: torch.Tensor, dim: int) -> torch.Tensor:
    """d c / d (pixel) along ``dim`` (0: rows, 1: columns) of a box of photo coordinates ``c`` (float64): central
    where both neighbours have coordinates (``ok``), one-sided where one has, nan where none (``_warp_shade``)."""
    n = c.shape[dim]
    pad = [(0, 0), (0, 0)]
    pad[dim] = (1, 1)
    flat_pad = [p for pr in reversed(pad) for p in pr]
    cp = torch.nn.functional.pad(c[None], flat_pad, mode="replicate")[0]
    okp = torch.nn.functional.pad(ok[None].float(), flat_pad)[0] > 0
    lo_c, hi_c = cp.narrow(dim, 0, n), cp.narrow(dim, 2, n)
    lo, hi = okp.narrow(dim, 0, n), okp.narrow(dim, 2, n)
    nan = torch.full_like(c, float("nan"))
    return torch.where(lo & hi, (hi_c - lo_c) * 0.5, torch.where(hi, hi_c - c, torch.where(lo, c - lo_c, nan)))


def _stretch_fade(u: torch.Tensor, v: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """(bh,bw) float32: the photo's weight left where the frame magnifies the photo coordinates (``PHOTO_STRETCH``):
    1 up to PHOTO_STRETCH[0], 0 from PHOTO_STRETCH[1], linear in the magnification between; 1 where a pixel has no
    coordinate (tensor twin of ``_warp_shade.stretch_fade``)."""
    ux, vx = _derivative(u, ok, 1), _derivative(v, ok, 1)
    uy, vy = _derivative(u, ok, 0), _derivative(v, ok, 0)
    nx, ny = torch.isnan(ux), torch.isnan(uy)
    ux, vx = torch.where(nx, 1.0, ux), torch.where(nx, 0.0, vx)
    uy, vy = torch.where(ny, 0.0, uy), torch.where(ny, 1.0, vy)
    E = ux * ux + vx * vx + uy * uy + vy * vy
    D = (ux * vy - uy * vx).abs()
    smin2 = 0.5 * (E - (E * E - 4.0 * D * D).clamp_min(0.0).sqrt())
    st0, st1 = PHOTO_STRETCH
    fade = ((st1 - 1.0 / smin2.sqrt()) / (st1 - st0)).clamp(max=1.0)
    fade = torch.where(smin2 * st0 * st0 < 1.0, fade, torch.ones_like(fade))
    fade = torch.where(smin2 * st1 * st1 < 1.0, torch.zeros_like(fade), fade)
    return torch.where(ok, fade, torch.ones_like(fade)).float()


def _spread_fade(fade: torch.Tensor) -> torch.Tensor:
    """The stretch fade spread over STRETCH_SPREAD px (its minimum over the square about each pixel)."""
    if STRETCH_SPREAD <= 0:
        return fade
    import cv2

    k = np.ones((2 * STRETCH_SPREAD + 1, 2 * STRETCH_SPREAD + 1), np.uint8)
    return torch.from_numpy(cv2.erode(fade.numpy(), k, borderType=cv2.BORDER_REPLICATE))


def _photo_coords(extra: torch.Tensor, depth: torch.Tensor, box: tuple, camera: Camera, pc: Camera, one_map):
    """Tensor twin of ``_warp_shade.photo_coords``: (u, v) float64 and ok (bh,bw) of the box's pixels."""
    y0, y1, x0, x1 = box
    S = extra[y0:y1, x0:x1, -1]
    ok = S > 1e-6
    rx = ((torch.arange(x0, x1, dtype=torch.float64) + 0.5 - camera.cx) / camera.fx)[None, :]
    ry = ((torch.arange(y0, y1, dtype=torch.float64) + 0.5 - camera.cy) / camera.fy)[:, None]
    if one_map is not None:
        A, b = one_map
        d = depth[y0:y1, x0:x1].double()
        X = d * (A[0, 0] * rx + A[0, 1] * ry + A[0, 2]) + b[0]
        Y = d * (A[1, 0] * rx + A[1, 1] * ry + A[1, 2]) + b[1]
        Z = d * (A[2, 0] * rx + A[2, 1] * ry + A[2, 2]) + b[2]
        front = Z > 1e-9
        ok = ok & front
        Zs = torch.where(front, Z, torch.ones_like(Z))
        u = torch.where(ok, pc.fx * X / Zs + pc.cx, torch.zeros_like(Z))
        v = torch.where(ok, pc.fy * Y / Zs + pc.cy, torch.zeros_like(Z))
    else:
        Sd = torch.where(ok, S, torch.ones_like(S)).double()
        u = torch.where(ok, pc.fx * rx + pc.cx + extra[y0:y1, x0:x1, 0].double() / Sd, 0.0)
        v = torch.where(ok, pc.fy * ry + pc.cy + extra[y0:y1, x0:x1, 1].double() / Sd, 0.0)
    return u, v, ok


def shade(texture: PhotoTexture, camera: Camera, rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor,
          extra: torch.Tensor, one_map=None, into: Optional[tuple] = None,
          compiled: Optional[bool] = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A frame's premultiplied colour and alpha with the photo texture: ``rgb``, ``alpha``, ``depth`` the splat
    render (H,W[,3]), ``extra`` its composited ``texture_features`` (H,W,1 or 3), ``one_map`` (A, b) when every
    splat goes back to rest by that one map (then ``extra`` holds s only). Written into ``into`` (colour, alpha
    tensors of the frame's shape, contiguous) when given, else into new tensors; returned (CPU, float32).

    ``compiled``: the per-pixel passes compiled (``_warp_shade``; None: when Warp is available) or as tensor
    operations (False); the two agree to float32 round-off."""
    rgb, alpha = rgb.float().cpu().contiguous(), alpha.float().cpu().contiguous()
    extra, depth = extra.float().cpu().contiguous(), depth.float().cpu().contiguous()
    if into is None:
        out_rgb, out_a = rgb.clone(), alpha.clone()
    else:
        out_rgb, out_a = into
        out_rgb.copy_(rgb)
        out_a.copy_(alpha)
    if compiled is None:
        from . import _warp_shade

        compiled = _warp_shade.available()
    # The box of the pixels the seen splats reach (S > 1e-6): every pass below works in it. (A compiled pass over
    # the rows took as long, 0.42 against 0.45 ms at 640x360: reading the frame's channels is the cost.)
    S = extra[..., -1]
    has = S > 1e-6
    rows, cols = has.any(1).nonzero(), has.any(0).nonzero()
    if rows.numel() == 0:
        return out_rgb, out_a
    box = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)
    y0, y1, x0, x1 = box
    pc = texture.camera
    photo_map = None
    if one_map is not None:  # the render camera's surface point -> rest -> the photo camera's coordinates
        A0, b0 = one_map
        M, c = _to_photo_camera(camera, pc)
        photo_map = (M @ A0.double(), M @ b0.double() + c)
    import cv2

    a = alpha[y0:y1, x0:x1]
    # The splats' interior: distance (px) inside their silhouette, for the coverage floor (INTERIOR_PX).
    dist = torch.from_numpy(cv2.distanceTransform((a > 0.5).numpy().astype(np.uint8), cv2.DIST_L2, 3))
    if compiled:
        from . import _warp_shade

        u, v, ok = _warp_shade.photo_coords(extra, depth, box, camera, pc, photo_map)
        dist = _floor_outside(dist, texture, u, v, ok).contiguous()
        fade = _spread_fade(_warp_shade.stretch_fade(u, v, ok, box, PHOTO_STRETCH[0], PHOTO_STRETCH[1]))
        planes = _texture_planes(texture)
        pw = texture.__dict__.get("_planes_wp")
        if pw is None:
            pw = texture.__dict__["_planes_wp"] = _warp_shade.planes_array(planes)
        if out_rgb.is_contiguous() and out_a.is_contiguous():
            _warp_shade.blend(u, v, ok, fade, extra, rgb, alpha, dist, box, planes, pw,
                              (MIN_COVERAGE, INTERIOR_PX[0], INTERIOR_PX[1]), out_rgb, out_a)
            return out_rgb, out_a
        tmp_rgb, tmp_a = rgb.clone(), alpha.clone()
        _warp_shade.blend(u, v, ok, fade, extra, rgb, alpha, dist, box, planes, pw,
                          (MIN_COVERAGE, INTERIOR_PX[0], INTERIOR_PX[1]), tmp_rgb, tmp_a)
        out_rgb.copy_(tmp_rgb)
        out_a.copy_(tmp_a)
        return out_rgb, out_a
    u, v, ok = _photo_coords(extra, depth, box, camera, pc, photo_map)
    dist = _floor_outside(dist, texture, u, v, ok)
    ok_box = ok.reshape(y1 - y0, x1 - x0)
    u, v = u.reshape(ok_box.shape), v.reshape(ok_box.shape)
    Sb = S[y0:y1, x0:x1]
    # The photo's share of the pixel: the seen splats' share of its coverage, ramped in over faint tails, faded
    # out where the photo is stretched past what it resolved.
    w = (Sb / a.clamp_min(1e-12)).clamp(0.0, 1.0) * (a * (1.0 / MIN_COVERAGE)).clamp(0.0, 1.0)
    w = w * _spread_fade(_stretch_fade(u, v, ok_box))
    w = torch.where(ok_box, w, torch.zeros_like(w))
    # Bicubic (Keys): a surface moved by a fraction of a pixel keeps its detail (bilinear sampling halves the
    # high-pass energy at half-pixel offsets: 0.60 of the photo's over a jelly's clip against 0.90,
    # docs/quality.md); its overshoot is clamped (coverage to 0..1, premultiplied colour to 0..coverage).
    smp = _bicubic(torch.from_numpy(_texture_planes(texture)), u, v)
    smp = torch.where(ok_box[..., None], smp, torch.zeros_like(smp))
    m_s = smp[..., 3].clamp(0.0, 1.0)
    col = torch.minimum(smp[..., :3].clamp(min=0.0), m_s[..., None])
    keep = 1.0 - w
    alpha_m = w * m_s + keep * a
    # Coverage follows the photo's matte (so frame 0 is the photo, soft edge included, and edges stay crisp in
    # motion), but never opens a hole well inside the splats' own silhouette (a photo coordinate at the matte's
    # edge there, e.g. a rim turned toward the camera): from INTERIOR_PX px inside it the splats' coverage is a
    # floor, the difference filled with their colour.
    floor = a * ((dist - INTERIOR_PX[0]) / (INTERIOR_PX[1] - INTERIOR_PX[0])).clamp(0.0, 1.0)
    ex = (floor - alpha_m).clamp(min=0.0)
    rgb_b = rgb[y0:y1, x0:x1]
    out_a[y0:y1, x0:x1] = alpha_m + ex
    g = ex / a.clamp_min(1e-6)
    out_rgb[y0:y1, x0:x1] = w[..., None] * col + keep[..., None] * rgb_b + g[..., None] * rgb_b
    return out_rgb, out_a


class TexturedPoser:
    """Per frame of a simulation: the texture channels for the rasterizer and, after it, the shaded frame.

    Holds the rest pose (frame 0) and its deformation, computed once per renderer."""

    def __init__(self, sim, camera: Camera, texture: PhotoTexture, backend: str = "auto"):
        from ..controls import _splat_linear_part

        self.sim, self.camera, self.texture = sim, camera, texture
        g0 = sim.gaussians_at(0)
        self.rest_gaussians = g0  # frame 0 posed: the renderer draws it from here instead of posing it again
        if texture.seen is None or texture.seen.shape[0] != g0.means.shape[0]:
            texture.seen = seen_weights(g0, texture.camera, backend=backend)
        self.seen = texture.seen
        self.w2c = camera.w2c_opencv().double()
        self.mu0 = g0.means.double()
        self.L0 = _splat_linear_part(sim, 0)
        self._bound = None
        self._seen64 = None  # the seen weights in float64 (features), and the rest pose in the render camera
        self._rest_cam = None  # (_one_map), made on first use
        self._use_compiled = None  # whether features() takes the compiled loop (``_compiled``)
        # Where the photo shows each splat's centre at rest (photo pixels).
        pw = texture.camera.w2c_opencv().double()
        mc = self.mu0 @ pw[:3, :3].T + pw[:3, 3]
        z = mc[:, 2].clamp_min(1e-9)
        pc = texture.camera
        self.uv0 = torch.stack([pc.fx * mc[:, 0] / z + pc.cx, pc.fy * mc[:, 1] / z + pc.cy], 1)
        # The splats' colours for the render: their own where the photo saw them, low-passed where it did not
        # (UNSEEN_BLUR_CELLS).
        rgb = g0.rgb.float()
        self.colors = rgb
        if UNSEEN_BLUR_CELLS > 0 and bool((self.seen < 1.0).any()):
            spacing = (sim.stats or {}).get("particle_spacing") if hasattr(sim, "stats") else None
            if not spacing:
                spacing = 4.0 * float(g0.scales.max(1).values.median()) if g0.scales.numel() else 0.0
            if spacing and spacing > 0:
                blur = smoothed_colours(g0.means, rgb, float(spacing), UNSEEN_BLUR_CELLS)
                s = self.seen.float().clamp(0.0, 1.0)[:, None]
                self.colors = s * rgb + (1.0 - s) * blur

    def features(self, frame: int, g: Gaussians):
        """(extra_features for ``rasterize``, one_map or None) of frame ``frame`` posed as ``g``."""
        from .. import controls as C

        R, t = self.w2c[:3, :3], self.w2c[:3, 3]
        one, ms = None, None
        if C.ONE_MAP_FLOW and not self._clearly_deformed(frame):
            ms = torch.addmm(t, g.means.double(), R.T)  # the centres now, render-camera coordinates
            one = self._one_map(frame, ms)
        if one is None and g.means.device.type == "cpu" and g.means.dtype == torch.float32 and self._compiled():
            from . import _warp_shade

            return _warp_shade.texture_shift_features(g.means, self.w2c, self.texture.camera, self.uv0,
                                                      self.seen).to(g.means.dtype), None
        shift = None
        if one is None:
            if ms is None:
                ms = torch.addmm(t, g.means.double(), R.T)
            r = ms[:, :2] / ms[:, 2:].clamp_min(1e-9)  # the rays' x/z, y/z (their z = 1 is not needed)
            px, py = _render_to_photo_px(self.camera, self.texture.camera, r)
            shift = self.uv0 - torch.stack([px, py], 1)
        if self._seen64 is None:
            self._seen64 = self.seen.to(torch.float64)
        return texture_features(self._seen64, shift).to(g.means.dtype).to(g.means.device), one

    def _compiled(self) -> bool:
        """Whether the per-splat channels are computed compiled (``_warp_shade.texture_shift_features``; the tensor
        operations below are its twin, for a Warp that is unavailable)."""
        if self._use_compiled is None:
            from . import _warp_shade

            self._use_compiled = _warp_shade.available()
        return self._use_compiled

    def _clearly_deformed(self, frame: int) -> bool:
        """Whether the particles' deformation gradients at ``frame`` differ from one another by more than 0.1 %
        (relative), so no single map can take every splat back to rest (``controls._one_map``'s test fails by
        orders of magnitude): then the per-splat displacement channels are used and no per-splat map is formed.
        A frame that passes is tested exactly."""
        if self._bound is None:
            self._bound = torch.unique(self.sim.binding)
        F = self.sim.F[frame][self._bound]
        if F.shape[0] == 0:
            return False
        mean = F.mean(0)
        spread = float((F - mean).flatten(1).abs().amax())
        return spread > 1e-3 * max(float(mean.abs().amax()), 1e-12)

    def _one_map(self, frame: int, ms: torch.Tensor):
        """``controls._one_map`` for a frame whose particles share one deformation (``_clearly_deformed`` is
        false), without forming a 3x3 map per splat: the particles' maps back to rest (P of them) and each
        splat's offset b = its rest centre - A its centre now, both in camera coordinates; (A, b) when they agree
        to ``ONE_MAP_TOLERANCE_PX`` px (the photo coordinate needs no better), else None."""
        from .. import controls as C

        b_idx = self._bound
        L = C._splat_linear_part(self.sim, frame)[b_idx]
        R = self.w2c[:3, :3]
        if self._rest_cam is None:  # the bound particles' rest deformation and the rest centres (camera coordinates)
            self._rest_cam = (self.L0[b_idx], torch.addmm(self.w2c[:3, 3], self.mu0, R.T))
        L0, m0 = self._rest_cam
        # The maps in world axes, B_p = L0 L^-1; in camera axes A_p = R B_p Rᵀ, whose mean is R B̄ Rᵀ and whose
        # spread has the same (Frobenius) norms: the camera's rotation is applied to the mean only.
        B_p = L0 @ C._inverse(L)
        B0 = B_p.mean(0)
        dA = float((B_p - B0).flatten(1).norm(dim=1).max())
        A0 = R @ B0 @ R.T
        b = m0 - ms @ A0.T
        b0 = b.mean(0)
        db = float((b - b0).norm(dim=1).max())
        z = ms[:, 2]
        near = float(z[z > 0].min()) if bool((z > 0).any()) else 0.0
        if near <= 0.0:
            return None
        err_px = max(self.camera.fx, self.camera.fy) / near * (dA * float(ms.norm(dim=1).max()) + db)
        return (A0, b0) if err_px <= ONE_MAP_TOLERANCE_PX else None

    def shade(self, out, one, into: Optional[tuple] = None) -> tuple[torch.Tensor, torch.Tensor]:
        return shade(self.texture, self.camera, out.rgb, out.alpha, out.depth, out.extra, one, into)


def photo_texture_for(sim, camera: Camera, photo: torch.Tensor, matte: Optional[torch.Tensor] = None,
                      background: Optional[torch.Tensor] = None, *, backend: str = "auto") -> PhotoTexture:
    """The texture for rendering ``sim``, from the photo its Gaussians were lifted from (one IMAGE, (H,W,3) or
    (1,H,W,3)) and ``camera`` (the lift's input camera). Without a ``matte`` (the object's mask), the object is
    where the rest pose renders through that camera (alpha, taken as the matte): fine for a fitted lift, softer
    than the segmentation's own edge."""
    img = _as_hw3(photo, "photo")
    cam = camera if (camera.width, camera.height) == (img.shape[1], img.shape[0]) else camera.resized(
        int(img.shape[1]), int(img.shape[0]))
    if matte is None:
        from .rasterize import rasterize

        with torch.no_grad():
            matte = rasterize(sim.gaussians_at(0).to("cpu"), cam, backend=backend).alpha.float()
        matte = ((matte - 0.5) * 4.0 + 0.5).clamp(0.0, 1.0)  # the rendered coverage, its faint tails cut
    else:
        matte = torch.as_tensor(matte).float()
        if matte.ndim == 3:
            matte = matte[0]
        if tuple(matte.shape) != tuple(img.shape[:2]):
            matte = torch.nn.functional.interpolate(matte[None, None], size=tuple(img.shape[:2]), mode="bilinear",
                                                    align_corners=False)[0, 0]
    return make_photo_texture(img, matte, cam, background=background)
