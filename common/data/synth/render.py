"""Fast vectorised ray-casting renderer of the synthetic scene into distorted images.

Per camera, the ray of every distorted pixel is computed once through its camera model
(``CameraModel.pixel_rays``: radial-tangential, or a fisheye's rays also beyond 90 degrees;
pixels outside a model's field of view stay black), with its angular footprint. Per frame:
rotate the rays into the world, intersect them with the room (exit distance of a box from
inside) and with each box (slab test; boxes whose bounding sphere no ray can reach are
skipped), take the nearest hit, compute the face's texture coordinates and a mip level from the
ray footprint on the surface (distance and incidence: ``footprint = t * pixel_angle / |cos|``),
then sample the mip-mapped atlas trilinearly with two ``cv2.remap`` calls. Optics and sensor:
slight blur, vignetting, exposure drift over time, Gaussian read noise, 8-bit quantisation;
optionally (:class:`EffectsConfig`) auto-exposure steps and motion blur.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.camera import CameraModel
from common.data.synth.scene import Scene
from common.data.synth.textures import TextureAtlas

_SHADE = {
    "floor": 0.82,
    "ceiling": 1.0,
    "wall": 0.95,
    "box_top": 1.0,
    "box_side": 0.9,
    "box_bottom": 0.5,
}


@dataclass(frozen=True)
class RenderConfig:
    """Image formation. ``noise_std``: Gaussian read noise [DN]; ``blur_sigma``: optics blur
    [px] (0 = none); ``vignetting``: brightness loss at the image corners (fraction);
    ``exposure_amplitude``: relative amplitude of the slow exposure drift; ``lod_bias``:
    added to the mip level (negative = sharper, risks aliasing)."""

    noise_std: float = 2.0
    blur_sigma: float = 0.6
    vignetting: float = 0.25
    exposure_amplitude: float = 0.12
    lod_bias: float = 0.0
    min_cos: float = 0.06


@dataclass(frozen=True)
class EffectsConfig:
    """Sensor effects beyond :class:`RenderConfig`, off by default.

    Exposure steps (``exposure_steps``), as an auto-exposure makes them: the exposure gain
    jumps at times spaced ``step_every_s`` apart (uniform) by a factor drawn log-uniformly in
    ``step_factor``, kept within ``gain_range``; constant between jumps.
    Motion blur (``motion_blur_ms`` > 0): the exposure lasts that long, centred on the frame's
    timestamp (so the ground truth at the timestamp is the mid-exposure pose); the image is the
    mean radiance of ``S = clip(round(motion_blur_ms / blur_step_ms) + 1, 2, max_subframes)``
    renders at poses evenly spaced over the exposure, before optics blur, vignetting, gain and
    noise (a box filter of the motion during the exposure, sampled S times).
    """

    exposure_steps: bool = False
    step_every_s: tuple[float, float] = (1.5, 4.0)
    step_factor: tuple[float, float] = (0.5, 2.0)
    gain_range: tuple[float, float] = (0.4, 2.0)
    motion_blur_ms: float = 0.0
    blur_step_ms: float = 2.0
    max_subframes: int = 9

    @property
    def is_default(self) -> bool:
        return self == EffectsConfig()

    def subframe_offsets_s(self) -> np.ndarray:
        """(S,) times [s] of the sub-renders relative to the frame's timestamp (empty: none)."""
        if self.motion_blur_ms <= 0:
            return np.zeros(0)
        n = int(np.clip(round(self.motion_blur_ms / self.blur_step_ms) + 1, 2, self.max_subframes))
        half = self.motion_blur_ms * 1e-3 / 2.0
        return np.linspace(-half, half, n)

    def exposure_schedule(
        self, seconds: float, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray]:
        """(step times (J,) [s] with 0 first, gains (J,)): the gain at ``t`` is
        ``gains[searchsorted(times, t, "right") - 1]``; one step of gain 1 when off."""
        times, gains = [0.0], [1.0]
        if self.exposure_steps:
            lo, hi = np.log(self.step_factor[0]), np.log(self.step_factor[1])
            t = float(rng.uniform(*self.step_every_s))
            while t < seconds:
                g = gains[-1] * float(np.exp(rng.uniform(lo, hi)))
                if not self.gain_range[0] <= g <= self.gain_range[1]:
                    g = gains[-1] / float(np.exp(rng.uniform(lo, hi)))  # step the other way
                gains.append(float(np.clip(g, *self.gain_range)))
                times.append(t)
                t += float(rng.uniform(*self.step_every_s))
        return np.array(times), np.array(gains)


@dataclass(frozen=True, eq=False)
class RenderResult:
    """``radiance`` (H, W) float32 before sensor effects; ``depth`` (H, W) float32 ray length
    [m]; ``face`` (H, W) int32 face index; ``lod`` (H, W) float32 mip level used."""

    radiance: np.ndarray
    depth: np.ndarray
    face: np.ndarray
    lod: np.ndarray


