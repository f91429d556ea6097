"""Textures of the synthetic scene: one grayscale image per face, packed into a mip-mapped atlas.

Each face gets its own seeded texture so that no two places look alike: a procedural base
(fractal noise "concrete", floor tiles, wood planks, ceiling panels, or a photographic
material such as scikit-image's brick/gravel/grass, always modulated by noise), then framed
photographs (scikit-image's bundled pictures: astronaut, coffee, rocket, ...), random
shapes and printed text, all at physical sizes in metres, so corners exist at every scale.

The atlas (:class:`TextureAtlas`) stores every level of the mip pyramid in one image, laid
out the classic way (level 0 on the left, levels 1, 2, ... stacked on its right), so a
renderer samples any level with one ``cv2.remap``. Each face's rectangle is padded by a
gutter and aligned to ``2 ** (levels - 1)`` texels, so bilinear lookups at any level never
bleed into a neighbouring face.
"""

from __future__ import annotations

import logging
import string
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from common.data.synth.scene import Face, Scene

logger = logging.getLogger(__name__)

# Photos bundled with scikit-image that load offline (grayscale conversion below).
PHOTO_NAMES = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "camera",
    "page",
    "text",
    "moon",
    "coins",
    "hubble_deep_field",
    "immunohistochemistry",
    "retina",
    "clock",
    "cell",
    "colorwheel",
    "logo",
    "horse",
    "brick",
    "grass",
    "gravel",
)
MATERIAL_PHOTOS = ("brick", "grass", "gravel")


@dataclass(frozen=True)
class TextureConfig:
    """Texture resolution and content density.

    ``texel_m``: texel size of the room's walls and floor [m]; ``box_texel_m`` of boxes;
    ``ceiling_texel_m`` of the ceiling (seen from afar). ``levels``: mip levels (level ``L``
    has texels ``2**L`` times larger). ``atlas_width``: width of level 0 [texels].
    ``shapes_per_m2`` / ``text_per_m2`` / ``posters_per_m2``: decal densities.
    """

    texel_m: float = 0.004
    box_texel_m: float = 0.003
    ceiling_texel_m: float = 0.006
    levels: int = 7
    atlas_width: int = 8192
    shapes_per_m2: float = 12.0
    text_per_m2: float = 3.0
    posters_per_m2: float = 0.25


@cache
def _photo(name: str) -> np.ndarray:
    """A scikit-image bundled picture as uint8 grayscale (H, W)."""
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)())
    if img.dtype == bool:
        img = np.where(img, 230, 25).astype(np.uint8)
    if img.ndim == 3:
        img = img[..., :3] if img.shape[2] >= 3 else img[..., :1]
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    img = img.astype(np.uint8)
    img.setflags(write=False)
    return img


