"""Ray-casting renderer: RGB and label images of the synthetic world from one camera.

Every pixel's ray (``CameraModel.pixel_rays``, z = 1 in the optical frame, so the ray
parameter ``t`` is the optical depth) is intersected with the ground plane z = 0 and with the
object boxes; the nearest hit wins. Boxes are tested only inside their projected image
rectangle (a z-buffer over exact ray/box intersections), so cost scales with covered pixels.
A ground pixel carries the raster label of the exact world point its ray hits.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.rig import RigCamera
from ..geometry.transforms import invert_transform
from .objects import CAR_BODY, FACADE, GLASS, Boxes
from .raster import NUM_MATS, GroundRaster, Mat, unpack

_NEAR = 0.05
_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                   [0, 4], [1, 5], [2, 6], [3, 7]])


@dataclass(frozen=True)
class Look:
    """Per-seed appearance: ground palette, sky, sun, exposure, noise, haze."""

    ground: np.ndarray  # (NUM_MATS, 3) RGB
    horizon: np.ndarray  # (3,)
    zenith: np.ndarray  # (3,)
    sun: np.ndarray  # (3,) unit vector towards the sun
    ambient: float
    diffuse: float
    gain: float
    noise: float  # sensor noise sigma, DN
    fog: float  # haze distance, m
    window: np.ndarray  # (3,)
    clouds: float  # cloud cover 0..1
    # Appearance-style extras (see styles.py); the defaults leave the image as Look.random's.
    texture: float = 1.0  # scale of the ground texture contrast
    wear: float = 0.0  # 0..1: how much lane paint fades into the asphalt (patchy)
    wet: float = 0.0  # 0..1: wet asphalt mirrors the sky at grazing angles (puddles)
    cloud_color: float | np.ndarray = 235.0  # grey level (or RGB) of the clouds
    lit_windows: float = 0.0  # fraction of windows lit from inside (emissive)
    lamp: np.ndarray | None = None  # (3,) colour of lit windows
    facade: np.ndarray | None = None  # (K, 3) facade palette, picked per building by its id
    facade_mix: float = 0.0  # 0..1: how far facades move from their own colour to the palette
    paint_saturation: float = 1.0  # saturation scale of object colours (cars, people, ...)
    paint_gain: np.ndarray | None = None  # (3,) per-channel scale of object colours
    tint: np.ndarray | None = None  # (3,) white balance: per-channel scale of the image
    saturation: float = 1.0  # saturation scale of the whole image
    vignette: float = 0.18  # corner darkening: 1 - vignette * r^2 (r = 1 at the side edges)
    blur: float = 0.0  # Gaussian blur sigma, pixels of a 400 px wide image (scales with width)

    @staticmethod
    def random(rng: np.random.Generator, noise_scale: float = 1.0) -> "Look":
        """A random but plausible look."""
        g = np.zeros((NUM_MATS, 3))
        g[Mat.GRASS] = np.array([70, 105, 45]) * rng.uniform(0.75, 1.2, 3)
        g[Mat.DIRT] = np.array([120, 100, 75]) * rng.uniform(0.8, 1.15, 3)
        g[Mat.CONCRETE] = rng.uniform(140, 195) * rng.uniform(0.93, 1.05, 3)
        g[Mat.ASPHALT] = rng.uniform(60, 105) * rng.uniform(0.96, 1.04, 3)
        g[Mat.CURB] = rng.uniform(165, 210) * np.ones(3)
        g[Mat.WHITE] = rng.uniform(215, 240) * np.ones(3)
        g[Mat.YELLOW] = np.array([225, 185, 45]) * rng.uniform(0.9, 1.05)
        elev, az = rng.uniform(np.radians(15), np.radians(70)), rng.uniform(-np.pi, np.pi)
        sun = np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        overcast = rng.random() < 0.3
        horizon = np.array([205, 215, 228]) * rng.uniform(0.9, 1.08, 3)
        zenith = np.array([150, 160, 170]) if overcast else np.array([70, 120, 200])
        zenith = zenith * rng.uniform(0.85, 1.1, 3)
        return Look(g.astype(np.float32), horizon.clip(0, 255), zenith.clip(0, 255), sun,
                    ambient=rng.uniform(0.5, 0.65) if overcast else rng.uniform(0.35, 0.5),
                    diffuse=rng.uniform(0.2, 0.35) if overcast else rng.uniform(0.5, 0.7),
                    gain=rng.uniform(0.85, 1.12), noise=rng.uniform(1.5, 5.0) * noise_scale,
                    fog=rng.uniform(250.0, 700.0),
                    window=np.array([45, 60, 80]) * rng.uniform(0.8, 1.3),
                    clouds=rng.uniform(0.1, 0.8))

    def box_colors(self, boxes: Boxes) -> np.ndarray:
        """Base colours ``(N, 3)`` float32 of ``boxes`` under this look: facades moved towards
        the look's palette (entry picked by a hash of the object id), object paint scaled in
        saturation and per channel. Geometry and labels are untouched.
        """
        col = boxes.color
        if self.facade is not None and self.facade_mix > 0 and len(boxes):
            fac = boxes.kind == FACADE
            if fac.any():
                pick = (_hash(boxes.obj[fac], np.zeros(int(fac.sum()), np.int64), 11)
                        * len(self.facade)).astype(np.int64)
                col = col.copy()
                col[fac] += (self.facade[pick].astype(np.float32) - col[fac]) * np.float32(self.facade_mix)
        if self.paint_saturation != 1.0 or self.paint_gain is not None:
            grey = col.mean(axis=1, keepdims=True)
            col = grey + (col - grey) * np.float32(self.paint_saturation)
            if self.paint_gain is not None:
                col = col * self.paint_gain.astype(np.float32)
            col = np.clip(col, 0.0, 255.0)
        return col.astype(np.float32, copy=False)


@dataclass
class CameraRender:
    """Output of :meth:`CameraRenderer.render` (all ``(H, W)`` except ``rgb``)."""

    rgb: np.ndarray  # (H, W, 3) uint8
    labels: np.ndarray  # uint8 Label ids
    depth: np.ndarray  # float64 optical depth of the visible surface, inf for sky
    part: np.ndarray  # int64 index into the frame's boxes of the visible box, -1 for ground/sky


def _hash(ix, iy, salt: int) -> np.ndarray:
    """Deterministic hash of integer lattice coordinates to floats in [0, 1)."""
    h = ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + salt * 2654435761
    h &= 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    return ((h ^ (h >> 16)) & 0xFFFFFF).astype(np.float32) / np.float32(1 << 24)


def value_noise(x, y, scale: float, salt: int = 0) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1) with lattice spacing ``scale``."""
    gx, gy = x / scale, y / scale
    ix, iy = np.floor(gx), np.floor(gy)
    fx, fy = (gx - ix).astype(np.float32), (gy - iy).astype(np.float32)
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    a, b = _hash(ix, iy, salt), _hash(ix + 1, iy, salt)
    c, d = _hash(ix, iy + 1, salt), _hash(ix + 1, iy + 1, salt)
    return (a + (b - a) * fx) * (1 - fy) + (c + (d - c) * fx) * fy


