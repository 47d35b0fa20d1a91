"""Procedural, non-repeating surface textures and their mip-mapped atlas.

A texture is a grey image in surface coordinates (column = s / texel, row = t / texel, see
:mod:`.scene`), made of multi-octave value noise (random grids upsampled bicubically), random
filled ellipses and rectangles, line segments and text-like glyph strings, with a constant Lambertian
shading factor of the quad baked in (the light is directional and fixed in the world, so shading is
view-independent and brightness constancy holds exactly). Every quad gets its own random texture, so
places can be recognised. Textures are stored as uint8 mip pyramids (``cv2.pyrDown``) in one flat
atlas; :class:`TextureAtlas` holds per (quad, level) offsets, shapes and texels per metre.

Low-texture styles (:data:`PLAIN_STYLES`: plain paint, floor tiles, doors, wall panels) are the
opposite: a uniform albedo with faint smooth noise, plus faint grout lines on a regular grid (tiles),
a door leaf with a darker frame band and a handle (doors), or thin grout lines between near-white
rectangular panels (panels: ``panel_size_m`` wide and high, ``panel_line_width_m`` joints). They are
not normalised to a fixed contrast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ...core.config import MAX_IMAGE_SIDE, MAX_LEVELS, MAX_SCALAR, ranged
from ...core.errors import ConfigError
from .scene import SceneArrays

_GLYPHS = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#&%@"
_MIN_MARK_TEXELS = 1.0  # marks whose largest size is below this many texels are not drawn
_MIN_TEXT_TEXELS = 4.0  # glyph strings smaller than this many texels are not drawn
_HERSHEY_HEIGHT_PX = 22.0  # height in pixels of FONT_HERSHEY_SIMPLEX capitals at scale 1
_LINE_LENGTH_M = (0.1, 1.0)  # range of line segment lengths
_LINE_WIDTH_M = (0.005, 0.03)  # range of line widths
_NORMALISED_STD = 0.25  # standard deviation of a texture after normalisation (values in [0, 1])

# textured styles: index into TextureConfig.style_mark_scale
STYLE_WALL, STYLE_GROUND, STYLE_OBJECT = 0, 1, 2
# low-texture styles beyond the textured ones
STYLE_PLAIN, STYLE_TILES, STYLE_DOOR, STYLE_PANELS = 3, 4, 5, 6
PLAIN_STYLES = (STYLE_PLAIN, STYLE_TILES, STYLE_DOOR, STYLE_PANELS)


@dataclass
class PlainTextureConfig:
    """Low-texture styles (plain paint, tiles, doors): albedos in [0, 1] before contrast and shading."""

    albedo: list[float] = ranged(default_factory=lambda: [0.92, 0.8, 0.45], ge=0, le=1)  # plain, tiles, door
    noise: float = ranged(0.01, ge=0, le=1)  # std of the faint smooth noise (fraction of the grey range)
    noise_cell_m: float = ranged(0.3, gt=0, le=MAX_SCALAR)  # cell size of that noise (one octave: no fine detail)
    tile_size_m: float = ranged(0.6, gt=0, le=MAX_SCALAR)  # floor tile side
    tile_line_width_m: float = ranged(0.008, gt=0, le=MAX_SCALAR)  # grout line width
    tile_line_depth: float = ranged(0.1, ge=0, le=1)  # grout darkening (fraction of the albedo): faint
    door_frame_m: float = ranged(0.06, ge=0, le=MAX_SCALAR)  # width of the door's frame band along its border
    door_frame_depth: float = ranged(0.25, ge=0, le=1)  # darkening of the frame band (fraction of the albedo)
    handle_size_m: list[float] = ranged(default_factory=lambda: [0.12, 0.03], gt=0, le=MAX_SCALAR)  # handle (width, height)
    handle_position_m: list[float] = ranged(default_factory=lambda: [0.12, 1.0], ge=0, le=MAX_SCALAR)  # handle centre from the
    # door's far edge (along u) and from its bottom (along v)
    handle_albedo: float = ranged(0.1, ge=0, le=1)
    panel_albedo: float = ranged(0.94, ge=0, le=1)  # wall panels (STYLE_PANELS): near-white
    panel_size_m: list[float] = ranged(default_factory=lambda: [0.6, 1.2], gt=0, le=MAX_SCALAR)  # panel (width along u, height along v)
    panel_line_width_m: float = ranged(0.005, gt=0, le=MAX_SCALAR)  # joint between panels (a few px at 1 m in VGA)
    panel_line_depth: float = ranged(0.35, ge=0, le=1)  # joint darkening (fraction of the albedo)
    panel_albedo_jitter: float = ranged(0.0, ge=0, le=1)  # std of each panel's own albedo factor (0: identical panels)


@dataclass
class TextureConfig:
    """Tunables of the procedural textures (lengths in metres on the surface)."""

    noise_cells_m: list[float] = ranged(default_factory=lambda: [1.6, 0.7, 0.3, 0.12, 0.05, 0.02], gt=0, le=MAX_SCALAR)  # noise cell sizes of the octaves (m)
    noise_persistence: float = ranged(0.75, gt=0, le=1)  # amplitude ratio between successive (finer) octaves
    blobs_per_m2: float = ranged(1.5, ge=0, le=MAX_SCALAR)  # random filled ellipses / rectangles per square metre
    blob_size_m: tuple[float, float] = ranged((0.04, 0.45), gt=0, le=MAX_SCALAR)  # range of blob half-axes
    lines_per_m2: float = ranged(0.8, ge=0, le=MAX_SCALAR)  # random line segments per square metre
    text_per_m2: float = ranged(0.6, ge=0, le=MAX_SCALAR)  # random glyph strings per square metre
    text_height_m: tuple[float, float] = ranged((0.04, 0.25), gt=0, le=MAX_SCALAR)  # range of glyph heights
    contrast: float = ranged(0.8, ge=0, le=1)  # final grey range fraction of [0, 255] before shading
    light_dir_W: tuple[float, float, float] = ranged((0.35, 0.55, 0.76), ge=-MAX_SCALAR, le=MAX_SCALAR)  # directional light (normalised)
    ambient: float = ranged(0.55, ge=0, le=1)  # shading = ambient + (1 - ambient) * max(0, n . l)
    max_texture_side: int = ranged(4096, ge=1, le=MAX_IMAGE_SIDE)  # texels; the density of a quad is lowered to fit
    max_levels: int = ranged(7, ge=1, le=MAX_LEVELS)  # mip levels at most (level 0 = full resolution)
    min_level_side: int = ranged(4, ge=1, le=MAX_IMAGE_SIDE)  # stop the pyramid before a side gets smaller than this
    colour_saturation: float = ranged(0.35, ge=0, le=1)  # spread of per-quad RGB tints when colour is rendered
    # multiplier of the mark counts (blobs, lines, text) per style: wall, ground, small object
    style_mark_scale: list[float] = ranged(default_factory=lambda: [1.0, 1.0, 4.0], ge=0, le=MAX_SCALAR)
    plain: PlainTextureConfig = field(default_factory=PlainTextureConfig)  # low-texture styles




@dataclass(frozen=True)
class TextureAtlas:
    """Flat uint8 texel array plus (Q, L) tables: ``offset`` (int64), ``width``/``height`` (int64),
    ``texels_per_m_u``/``texels_per_m_v`` (float32) of level l of quad q, ``n_levels`` (Q,) and
    per-quad RGB tints ``tint`` (Q, 3) float32."""

    texels: np.ndarray
    offset: np.ndarray
    width: np.ndarray
    height: np.ndarray
    texels_per_m_u: np.ndarray
    texels_per_m_v: np.ndarray
    n_levels: np.ndarray
    tint: np.ndarray


def _value_noise(shape: tuple[int, int], texel_m: float, cfg: TextureConfig,
                 rng: np.random.Generator) -> np.ndarray:
    """Multi-octave value noise in [0, 1]-ish, float32 (H, W)."""
    h, w = shape
    out = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for cell_m in cfg.noise_cells_m:
        cell_px = cell_m / texel_m
        if cell_px < 1.5:
            break
        gh, gw = int(np.ceil(h / cell_px)) + 3, int(np.ceil(w / cell_px)) + 3
        grid = rng.random((gh, gw), dtype=np.float32)
        up = cv2.resize(grid, (int(round(gw * cell_px)), int(round(gh * cell_px))),
                        interpolation=cv2.INTER_CUBIC)
        oy, ox = int(cell_px), int(cell_px)
        out += amp * up[oy:oy + h, ox:ox + w]
        total += amp
        amp *= cfg.noise_persistence
    return out / max(total, 1e-6)


def make_texture(size_m: tuple[float, float], density: float, cfg: TextureConfig,
                 rng: np.random.Generator, mark_scale: float = 1.0) -> np.ndarray:
    """Unshaded grey texture in [0, 1] (float32, (H, W)) for a quad of ``size_m = (su, sv)``;
    ``mark_scale`` multiplies the expected numbers of blobs, lines and glyph strings."""
    su, sv = size_m
    w = max(4, int(np.ceil(su * density)))
    h = max(4, int(np.ceil(sv * density)))
    texel_m = 1.0 / density
    img = _value_noise((h, w), texel_m, cfg, rng)
    area = su * sv * mark_scale
    marks = img.copy()
    lo, hi = cfg.blob_size_m
    if hi * density >= _MIN_MARK_TEXELS:
        n = rng.poisson(cfg.blobs_per_m2 * area)
        cx, cy = rng.integers(0, w, n), rng.integers(0, h, n)
        axes = np.maximum(1, (rng.uniform(lo, hi, (n, 2)) * density).astype(np.int64))
        vals, kinds, angles = rng.random(n), rng.random(n), rng.uniform(0, 180, n)
        for i in range(n):
            c, ax = (int(cx[i]), int(cy[i])), (int(axes[i, 0]), int(axes[i, 1]))
            if kinds[i] < 0.5:
                cv2.ellipse(marks, c, ax, float(angles[i]), 0, 360, float(vals[i]), -1, cv2.LINE_AA)
            else:
                cv2.rectangle(marks, (c[0] - ax[0], c[1] - ax[1]), (c[0] + ax[0], c[1] + ax[1]),
                              float(vals[i]), -1)
    if density * _LINE_LENGTH_M[1] >= _MIN_MARK_TEXELS:
        n = rng.poisson(cfg.lines_per_m2 * area)
        x0, y0 = rng.integers(0, w, n), rng.integers(0, h, n)
        length = rng.uniform(*_LINE_LENGTH_M, n) * density
        ang = rng.uniform(0, 2 * np.pi, n)
        x1 = (x0 + length * np.cos(ang)).astype(np.int64)
        y1 = (y0 + length * np.sin(ang)).astype(np.int64)
        thick = np.maximum(1, (rng.uniform(*_LINE_WIDTH_M, n) * density).astype(np.int64))
        vals = rng.random(n)
        for i in range(n):
            cv2.line(marks, (int(x0[i]), int(y0[i])), (int(x1[i]), int(y1[i])), float(vals[i]),
                     int(thick[i]), cv2.LINE_AA)
    tlo, thi = cfg.text_height_m
    if thi * density >= _MIN_TEXT_TEXELS:
        n = rng.poisson(cfg.text_per_m2 * area)
        lens = rng.integers(2, 8, n)
        glyphs = rng.integers(0, len(_GLYPHS), (n, 8))
        heights = rng.uniform(tlo, thi, n) * density
        ox, oy = rng.integers(0, w, n), rng.integers(0, h, n)
        vals = (rng.random(n) > 0.5).astype(np.float64)
        for i in range(n):
            if heights[i] < _MIN_TEXT_TEXELS:
                continue
            text = "".join(_GLYPHS[g] for g in glyphs[i, :lens[i]])
            scale = heights[i] / _HERSHEY_HEIGHT_PX
            _put_text(marks, text, (int(ox[i]), int(oy[i])), scale, float(vals[i]), max(1, int(scale * 2)))
    img = 0.55 * marks + 0.45 * img
    mean, std = float(img.mean()), float(img.std())
    img = (img - mean) * (_NORMALISED_STD / max(std, 1e-6)) + 0.5
    return np.clip(img, 0.0, 1.0)


def _put_text(marks: np.ndarray, text: str, origin: tuple[int, int], scale: float, value: float,
              thickness: int) -> None:
    """Hershey text of grey ``value`` on the float image ``marks`` (in place).

    OpenCV 4 (the pinned version) draws on float images directly (``LINE_AA`` is anti-aliased on 8-bit
    images only, so on a float image it draws 8-connected strokes). OpenCV 5 draws text on 8-bit images
    only: there the same strokes are drawn as an 8-bit mask and set to ``value``, the same pixels."""
    try:
        cv2.putText(marks, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, value, thickness, cv2.LINE_AA)
    except cv2.error:
        strokes = np.zeros(marks.shape, np.uint8)
        cv2.putText(strokes, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thickness, cv2.LINE_8)
        marks[strokes > 0] = value


def make_plain_texture(size_m: tuple[float, float], density: float, style: int, cfg: PlainTextureConfig,
                       rng: np.random.Generator) -> np.ndarray:
    """Low-texture surface in [0, 1] (float32, (H, W)) of style ``style`` in :data:`PLAIN_STYLES`
    (module docstring); rows run along the quad's v axis (t), columns along u (s)."""
    su, sv = size_m
    w = max(4, int(np.ceil(su * density)))
    h = max(4, int(np.ceil(sv * density)))
    albedo = cfg.panel_albedo if style == STYLE_PANELS else cfg.albedo[PLAIN_STYLES.index(style)]
    noise_cfg = TextureConfig(noise_cells_m=[cfg.noise_cell_m])
    noise = _value_noise((h, w), 1.0 / density, noise_cfg, rng)
    noise = (noise - noise.mean()) / max(float(noise.std()), 1e-6)
    img = np.full((h, w), albedo, np.float32) * (1.0 + cfg.noise * noise)
    s = (np.arange(w) + 0.5) / density  # texel centres in metres
    t = (np.arange(h) + 0.5) / density
    def grout(x: np.ndarray, period: float, width: float) -> np.ndarray:  # coverage of a line at the borders
        d = np.abs(x - period * np.round(x / period))
        return np.clip(0.5 + (0.5 * width - d) * density, 0.0, 1.0)

    if style == STYLE_TILES:
        line = np.maximum(grout(t, cfg.tile_size_m, cfg.tile_line_width_m)[:, None],
                          grout(s, cfg.tile_size_m, cfg.tile_line_width_m)[None, :])
        img *= (1.0 - cfg.tile_line_depth * line).astype(np.float32)
    elif style == STYLE_PANELS:
        pw, ph = cfg.panel_size_m
        line = np.maximum(grout(t, ph, cfg.panel_line_width_m)[:, None], grout(s, pw, cfg.panel_line_width_m)[None, :])
        if cfg.panel_albedo_jitter > 0:  # panels never match exactly: one albedo factor per panel
            col, row = np.floor(s / pw).astype(np.int64), np.floor(t / ph).astype(np.int64)
            factor = 1.0 + cfg.panel_albedo_jitter * rng.standard_normal((row[-1] + 1, col[-1] + 1))
            img *= factor[row[:, None], col[None, :]].astype(np.float32)
        img *= (1.0 - cfg.panel_line_depth * line).astype(np.float32)
    elif style == STYLE_DOOR:
        edge = np.minimum(np.minimum(s, su - s)[None, :], np.minimum(t, sv - t)[:, None])
        img *= np.where(edge < cfg.door_frame_m, np.float32(1.0 - cfg.door_frame_depth), np.float32(1.0))
        hw, hh = cfg.handle_size_m
        hu, hv = su - cfg.handle_position_m[0], cfg.handle_position_m[1]
        handle = (np.abs(s - hu) < hw / 2)[None, :] & (np.abs(t - hv) < hh / 2)[:, None]
        img[handle] = cfg.handle_albedo
    return np.clip(img, 0.0, 1.0)


