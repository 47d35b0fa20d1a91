"""Vectorised ray casting of textured quads (numpy, float32, CPU).

Camera convention: pinhole, optical frame C (x right, y down, z forward); pixel (u, v) with integer
coordinates at pixel centres sees the ray ``d_C = [(u - cx) / fx, (v - cy) / fy, 1]``, so a hit at
ray parameter z is the point ``z * d_C`` whose z-depth is z. Poses are ``T_WC`` (camera-to-world,
4x4). For every quad the analytic ray-plane intersection is evaluated only on the pixels of the
screen bounding box of the quad (clipped against the near plane), which is separable in u and v:
``n_C . d_C = n_x x_u + n_y y_v + n_z``. The nearest hit within the rectangle wins (z-buffer).
Texture is then sampled bilinearly from the mip level that matches the texel footprint.

Optional shading (``RenderConfig.point_light``, off by default; the ``panel-room`` preset turns it
on together with ``texture.ambient = 1`` so that the texture holds the albedo only): the texel value is
multiplied by ``ambient + diffuse * max(0, n . l) * r0^2 / (r0^2 + d^2)`` of a point light at
``light_position`` (world, m; ``l`` the unit direction and ``d`` the distance from the surface point
to the light, ``n`` the normal facing the camera, ``r0 = light_range``). It depends on the surface
point only (Lambertian), so it is the same from every view. ``vignetting`` multiplies the image by
``1 - vignetting * (r / r_corner)^2`` (``r`` the distance of a pixel from the principal point,
``r_corner`` that of the farthest image corner): a view-dependent darkening of the border.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...core.config import MAX_SCALAR, ranged
from ...core.errors import ConfigError
from .scene import SceneArrays
from .texture import TextureAtlas

_EDGE_MARGIN = 1.001  # texel coordinates are clamped to [0, size - margin] so x0 + 1 stays inside
_MIN_LIGHT_DIST2 = 1e-12  # m^2; floor of the squared light distance (a surface point at the light)


@dataclass
class RenderConfig:
    """Renderer tunables."""

    near: float = ranged(0.05, gt=0, le=MAX_SCALAR)  # near clipping distance along the optical axis (m)
    sky_grey: float = ranged(200.0, ge=0, le=255)  # grey value (0-255) of rays that hit nothing
    mip_bias: float = ranged(0.0, ge=-MAX_SCALAR, le=MAX_SCALAR)  # added to log2(texel footprint) before choosing the mip level
    edge_tolerance: float = ranged(1e-4, ge=0, le=MAX_SCALAR)  # m; quads are grown by this much so float32 rounding leaves no
    # cracks between adjacent quads (ground tiles, box faces)
    point_light: bool = False  # per-pixel Lambertian shading by a point light (module docstring); off: texels as baked
    light_position: list[float] = ranged(default_factory=lambda: [0.0, 0.0, 2.6], ge=-MAX_SCALAR, le=MAX_SCALAR)  # world (m)
    light_ambient: float = ranged(0.55, ge=0, le=MAX_SCALAR)  # shading where the light does not reach
    light_diffuse: float = ranged(1.3, ge=0, le=MAX_SCALAR)  # gain of the Lambertian term at distance 0
    light_range: float = ranged(4.0, gt=0, le=MAX_SCALAR)  # m; the diffuse term halves at this distance from the light
    vignetting: float = ranged(0.0, ge=0, le=1)  # darkening of the farthest image corner (fraction; 0: off)
    max_distance: float = ranged(0.0, ge=0, le=MAX_SCALAR)  # m; quads whose nearest point is farther from the
    # camera are not drawn (0: no limit); large scenes (kitti00-drive) bound the per-view cost with it


@dataclass(frozen=True)
class RenderOutput:
    """``image`` float32 (H, W) grey or (H, W, 3) RGB in [0, 255]; ``depth`` float32 (H, W) z-depth in
    the camera frame, 0 where no surface is hit; ``quad_id`` int32 (H, W), -1 where no hit."""

    image: np.ndarray
    depth: np.ndarray
    quad_id: np.ndarray


class Renderer:
    """Renders one scene for one pinhole camera ``K = (fx, fy, cx, cy)`` of size ``width x height``."""

    def __init__(self, scene: SceneArrays, atlas: TextureAtlas, K, width: int, height: int,
                 cfg: RenderConfig | None = None):
        self.scene = scene
        self.atlas = atlas
        self.cfg = cfg or RenderConfig()
        self.K = tuple(float(k) for k in K)
        self.width, self.height = int(width), int(height)
        fx, fy, cx, cy = self.K
        self._xs = ((np.arange(self.width) - cx) / fx).astype(np.float32)
        self._ys = ((np.arange(self.height) - cy) / fy).astype(np.float32)
        self._corners = scene.corners()
        n_lev = atlas.offset.shape[1]
        self._n_lev = n_lev
        if atlas.texels.size >= np.iinfo(np.int32).max:
            raise ConfigError(f"texture atlas of {atlas.texels.size} texels is too large for int32 "
                              "indexing: lower the texture densities of the preset")
        self._offset = atlas.offset.ravel().astype(np.int32)
        self._width = atlas.width.ravel().astype(np.int32)
        self._max_u = (atlas.width.ravel() - _EDGE_MARGIN).astype(np.float32)
        self._max_v = (atlas.height.ravel() - _EDGE_MARGIN).astype(np.float32)
        self._tpm_u = atlas.texels_per_m_u.ravel().astype(np.float32)
        self._tpm_v = atlas.texels_per_m_v.ravel().astype(np.float32)
        tpm0 = np.sqrt(atlas.texels_per_m_u[:, 0].astype(np.float64) * atlas.texels_per_m_v[:, 0])
        self._level_offset = (np.log2(tpm0) - 0.5 * np.log2(fx * fy) + self.cfg.mip_bias).astype(np.float32)
        self._norm_d = np.sqrt(self._xs[None, :] ** 2 + self._ys[:, None] ** 2 + 1).astype(np.float32)
        self._vignette = None
        if self.cfg.vignetting > 0:
            du = np.arange(self.width) - cx
            dv = np.arange(self.height) - cy
            r2 = du[None, :] ** 2 + dv[:, None] ** 2
            r2_corner = max(cx ** 2, (self.width - 1 - cx) ** 2) + max(cy ** 2, (self.height - 1 - cy) ** 2)
            self._vignette = (1.0 - self.cfg.vignetting * r2 / r2_corner).astype(np.float32)

    def _visible_quads(self, R_WC: np.ndarray, t_WC: np.ndarray):
        """Indices and pixel bounding boxes (u0, u1, v0, v1; exclusive ends) of the quads that may be
        visible: in front of the near plane, facing the camera (one-sided quads), overlapping the image."""
        near = self.cfg.near
        fx, fy, cx, cy = self.K
        sc = self.scene
        facing = sc.two_sided | (np.einsum("qi,qi->q", sc.normals, t_WC - sc.origins) > 0)
        X_C = (self._corners - t_WC) @ R_WC  # (Q, 4, 3)
        z = X_C[..., 2]
        nxt = np.roll(X_C, -1, axis=1)
        z_n = nxt[..., 2]
        cross = (z - near) * (z_n - near) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.where(cross, (near - z) / (z_n - z), 0.0)
        P = np.concatenate([X_C, X_C + lam[..., None] * (nxt - X_C)], axis=1)  # (Q, 8, 3)
        valid = np.concatenate([z >= near, cross], axis=1)
        pz = np.where(valid, P[..., 2], 1.0)
        u = np.where(valid, fx * P[..., 0] / pz + cx, np.nan)
        v = np.where(valid, fy * P[..., 1] / pz + cy, np.nan)
        any_valid = valid.any(axis=1) & facing
        if self.cfg.max_distance > 0:  # distance from the camera to the nearest point of each rectangle
            rel = t_WC - sc.origins
            s_near = np.clip(np.einsum("qi,qi->q", rel, sc.axes_u), 0.0, sc.sizes[:, 0])
            t_near = np.clip(np.einsum("qi,qi->q", rel, sc.axes_v), 0.0, sc.sizes[:, 1])
            nearest = sc.origins + s_near[:, None] * sc.axes_u + t_near[:, None] * sc.axes_v
            any_valid &= np.linalg.norm(t_WC - nearest, axis=1) <= self.cfg.max_distance
        with np.errstate(invalid="ignore"):
            u_min = np.nanmin(np.where(any_valid[:, None], u, 0.0), axis=1)
            u_max = np.nanmax(np.where(any_valid[:, None], u, 0.0), axis=1)
            v_min = np.nanmin(np.where(any_valid[:, None], v, 0.0), axis=1)
            v_max = np.nanmax(np.where(any_valid[:, None], v, 0.0), axis=1)
        u0 = np.clip(np.floor(u_min), 0, self.width).astype(np.int64)
        u1 = np.clip(np.floor(u_max) + 2, 0, self.width).astype(np.int64)
        v0 = np.clip(np.floor(v_min), 0, self.height).astype(np.int64)
        v1 = np.clip(np.floor(v_max) + 2, 0, self.height).astype(np.int64)
        keep = np.flatnonzero(any_valid & (u1 > u0) & (v1 > v0))
        return keep, u0, u1, v0, v1

    def render(self, T_WC: np.ndarray, colour: bool = False) -> RenderOutput:
        """Render the view of camera pose ``T_WC`` (4x4 camera-to-world)."""
        T_WC = np.asarray(T_WC, np.float64)
        R_WC, t_WC = T_WC[:3, :3], T_WC[:3, 3]
        H, W = self.height, self.width
        sc = self.scene
        keep, u0s, u1s, v0s, v1s = self._visible_quads(R_WC, t_WC)
        # quad geometry in the camera frame
        n_C = (sc.normals[keep] @ R_WC).astype(np.float32)
        a_C = (sc.axes_u[keep] @ R_WC).astype(np.float32)
        b_C = (sc.axes_v[keep] @ R_WC).astype(np.float32)
        o_C = (sc.origins[keep] - t_WC) @ R_WC
        n_dot_o = np.einsum("qi,qi->q", n_C.astype(np.float64), o_C).astype(np.float32)
        a_dot_o = np.einsum("qi,qi->q", a_C.astype(np.float64), o_C).astype(np.float32)
        b_dot_o = np.einsum("qi,qi->q", b_C.astype(np.float64), o_C).astype(np.float32)
        eps = np.float32(self.cfg.edge_tolerance)
        s_max = (sc.sizes[keep] + self.cfg.edge_tolerance).astype(np.float32)

        zbuf = np.full((H, W), np.inf, np.float32)
        qbuf = np.full((H, W), -1, np.int32)
        sbuf = np.zeros((H, W), np.float32)
        tbuf = np.zeros((H, W), np.float32)
        dbuf = np.ones((H, W), np.float32)  # n_C . d_C of the nearest hit (incidence for mip levels)
        near = np.float32(self.cfg.near)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for k, q in enumerate(keep):
                u0, u1, v0, v1 = u0s[q], u1s[q], v0s[q], v1s[q]
                xs, ys = self._xs[u0:u1], self._ys[v0:v1]
                n, a, b = n_C[k], a_C[k], b_C[k]
                den = (n[1] * ys + n[2])[:, None] + n[0] * xs
                z = n_dot_o[k] / den
                zb = zbuf[v0:v1, u0:u1]
                m = (z > near) & (z < zb)
                if not m.any():
                    continue
                s = ((a[1] * ys + a[2])[:, None] + a[0] * xs) * z - a_dot_o[k]
                m &= (s >= -eps) & (s <= s_max[k, 0])
                t = ((b[1] * ys + b[2])[:, None] + b[0] * xs) * z - b_dot_o[k]
                m &= (t >= -eps) & (t <= s_max[k, 1])
                np.copyto(zb, z, where=m)
                np.copyto(qbuf[v0:v1, u0:u1], np.int32(q), where=m)
                np.copyto(sbuf[v0:v1, u0:u1], s, where=m)
                np.copyto(tbuf[v0:v1, u0:u1], t, where=m)
                np.copyto(dbuf[v0:v1, u0:u1], den, where=m)
            sky = qbuf < 0
            depth = np.where(sky, np.float32(0.0), zbuf)
            grey = self._shade(qbuf, sbuf, tbuf, depth, dbuf)
            if self.cfg.point_light:
                grey *= self._lighting(qbuf, depth, R_WC, t_WC)
        sky_value = np.float32(self.cfg.sky_grey)
        if colour:
            img = grey[..., None] * self.atlas.tint[np.maximum(qbuf, 0)]
            img[sky] = sky_value
            img = np.clip(img, 0, 255)
        else:
            img = np.where(sky, sky_value, grey)
        if self._vignette is not None:
            img = img * (self._vignette[..., None] if img.ndim == 3 else self._vignette)
        return RenderOutput(image=img, depth=depth, quad_id=qbuf)

    def _lighting(self, qbuf: np.ndarray, z: np.ndarray, R_WC: np.ndarray, t_WC: np.ndarray) -> np.ndarray:
        """(H, W) float32 point-light shading factor (module docstring) of the hit surface points."""
        cfg = self.cfg
        q = np.maximum(qbuf, 0)
        X_C = np.stack([self._xs[None, :] * z, self._ys[:, None] * z, z], axis=-1)
        X_W = X_C @ R_WC.T.astype(np.float32) + t_WC.astype(np.float32)
        to_light = np.asarray(cfg.light_position, np.float32) - X_W
        d2 = np.einsum("hwi,hwi->hw", to_light, to_light)
        n = self.scene.normals.astype(np.float32)[q]
        # two-sided quads: the side that faces the camera
        facing = np.einsum("hwi,hwi->hw", n, t_WC.astype(np.float32) - X_W)
        n *= np.where(facing < 0, np.float32(-1.0), np.float32(1.0))[..., None]
        cos = np.einsum("hwi,hwi->hw", n, to_light) / np.sqrt(np.maximum(d2, np.float32(_MIN_LIGHT_DIST2)))
        r0 = np.float32(cfg.light_range ** 2)
        return (np.float32(cfg.light_ambient)
                + np.float32(cfg.light_diffuse) * np.maximum(cos, np.float32(0.0)) * r0 / (r0 + d2)).astype(np.float32)

    def _shade(self, qbuf: np.ndarray, s: np.ndarray, t: np.ndarray, z: np.ndarray,
               den: np.ndarray) -> np.ndarray:
        """Bilinear texture lookup (H, W) from the mip level of the texel footprint, whose size in
        metres is ``z / (f sqrt(cos))`` with ``cos = |n_C . d_C| / |d_C|`` (geometric mean of the
        two axes of the footprint ellipse); values at sky pixels are meaningless."""
        q = np.maximum(qbuf, 0)
        arg = (z * z) * self._norm_d / np.maximum(np.abs(den), np.float32(1e-3))
        lev = np.float32(0.5) * np.log2(arg) + self._level_offset[q]
        lev = np.clip(lev, 0, self._n_lev - 1, out=lev).astype(np.int32)
        idx = q * np.int32(self._n_lev) + lev
        w = self._width[idx]
        tx = np.clip(s * self._tpm_u[idx] - np.float32(0.5), 0, self._max_u[idx])
        ty = np.clip(t * self._tpm_v[idx] - np.float32(0.5), 0, self._max_v[idx])
        x0f = np.floor(tx)
        y0f = np.floor(ty)
        fx_ = tx - x0f
        fy_ = ty - y0f
        i00 = self._offset[idx] + y0f.astype(np.int32) * w + x0f.astype(np.int32)
        tex = self.atlas.texels
        top = tex[i00] * (1 - fx_)
        top += tex[i00 + 1] * fx_
        i00 += w
        bot = tex[i00] * (1 - fx_)
        bot += tex[i00 + 1] * fx_
        top *= 1 - fy_
        bot *= fy_
        top += bot
        return top