class CameraRenderer:
    """Renders one camera of a rig; the per-pixel rays are computed once."""

    def __init__(self, cam: RigCamera) -> None:
        self.name = cam.name
        self.model = cam.model.effective()
        self.w, self.h = self.model.image_size
        self.rays = self.model.pixel_rays()  # (H, W, 3) optical frame, z = 1
        self.ray_len = np.linalg.norm(self.rays, axis=2)
        self.ego_from_cam = cam.ego_from_cam_array
        self.pinhole = not np.any(self.model.D_array)
        self.K = self.model.K_array
        u = (np.arange(self.w) - self.w / 2) / (self.w / 2)
        v = (np.arange(self.h) - self.h / 2) / (self.w / 2)
        self._r2 = u[None, :] ** 2 + v[:, None] ** 2  # (H, W) squared radius, 1 at the side edges
        self._vignettes: dict[float, np.ndarray] = {}
        self.vignette = self.vignette_mask(0.18)

    def vignette_mask(self, strength: float) -> np.ndarray:
        """``(H, W)`` float32 gain ``1 - strength * r^2`` (cached per strength)."""
        if strength not in self._vignettes:
            self._vignettes[strength] = (1.0 - strength * self._r2).astype(np.float32)
        return self._vignettes[strength]

    # ------------------------------------------------------------- geometry
    def rects(self, boxes: Boxes, cam_from_world: np.ndarray) -> np.ndarray:
        """Image rectangles ``(N, 4)`` = ``x0, y0, x1, y1`` (exclusive) covering each box."""
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        pc = boxes.corners() @ R.T + t  # (N, 8, 3)
        a, b = pc[:, _EDGES[:, 0]], pc[:, _EDGES[:, 1]]  # (N, 12, 3)
        fa, fb = a[..., 2] > _NEAR, b[..., 2] > _NEAR
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(fa != fb, (_NEAR - a[..., 2]) / (b[..., 2] - a[..., 2]), 0.0)
        q = a + u[..., None] * (b - a)  # edge / near-plane crossings
        # clipped edge segments [p0, p1] (both ends in front of the near plane)
        p0 = np.where(fa[..., None], a, q)
        p1 = np.where(fb[..., None], b, q)
        valid = fa | fb
        fr = np.linspace(0.0, 1.0, 2 if self.pinhole else 9)
        pts = p0[:, :, None] + fr[None, None, :, None] * (p1 - p0)[:, :, None]  # (N, 12, F, 3)
        ok = np.broadcast_to(valid[:, :, None], pts.shape[:3]).reshape(len(boxes), -1)  # (N, 12*F)
        pts = pts.reshape(len(boxes), -1, 3)  # (N, 12, F, 3) -> (N, 12*F, 3)
        if self.pinhole:
            z = np.maximum(pts[..., 2], _NEAR)
            K = self.K
            uv = np.stack([K[0, 0] * pts[..., 0] / z + K[0, 1] * pts[..., 1] / z + K[0, 2],
                           K[1, 1] * pts[..., 1] / z + K[1, 2]], -1)
            margin = 1
        else:
            # (N, 12*F, 3) -> (N*12*F, 3) -> uv (N*12*F, 2) -> (N, 12*F, 2)
            uv = self.model.project(pts.reshape(-1, 3))[0].reshape(pts.shape[0], -1, 2)
            margin = 3
        uv = np.where(ok[..., None], uv, np.nan)
        with np.errstate(invalid="ignore"):
            lo = np.floor(np.nanmin(np.where(ok[..., None], uv, np.inf), axis=1)) - margin
            hi = np.ceil(np.nanmax(np.where(ok[..., None], uv, -np.inf), axis=1)) + 1 + margin
        lo = np.clip(np.nan_to_num(lo, nan=0, posinf=self.w, neginf=0), 0, [self.w, self.h])
        hi = np.clip(np.nan_to_num(hi, nan=0, posinf=self.w, neginf=0), 0, [self.w, self.h])
        return np.concatenate([lo, hi], 1).astype(np.int64)

    def cast(self, world_from_ego: np.ndarray, boxes: Boxes):
        """Nearest hits: ``(dirs (H,W,3) world, origin (3,), depth, part, face)``.

        ``face`` codes the hit face of the box: ``2 * axis + (ray component along axis > 0)``.
        """
        T = world_from_ego @ self.ego_from_cam
        R, o = T[:3, :3], T[:3, 3]
        r = self.rays
        d = r[..., 0:1] * R[:, 0] + r[..., 1:2] * R[:, 1] + r[..., 2:3] * R[:, 2]  # (H, W, 3)
        depth = np.full((self.h, self.w), np.inf)
        down = d[..., 2] < -1e-12
        if o[2] > 0:
            depth[down] = -o[2] / d[..., 2][down]
        part = np.full((self.h, self.w), -1, np.int64)
        face = np.zeros((self.h, self.w), np.int8)
        if len(boxes):
            rects = self.rects(boxes, invert_transform(T))
            todo = np.flatnonzero((rects[:, 2] > rects[:, 0]) & (rects[:, 3] > rects[:, 1]))
            for i in todo:
                x0, y0, x1, y1 = rects[i]
                self._box(i, boxes, o, d[y0:y1, x0:x1], depth[y0:y1, x0:x1],
                          part[y0:y1, x0:x1], face[y0:y1, x0:x1])
        return d, o, depth, part, face

    @staticmethod
    def _box(i, boxes: Boxes, o, d, depth, part, face) -> None:
        """Slab test of box ``i`` against the rays ``d`` (a window); updates the z-buffer views."""
        c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
        L, W, H = boxes.size[i]
        ox, oy = o[0] - boxes.center[i, 0], o[1] - boxes.center[i, 1]
        lo = (c * ox + s * oy, -s * ox + c * oy, o[2])  # ray origin in the box frame
        dl = (c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1], d[..., 2])
        bounds = ((-L / 2, L / 2), (-W / 2, W / 2), (boxes.z0[i], boxes.z0[i] + H))
        tn, tf, ax = None, None, None
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                inv = 1.0 / dl[k]
                t1, t2 = (bounds[k][0] - lo[k]) * inv, (bounds[k][1] - lo[k]) * inv
                tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
                if tn is None:
                    tn, tf, ax = tmin, tmax, np.zeros(tmin.shape, np.int8)
                else:
                    newer = tmin > tn
                    ax = np.where(newer, np.int8(k), ax)
                    tn, tf = np.maximum(tn, tmin), np.minimum(tf, tmax)
            hit = (tn <= tf) & (tn > _NEAR) & (tn < depth)
        if not hit.any():
            return
        dax = np.choose(ax, dl)
        depth[hit] = tn[hit]
        part[hit] = i
        face[hit] = (2 * ax + (dax > 0))[hit]

    # -------------------------------------------------------------- shading
    def render(self, world_from_ego: np.ndarray, boxes: Boxes, ground: GroundRaster, look: Look,
               rng: np.random.Generator) -> CameraRender:
        """Render RGB + labels (+ depth and box index buffers) of one frame.

        Only ``rgb`` depends on ``look`` and ``rng`` (sensor noise); labels, depth and the box
        buffer are the scene's alone.
        """
        d, o, depth, part, face = self.cast(world_from_ego, boxes)
        labels = np.zeros((self.h, self.w), np.uint8)
        rgb = np.empty((self.h, self.w, 3), np.float32)
        dist = depth * self.ray_len
        gnd = (part < 0) & np.isfinite(depth)
        if gnd.any():
            t = depth[gnd]
            gx, gy = o[0] + t * d[..., 0][gnd], o[1] + t * d[..., 1][gnd]
            lab, mat = unpack(ground.lookup(gx, gy, center=world_from_ego[:2, 3]))
            labels[gnd] = lab
            rgb[gnd] = self._shade_ground(gx, gy, mat, d[..., 2][gnd] / self.ray_len[gnd], look)
        obj = part >= 0
        if obj.any():
            rgb[obj], labels[obj] = self._shade_boxes(boxes, part[obj], face[obj], o,
                                                      d[obj], depth[obj], look)
        sky = ~np.isfinite(depth)
        if sky.any():
            rgb[sky] = self._sky(d[sky], o, look)
        fog = 1.0 - np.exp(-np.where(sky, 0.0, dist) / look.fog).astype(np.float32)
        rgb += (look.horizon.astype(np.float32) - rgb) * fog[..., None]
        if look.saturation != 1.0 or look.tint is not None:  # one 3x3 colour matrix per pixel
            s = look.saturation
            m = s * np.eye(3) + (1.0 - s) / 3.0  # saturation about the channel mean
            if look.tint is not None:
                m = look.tint[:, None] * m  # then white balance
            rgb = cv2.transform(rgb, m.astype(np.float32))
        rgb *= (look.gain * self.vignette_mask(look.vignette))[..., None]
        sigma = look.blur * self.w / 400.0
        if sigma >= 0.2:  # optics: blur before the sensor adds its noise
            rgb = cv2.GaussianBlur(rgb, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
        if look.noise > 0:
            rgb += rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(look.noise)
        return CameraRender(np.clip(rgb, 0, 255).astype(np.uint8), labels, depth, part)

    @staticmethod
    def _shade_ground(gx, gy, mat, dz, look: Look) -> np.ndarray:
        """Colours ``(M, 3)`` of ground points ``(gx, gy)`` of materials ``mat``, seen along rays
        of unit z component ``dz`` (< 0).
        """
        k = look.texture
        tex = ((0.8 + 0.35 * k * value_noise(gx, gy, 1.7, 1))
               * (0.93 + 0.14 * k * value_noise(gx, gy, 0.11, 2)))
        light = look.ambient + look.diffuse * max(look.sun[2], 0.0)
        col = look.ground[mat]
        paint = None
        if look.wear > 0 or look.wet > 0:
            paint = (mat == Mat.WHITE) | (mat == Mat.YELLOW)
        if look.wear > 0 and paint.any():  # worn paint: patches of it show the asphalt
            keep = np.clip(1.0 - look.wear * (0.5 + value_noise(gx[paint], gy[paint], 0.6, 4)),
                           0.0, 1.0)[:, None]
            asphalt = look.ground[Mat.ASPHALT]
            col[paint] = asphalt + (col[paint] - asphalt) * keep
        col *= (tex * light)[:, None]
        if look.wet > 0:  # wet road: mirrors the horizon at grazing angles, more in puddles
            road = paint | (mat == Mat.ASPHALT)
            if road.any():
                fresnel = 0.04 + 0.96 * (1.0 + dz[road]).astype(np.float32) ** 5
                puddle = 0.35 + 0.65 * np.clip(value_noise(gx[road], gy[road], 4.0, 5) * 2.0 - 0.6,
                                               0.0, 1.0)
                a = np.clip(look.wet * fresnel * puddle, 0.0, 0.9)[:, None]
                col[road] += (look.horizon.astype(np.float32) - col[road]) * a
        return col

    @staticmethod
    def _shade_boxes(boxes: Boxes, p, f, o, d, t, look: Look):
        """Colours ``(M, 3)`` and labels ``(M,)`` of pixels showing box ``p`` through face ``f``."""
        axis, positive_dir = f // 2, (f % 2).astype(bool)
        yaw = boxes.yaw[p]
        c, s = np.cos(yaw), np.sin(yaw)
        sign = np.where(positive_dir, -1.0, 1.0)  # the face's outward normal points back to the ray
        nx = np.choose(axis, [c, -s, np.zeros_like(c)]) * sign
        ny = np.choose(axis, [s, c, np.zeros_like(c)]) * sign
        nz = np.where(axis == 2, sign, 0.0)
        sun = look.sun
        lam = look.ambient + look.diffuse * np.maximum(nx * sun[0] + ny * sun[1] + nz * sun[2], 0)
        col = look.box_colors(boxes)[p] * lam[:, None].astype(np.float32)
        hit = o + t[:, None] * d  # (M, 3) world hit points
        kind = boxes.kind[p]
        lx = c * (hit[:, 0] - boxes.center[p, 0]) + s * (hit[:, 1] - boxes.center[p, 1])
        ly = -s * (hit[:, 0] - boxes.center[p, 0]) + c * (hit[:, 1] - boxes.center[p, 1])
        fac = (kind == FACADE) & (axis < 2)
        if fac.any():
            u = np.where(axis == 0, ly + boxes.size[p, 1] / 2, lx + boxes.size[p, 0] / 2)
            fu, fz = (u / 2.8) % 1.0, (hit[:, 2] / 3.2) % 1.0
            win = fac & (fu > 0.22) & (fu < 0.78) & (fz > 0.3) & (fz < 0.8) & (hit[:, 2] > 0.8)
            shade = 0.6 + 0.7 * _hash(np.floor(u / 2.8), np.floor(hit[:, 2] / 3.2), 7)[win]
            col[win] = (look.window * shade[:, None] * lam[win, None]).astype(np.float32)
            if look.lit_windows > 0:  # lit from inside: emissive, independent of the light
                cell = (np.floor(u[win] / 2.8), np.floor(hit[win, 2] / 3.2))
                lit = _hash(*cell, 8) < look.lit_windows
                idx = np.flatnonzero(win)[lit]
                col[idx] = (look.lamp * (0.75 + 0.25 * shade[lit, None])).astype(np.float32)
        roof = (kind == FACADE) & (axis == 2)
        col[roof] *= 0.7
        tyre = (kind == CAR_BODY) & (hit[:, 2] < 0.32)
        col[tyre] = 22.0
        glass = kind == GLASS
        col[glass] += np.float32(25.0) * (nz[glass] > 0)[:, None]
        return col, boxes.label[p]

    @staticmethod
    def _sky(d, o, look: Look) -> np.ndarray:
        """Sky colour ``(M, 3)`` for world ray directions ``d`` (gradient + clouds)."""
        e = d[:, 2] / np.linalg.norm(d, axis=1)
        k = np.clip(e * 2.5, 0.0, 1.0)[:, None] ** 0.7
        col = (look.horizon * (1 - k) + look.zenith * k).astype(np.float32)
        up = e > 0.02
        if up.any():
            h = 1500.0 / d[up, 2]
            n = value_noise(o[0] + h * d[up, 0], o[1] + h * d[up, 1], 600.0, 3)
            cover = np.clip((n - (1 - look.clouds)) * 3.0, 0.0, 1.0)[:, None]
            col[up] += (np.asarray(look.cloud_color, np.float32) - col[up]) * cover * 0.8
        return col