class Renderer:
    """Renders ``scene`` textured by ``atlas`` through ``camera``."""

    def __init__(
        self,
        scene: Scene,
        atlas: TextureAtlas,
        camera: CameraModel,
        config: RenderConfig = RenderConfig(),
    ) -> None:
        self.scene, self.atlas, self.camera, self.config = scene, atlas, camera, config
        rays = camera.pixel_rays()
        h, w = rays.shape[:2]
        seen = np.isfinite(rays).all(axis=2)
        # Pixels beyond the model's field of view: any ray for the geometry, black in the image.
        self._unseen = None if seen.all() else ~seen
        rays[~seen] = (0.0, 0.0, 1.0)
        # Angular size of each pixel: the larger of the angles to the right and lower neighbours.
        dx = np.linalg.norm(np.diff(rays, axis=1, append=rays[:, -2:-1] * 0 + rays[:, -1:]), axis=2)
        dx[:, -1] = dx[:, -2]
        dy = np.linalg.norm(np.diff(rays, axis=0), axis=2)
        dy = np.concatenate([dy, dy[-1:]], axis=0)
        self._rays = [np.ascontiguousarray(rays[..., k].reshape(-1), np.float32) for k in range(3)]
        self._log_pix = np.log2(np.maximum(dx, dy)).reshape(-1).astype(np.float32)
        xy = (camera.pixel_grid() - (camera.cx, camera.cy)) / (camera.fx, camera.fy)
        r2 = (xy**2).sum(axis=1) / (xy**2).sum(axis=1).max()
        self._vignette = (1.0 - config.vignetting * r2).reshape(h, w).astype(np.float32)
        faces = scene.faces
        texel = atlas.texel_m
        u_dir = np.array([f.u_dir for f in faces])
        v_dir = np.array([f.v_dir for f in faces])
        self._ax = (u_dir / texel).astype(np.float32)
        self._bx = atlas.rect[:, 0] - np.array([f.u_origin for f in faces]) * u_dir / texel
        self._ay = (v_dir / texel).astype(np.float32)
        self._by = atlas.rect[:, 1] - np.array([f.v_origin for f in faces]) * v_dir / texel
        self._bx = self._bx.astype(np.float32)
        self._by = self._by.astype(np.float32)
        self._log_texel = np.log2(texel).astype(np.float32)
        self._shade = np.array([_SHADE[f.kind] for f in faces], np.float32)
        self._normal_axis = np.array([f.axis for f in faces], np.int8)
        self._boxes = [(np.array(b.lo), np.array(b.hi)) for b in scene.boxes]
        self._cos_fov = float(self._rays[2].min())
        origins = atlas.level_origin.astype(np.float32)
        self._level_scale = (1.0 / 2.0 ** np.arange(atlas.levels)).astype(np.float32)
        # Texel centres: level-L coordinate = level-0 coordinate / 2^L - 0.5 + level origin.
        self._level_ox = origins[:, 0] - np.float32(0.5)
        self._level_oy = origins[:, 1] - np.float32(0.5)
        self._axis_is_x = self._normal_axis == 0
        self._axis_is_z = self._normal_axis == 2
        self._log_texel_bias = (self._log_texel - np.float32(config.lod_bias)).astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        return self.camera.height, self.camera.width

    def _cast(
        self, o: np.ndarray, d: list[np.ndarray], R_world_cam: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """Nearest hit distance (N,) and face (N,) int32 of unit rays ``d`` (3 arrays (N,),
        structure of arrays for speed) from ``o``; also returns the inverse directions."""
        lo = self.scene.room_lo
        hi = self.scene.room_hi
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = [np.float32(1.0) / dk for dk in d]
        tt = []
        for k in range(3):
            pos = d[k] > 0
            tk = np.where(pos, np.float32(hi[k] - o[k]), np.float32(lo[k] - o[k])) * inv[k]
            tk[d[k] == 0] = np.inf
            tt.append(tk)
        t = np.minimum(np.minimum(tt[0], tt[1]), tt[2])
        face = np.where(t == tt[0], 0, np.where(t == tt[1], 2, 4)).astype(np.int32)
        ax_d = np.where(face == 0, d[0], np.where(face == 2, d[1], d[2]))
        face += ax_d > 0
        n = len(t)
        z_cam = R_world_cam[:, 2]
        for b, (blo, bhi) in enumerate(self._boxes):
            centre = (blo + bhi) / 2
            radius = float(np.linalg.norm(bhi - blo) / 2)
            to_c = centre - o
            dist = float(np.linalg.norm(to_c))
            if dist > radius:
                # Skip boxes entirely outside the field of view; else test only rays that can
                # reach the bounding sphere.
                half = np.arcsin(min(radius / dist, 1.0))
                ang = np.arccos(np.clip(to_c @ z_cam / dist, -1, 1))
                if ang - half > np.arccos(self._cos_fov):
                    continue
                u = (to_c / dist).astype(np.float32)
                sel = np.flatnonzero(d[0] * u[0] + d[1] * u[1] + d[2] * u[2] >= np.cos(half))
                if len(sel) == 0:
                    continue
                inv_s = [iv[sel] for iv in inv]
            else:
                sel = np.arange(n)
                inv_s = inv
            tn, tf = [], []
            with np.errstate(invalid="ignore"):
                for k in range(3):
                    t1 = np.float32(blo[k] - o[k]) * inv_s[k]
                    t2 = np.float32(bhi[k] - o[k]) * inv_s[k]
                    tn.append(np.fmin(t1, t2))
                    tf.append(np.fmax(t1, t2))
            tnear = np.maximum(np.maximum(tn[0], tn[1]), tn[2])
            tfar = np.minimum(np.minimum(tf[0], tf[1]), tf[2])
            hit = (tnear <= tfar) & (tnear > 0) & (tnear < t[sel])
            if not hit.any():
                continue
            idx = sel[hit]
            th = tnear[hit]
            ax = np.where(th == tn[0][hit], 0, np.where(th == tn[1][hit], 1, 2))
            dax = np.where(ax == 0, d[0][idx], np.where(ax == 1, d[1][idx], d[2][idx]))
            t[idx] = th
            face[idx] = 6 + 6 * b + 2 * ax + (dax < 0)
        return t, face, inv

    def render_radiance(self, T_world_cam: np.ndarray) -> RenderResult:
        """Noise-free shaded texture values (0..255 scale) seen from ``T_world_cam`` (4, 4)."""
        R = np.asarray(T_world_cam[:3, :3], np.float64)
        o = np.asarray(T_world_cam[:3, 3], np.float64)
        rx, ry, rz = self._rays
        Rf = R.astype(np.float32)
        d = [Rf[k, 0] * rx + Rf[k, 1] * ry + Rf[k, 2] * rz for k in range(3)]
        t, face, _ = self._cast(o, d, R)
        on_x = self._axis_is_x[face]
        on_z = self._axis_is_z[face]
        # Tangent coordinates of the hit: (y, z) on x-faces, (x, z) on y-faces, (x, y) on z-faces.
        u = np.float32(o[0]) + np.where(on_x, d[1], d[0]) * t
        u += np.where(on_x, np.float32(o[1] - o[0]), np.float32(0.0))
        v = np.float32(o[2]) + np.where(on_z, d[1], d[2]) * t
        v += np.where(on_z, np.float32(o[1] - o[2]), np.float32(0.0))
        cx = u * self._ax[face] + self._bx[face]
        cy = v * self._ay[face] + self._by[face]
        cos = np.where(on_x, d[0], np.where(on_z, d[2], d[1]))
        np.abs(cos, out=cos)
        np.maximum(cos, self.config.min_cos, out=cos)
        lod = np.log2(t / cos)
        lod += self._log_pix
        lod -= self._log_texel_bias[face]
        top = self.atlas.levels - 1
        np.clip(lod, 0.0, top, out=lod)
        l0 = np.minimum(lod.astype(np.int8), top - 1)
        frac = lod - l0
        h, w = self.shape
        samples = []
        for lvl in (l0, l0 + 1):
            scale = self._level_scale[lvl]
            mx = (cx * scale + self._level_ox[lvl]).reshape(h, w)
            my = (cy * scale + self._level_oy[lvl]).reshape(h, w)
            samples.append(cv2.remap(self.atlas.image, mx, my, cv2.INTER_LINEAR))
        a = samples[0].reshape(-1).astype(np.float32)
        b = samples[1].reshape(-1)
        rad = (a + (b - a) * frac) * self._shade[face]
        if self._unseen is not None:
            rad[self._unseen.reshape(-1)] = 0.0
        return RenderResult(
            rad.reshape(h, w), t.reshape(h, w), face.reshape(h, w), lod.reshape(h, w)
        )

    def exposure_gain(self, t: float, phase: float = 0.0) -> float:
        """Relative exposure at time ``t`` [s]: a slow, smooth drift around 1."""
        amp = self.config.exposure_amplitude
        return float(
            1.0 + amp * (0.7 * np.sin(0.31 * t + phase) + 0.3 * np.sin(1.13 * t + 2 * phase))
        )

    def render(
        self,
        T_world_cam: np.ndarray,
        t: float,
        rng: np.random.Generator,
        phase: float = 0.0,
        gain: float = 1.0,
        exposure_poses: np.ndarray | None = None,
    ) -> np.ndarray:
        """uint8 (H, W) image as the sensor records it at time ``t`` [s].

        ``gain``: extra exposure factor (an auto-exposure step); ``exposure_poses``
        (S, 4, 4): camera poses over the exposure time, whose radiances are averaged (motion
        blur; ``T_world_cam`` is then unused), or None for an instantaneous exposure."""
        if exposure_poses is None:
            img = self.render_radiance(T_world_cam).radiance
        else:
            img = self.render_radiance(exposure_poses[0]).radiance
            for T in exposure_poses[1:]:
                img = img + self.render_radiance(T).radiance
            img = img / np.float32(len(exposure_poses))
        if self.config.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.config.blur_sigma)
        img = img * (self._vignette * (self.exposure_gain(t, phase) * gain))
        if self.config.noise_std > 0:
            img += rng.standard_normal(img.shape, dtype=np.float32) * self.config.noise_std
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