def build_atlas(scene: SceneArrays, cfg: TextureConfig, rng: np.random.Generator) -> TextureAtlas:
    """Generate, shade and mip-map the texture of every quad into one atlas."""
    n_q = len(scene)
    n_lev = cfg.max_levels
    light = np.asarray(cfg.light_dir_W, np.float64)
    light = light / np.linalg.norm(light)
    chunks, offsets = [], np.zeros((n_q, n_lev), np.int64)
    widths = np.zeros((n_q, n_lev), np.int64)
    heights = np.zeros((n_q, n_lev), np.int64)
    tpm_u = np.zeros((n_q, n_lev), np.float32)
    tpm_v = np.zeros((n_q, n_lev), np.float32)
    levels = np.zeros(n_q, np.int64)
    pos = 0
    for q in range(n_q):
        su, sv = scene.sizes[q]
        density = min(scene.densities[q], cfg.max_texture_side / max(su, sv))
        style = int(scene.styles[q])
        if style in PLAIN_STYLES:
            tex = make_plain_texture((su, sv), density, style, cfg.plain, rng)
        elif not 0 <= style < len(cfg.style_mark_scale):
            raise ConfigError(f"texture.style_mark_scale: no entry for style {style} of quad {q}")
        else:
            tex = make_texture((su, sv), density, cfg, rng, cfg.style_mark_scale[style])
        ndotl = float(scene.normals[q] @ light)
        if scene.two_sided[q]:
            ndotl = abs(ndotl)
        shade = cfg.ambient + (1.0 - cfg.ambient) * max(0.0, ndotl)
        base = ((1.0 - cfg.contrast) / 2 + cfg.contrast * tex) * shade * 255.0
        level_img = base.astype(np.float32)
        for lev in range(n_lev):
            h, w = level_img.shape
            chunks.append(np.clip(np.rint(level_img), 0, 255).astype(np.uint8).ravel())
            offsets[q, lev], widths[q, lev], heights[q, lev] = pos, w, h
            tpm_u[q, lev], tpm_v[q, lev] = w / su, h / sv
            pos += w * h
            levels[q] = lev + 1
            if lev + 1 == n_lev or min(h, w) // 2 < cfg.min_level_side:
                break
            level_img = cv2.pyrDown(level_img)
        last = levels[q] - 1
        for table in (offsets, widths, heights, tpm_u, tpm_v):
            table[q, levels[q]:] = table[q, last]
    tint = 1.0 + cfg.colour_saturation * (rng.random((n_q, 3)) - 0.5)
    tint = tint / tint.mean(axis=1, keepdims=True)
    return TextureAtlas(texels=np.concatenate(chunks) if chunks else np.zeros(1, np.uint8),
                        offset=offsets, width=widths, height=heights, texels_per_m_u=tpm_u,
                        texels_per_m_v=tpm_v, n_levels=levels, tint=tint.astype(np.float32))