def value_noise(h: int, w: int, cell: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth noise in about [-1, 1], (h, w) float32, features ``cell`` texels across."""
    gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
    grid = rng.uniform(-1.0, 1.0, size=(gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    return big[:h, :w]


def fractal_noise(
    h: int, w: int, texel: float, rng: np.random.Generator, scales_m: tuple[float, ...]
) -> np.ndarray:
    """Sum of value-noise octaves with feature sizes ``scales_m`` [m]; amplitude ~ size^0.5."""
    out = np.zeros((h, w), np.float32)
    total = 0.0
    for s in scales_m:
        amp = s**0.5
        out += amp * value_noise(h, w, max(s / texel, 1.5), rng)
        total += amp
    return out / total


def _tiled_photo(
    name: str, h: int, w: int, texel: float, tile_m: float, rng: np.random.Generator
) -> np.ndarray:
    """A material photo repeated over (h, w) at ``tile_m`` metres per picture, each copy from
    a random crop, flip and rotation so that no two copies are identical."""
    photo = _photo(name).astype(np.float32)
    n = max(round(tile_m / texel), 8)
    out = np.empty((h, w), np.float32)
    for y in range(0, h, n):
        for x in range(0, w, n):
            ph, pw = photo.shape
            c = int(min(ph, pw) * rng.uniform(0.55, 0.9))
            y0, x0 = rng.integers(0, ph - c + 1), rng.integers(0, pw - c + 1)
            tile = np.rot90(photo[y0 : y0 + c, x0 : x0 + c], int(rng.integers(4)))
            if rng.random() < 0.5:
                tile = tile[:, ::-1]
            cell = cv2.resize(np.ascontiguousarray(tile), (n, n), interpolation=cv2.INTER_AREA)
            out[y : y + n, x : x + n] = cell[: h - y, : w - x]
    return out


def _base(face: Face, h: int, w: int, texel: float, rng: np.random.Generator) -> np.ndarray:
    """Base material (h, w) float32 in ~[0, 255] for a face of the given kind."""
    kind = face.kind
    noise = fractal_noise(h, w, texel, rng, (2.0, 0.5, 0.12, 0.03))
    if kind == "floor":
        tile_m = 0.5
        n = max(int(tile_m / texel), 4)
        levels = rng.uniform(70, 190, size=(h // n + 2, w // n + 2)).astype(np.float32)
        img = cv2.resize(
            levels, (levels.shape[1] * n, levels.shape[0] * n), interpolation=cv2.INTER_NEAREST
        )[:h, :w]
        grain = _tiled_photo("gravel", h, w, texel, 0.6, rng) - 128.0
        img = img + 0.35 * grain + 40.0 * noise
        grout = max(int(0.01 / texel), 1)
        img[(np.arange(h) % n) < grout, :] *= 0.45
        img[:, (np.arange(w) % n) < grout] *= 0.45
        return img
    if kind == "ceiling":
        n = max(int(0.6 / texel), 4)
        img = 150.0 + 60.0 * noise
        img[(np.arange(h) % n) < 3, :] = 60.0
        img[:, (np.arange(w) % n) < 3] = 60.0
        for _ in range(int(face.size[0] * face.size[1] / 3.0)):
            cy, cx = rng.integers(0, h // n + 1) * n, rng.integers(0, w // n + 1) * n
            img[cy + 6 : cy + n - 6, cx + 6 : cx + n - 6] = rng.uniform(215, 245)
        return img
    choice = rng.choice(["concrete", "wood", "photo", "photo", "stripes"])
    if choice == "concrete":
        return 128.0 + 70.0 * noise + 25.0 * fractal_noise(h, w, texel, rng, (0.01, 0.004))
    if choice == "wood":
        ys = np.arange(h, dtype=np.float32)[:, None] * texel
        warp = 0.05 * fractal_noise(h, w, texel, rng, (0.4, 0.1))
        grain = np.sin(2 * np.pi * (ys + warp) / rng.uniform(0.012, 0.03))
        planks = max(int(rng.uniform(0.12, 0.25) / texel), 4)
        shade = rng.uniform(80, 170, size=(h // planks + 2, 1)).astype(np.float32)
        shade = np.repeat(shade, planks, axis=0)[:h]
        img = shade + 25.0 * grain + 35.0 * noise
        img[(np.arange(h) % planks) < 2, :] *= 0.5
        return img
    if choice == "stripes":
        angle = rng.uniform(0, np.pi)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) * texel
        period = rng.uniform(0.08, 0.3)
        phase = (xx * np.cos(angle) + yy * np.sin(angle)) / period
        return 128.0 + 45.0 * np.sign(np.sin(2 * np.pi * phase)) + 60.0 * noise
    name = str(rng.choice(MATERIAL_PHOTOS))
    photo = _tiled_photo(name, h, w, texel, rng.uniform(0.6, 1.2), rng)
    return photo * (1.0 + 0.45 * noise) + 20.0 * fractal_noise(h, w, texel, rng, (0.05,))


def _random_text(rng: np.random.Generator) -> str:
    alphabet = string.ascii_uppercase + string.digits + "#%&+-/<>=?@"
    return "".join(rng.choice(list(alphabet), size=int(rng.integers(2, 9))))


def _decorate(
    img: np.ndarray, face: Face, texel: float, cfg: TextureConfig, rng: np.random.Generator
) -> None:
    """Draw shapes and text onto ``img`` (h, w) float32, in place."""
    h, w = img.shape
    area = face.size[0] * face.size[1]
    n_shapes = rng.poisson(cfg.shapes_per_m2 * area)
    for _ in range(n_shapes):
        size = rng.uniform(0.02, 0.25) ** 1.0 / texel
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        color = float(rng.choice([rng.uniform(5, 60), rng.uniform(190, 250)]))
        kind = rng.integers(4)
        if kind == 0:
            axes = (max(int(size), 2), max(int(size * rng.uniform(0.3, 1.0)), 2))
            cv2.ellipse(
                img, (int(cx), int(cy)), axes, rng.uniform(0, 180), 0, 360, color, -1, cv2.LINE_AA
            )
        elif kind == 1:
            pts = np.array([cx, cy]) + rng.uniform(-size, size, size=(int(rng.integers(3, 7)), 2))
            cv2.fillPoly(img, [pts.astype(np.int32)], color, cv2.LINE_AA)
        elif kind == 2:
            dx, dy = size * rng.uniform(0.3, 1.0), size * rng.uniform(0.3, 1.0)
            cv2.rectangle(
                img,
                (int(cx - dx), int(cy - dy)),
                (int(cx + dx), int(cy + dy)),
                color,
                -1 if rng.random() < 0.7 else max(int(0.01 / texel), 2),
            )
        else:
            pts = np.array([cx, cy]) + rng.uniform(-size, size, size=(int(rng.integers(2, 5)), 2))
            thickness = max(int(rng.uniform(0.005, 0.02) / texel), 1)
            cv2.polylines(img, [pts.astype(np.int32)], False, color, thickness, cv2.LINE_AA)
    n_text = rng.poisson(cfg.text_per_m2 * area)
    if n_text == 0:
        return
    # putText draws on uint8 only: print dark and bright text into two coverage masks.
    masks = np.zeros((2, h, w), np.uint8)
    for _ in range(n_text):
        height_m = rng.uniform(0.03, 0.15)
        scale = height_m / texel / 22.0  # HERSHEY_SIMPLEX glyphs are ~22 px tall at scale 1
        org = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        thick = max(int(scale * rng.uniform(1.5, 3.5)), 1)
        font = int(rng.choice([0, 2, 3, 4]))
        cv2.putText(
            masks[int(rng.integers(2))],
            _random_text(rng),
            org,
            font,
            scale,
            255,
            thick,
            cv2.LINE_AA,
        )
    dark = masks[0].astype(np.float32) / 255.0
    img *= 1.0 - dark
    img += 20.0 * dark
    bright = masks[1].astype(np.float32) / 255.0
    img *= 1.0 - bright
    img += 235.0 * bright


def _posters(
    img: np.ndarray, face: Face, texel: float, cfg: TextureConfig, rng: np.random.Generator
) -> None:
    """Paste framed photographs onto ``img`` (h, w) float32, in place."""
    h, w = img.shape
    area = face.size[0] * face.size[1]
    posters = rng.poisson(cfg.posters_per_m2 * area) + (1 if face.kind != "ceiling" else 0)
    for _ in range(posters):
        photo = _photo(str(rng.choice(PHOTO_NAMES))).astype(np.float32)
        size_m = rng.uniform(0.25, min(1.4, 0.8 * min(face.size)))
        ph, pw = photo.shape
        scale = size_m / texel / max(ph, pw)
        th, tw = max(int(ph * scale), 4), max(int(pw * scale), 4)
        if th + 8 >= h or tw + 8 >= w:
            continue
        poster = cv2.resize(photo, (tw, th), interpolation=cv2.INTER_AREA)
        poster = poster * rng.uniform(0.7, 1.1) + rng.uniform(-20, 20)
        y, x = int(rng.integers(4, h - th - 4)), int(rng.integers(4, w - tw - 4))
        border = max(int(0.015 / texel), 2)
        img[max(y - border, 0) : y + th + border, max(x - border, 0) : x + tw + border] = (
            rng.uniform(10, 40) if rng.random() < 0.6 else rng.uniform(220, 250)
        )
        img[y : y + th, x : x + tw] = poster


def face_texel(face: Face, cfg: TextureConfig) -> float:
    """Texel size [m] used for ``face``."""
    if face.kind == "ceiling":
        return cfg.ceiling_texel_m
    if face.kind.startswith("box"):
        return cfg.box_texel_m * (8.0 if face.kind == "box_bottom" else 1.0)
    return cfg.texel_m


def make_face_texture(
    face: Face, texel: float, cfg: TextureConfig, rng: np.random.Generator
) -> np.ndarray:
    """uint8 (h, w) texture of ``face``: row ``r``, column ``c`` covers texture coordinates
    ``s in [c, c+1) * texel``, ``t in [r, r+1) * texel`` [m]."""
    w = max(int(np.ceil(face.size[0] / texel)), 2)
    h = max(int(np.ceil(face.size[1] / texel)), 2)
    img = _base(face, h, w, texel, rng)
    if face.kind != "box_bottom":
        _decorate(img, face, texel, cfg, rng)
        _posters(img, face, texel, cfg, rng)
    # Slow illumination changes across the surface.
    img *= 1.0 + 0.15 * value_noise(h, w, 1.5 / texel, rng)
    return np.clip(img, 8, 245).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class TextureAtlas:
    """Mip-mapped atlas of all face textures.

    ``image``: uint8 (H0, W0 + W0 // 2) holding level 0 at x 0 and level ``L >= 1`` at
    ``level_origin[L]``; ``rect`` (F, 4) int: x, y, width, height of each face's texels at
    level 0 (gutter excluded); ``texel_m`` (F,) texel size per face [m].
    """

    image: np.ndarray
    level_origin: np.ndarray  # (levels, 2) x, y of each level in ``image``
    rect: np.ndarray
    texel_m: np.ndarray
    levels: int

    def level(self, lvl: int) -> np.ndarray:
        """View of mip level ``lvl`` (H0 >> lvl, W0 >> lvl)."""
        x, y = self.level_origin[lvl]
        h0, w0 = self.image.shape[0], self.level_origin[1][0]
        return self.image[y : y + (h0 >> lvl), x : x + (w0 >> lvl)]

    def face_texture(self, face_index: int) -> np.ndarray:
        """Level-0 texels of one face (gutter excluded)."""
        x, y, w, h = self.rect[face_index]
        return self.image[y : y + h, x : x + w]

    def sample(self, face_index: int, st: np.ndarray, lvl: int = 0) -> np.ndarray:
        """Bilinear lookup at mip level ``lvl`` of texture coordinates (N, 2) [m] -> (N,)
        float32 (independent of the renderer; used to check it)."""
        st = np.asarray(st, dtype=np.float64).reshape(-1, 2)
        x0, y0, _, _ = self.rect[face_index]
        c = st / self.texel_m[face_index] + (x0, y0)
        ox, oy = self.level_origin[lvl]
        m = (c / (1 << lvl) - 0.5 + (ox, oy)).astype(np.float32)
        out = cv2.remap(self.image, m[:, :1], m[:, 1:], cv2.INTER_LINEAR)
        return out.reshape(-1).astype(np.float32)


def _pack(
    sizes: list[tuple[int, int]], width: int, align: int
) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing of (w, h) rectangles (multiples of ``align``) -> positions, total height."""
    order = sorted(range(len(sizes)), key=lambda i: (-sizes[i][1], -sizes[i][0], i))
    pos: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf_h = 0
    for i in order:
        w, h = sizes[i]
        if w > width:
            raise ValueError(f"texture of width {w} does not fit an atlas of width {width}")
        if x + w > width:
            x, y, shelf_h = 0, y + shelf_h, 0
        pos[i] = (x, y)
        x += w
        shelf_h = max(shelf_h, h)
    height = y + shelf_h
    return pos, -(-height // align) * align


def build_atlas(scene: Scene, seed: int, cfg: TextureConfig = TextureConfig()) -> TextureAtlas:
    """Generate every face's texture (seeded per face) and pack them with mips."""
    align = 1 << (cfg.levels - 1)
    gutter = align
    textures, sizes, texels = [], [], []
    for i, face in enumerate(scene.faces):
        rng = np.random.default_rng([seed, 7919, i])
        texel = face_texel(face, cfg)
        tex = make_face_texture(face, texel, cfg, rng)
        h, w = tex.shape
        sizes.append((-(-(w + 2 * gutter) // align) * align, -(-(h + 2 * gutter) // align) * align))
        textures.append(tex)
        texels.append(texel)
    pos, height = _pack(sizes, cfg.atlas_width, align)
    w0 = cfg.atlas_width
    level0 = np.zeros((height, w0), np.uint8)
    rects = np.zeros((len(textures), 4), np.int64)
    for i, tex in enumerate(textures):
        x, y = pos[i]
        pw, ph = sizes[i]
        h, w = tex.shape
        padded = cv2.copyMakeBorder(
            tex, gutter, ph - h - gutter, gutter, pw - w - gutter, cv2.BORDER_REPLICATE
        )
        level0[y : y + ph, x : x + pw] = padded
        rects[i] = (x + gutter, y + gutter, w, h)
    image = np.zeros((height, w0 + w0 // 2), np.uint8)
    image[:, :w0] = level0
    origins = [(0, 0)]
    lvl_img: np.ndarray = level0
    ly = 0
    for _ in range(1, cfg.levels):
        lvl_img = cv2.resize(
            lvl_img, (lvl_img.shape[1] // 2, lvl_img.shape[0] // 2), interpolation=cv2.INTER_AREA
        )
        image[ly : ly + lvl_img.shape[0], w0 : w0 + lvl_img.shape[1]] = lvl_img
        origins.append((w0, ly))
        ly += lvl_img.shape[0]
    logger.info("texture atlas %dx%d, %d faces", image.shape[1], image.shape[0], len(textures))
    image.setflags(write=False)
    return TextureAtlas(image, np.array(origins, np.int64), rects, np.array(texels), cfg.levels)
