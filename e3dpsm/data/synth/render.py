"""Numpy ray caster for the head-mounted fisheye: textured room plus a capsule body.

Rays through the pixel centres are fixed in the camera frame, so they are computed once.
Pixels are stored tile by tile (`tile` x `tile` blocks of the render image): a capsule is
only tested against the tiles whose cone of rays can reach its bounding sphere, which cuts
the body pass to the few percent of the image each limb covers.

Intensity is Lambertian under one ceiling light plus ambient, in (0, 1]; the renderer
returns log intensity, the quantity an event pixel responds to.
"""
from __future__ import annotations

import numpy as np

from e3dpsm.camera import OcamCamera
from e3dpsm.data.synth import texture
from e3dpsm.data.synth.motion import Room
from e3dpsm.errors import ConfigError

LOG_EPS = 0.01  # keeps log intensity finite in the darkest texels (dark-current floor)
AMBIENT = 0.3


def intersect_capsule(rays: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Distance along unit rays [M, 3] from the origin to a capsule (segment a-b, radius r);
    inf where the ray misses or the capsule is behind the camera.

    The ray enters the capsule either through its cylinder wall, if that entry point lies
    between the end planes, or through the end sphere on the side it falls; a ray missing
    the infinite cylinder misses both spheres too, since they lie inside it.
    """
    axis = b - a
    length = float(np.linalg.norm(axis))
    d_a = rays @ a  # ray direction . a
    if length < 1e-9:
        return _sphere_hit(d_a, float(a @ a), r)
    e = axis / length
    d_e = rays @ e
    a_e = float(a @ e)
    # |(t d - a)_perp|^2 = r^2  ->  A t^2 - 2 B t + C = 0
    A = 1.0 - d_e * d_e
    B = d_a - a_e * d_e
    C = float(a @ a) - a_e * a_e - r * r
    disc = B * B - A * C
    hit = disc >= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (B - np.sqrt(np.where(hit, disc, 0.0))) / A
    along = t * d_e - a_e
    t_a = _sphere_hit(d_a, float(a @ a), r)
    t_b = _sphere_hit(d_a + length * d_e, float(b @ b), r)
    t = np.where(along < 0, t_a, np.where(along > length, t_b, t))
    return np.where(hit & (t > 0), t, np.inf)


def closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fraction along a-b [M] and point [M, 3] of the segment closest to each of p [M, 3]."""
    axis = b - a
    length2 = float(axis @ axis)
    s = np.clip((p - a) @ axis / length2, 0, 1) if length2 > 1e-18 else np.zeros(len(p))
    return s, a + s[:, None] * axis


def _sphere_hit(d_c: np.ndarray, c_c: float, r: float) -> np.ndarray:
    disc = d_c * d_c - (c_c - r * r)
    with np.errstate(invalid="ignore"):
        t = d_c - np.sqrt(disc)
    return np.where((disc >= 0) & (t > 0), t, np.inf)


class Renderer:
    def __init__(self, camera: OcamCamera, scale: float, room: Room, rng: np.random.Generator,
                 tile: int = 16):
        rays = camera.pixel_rays(scale).astype(np.float64)
        h, w = rays.shape[:2]
        if h % tile or w % tile:
            tile = 8
        if h % tile or w % tile:
            raise ConfigError(f"render scale {scale} gives {w}x{h} pixels, not a multiple of 8")
        self.render_hw, self.block = (h, w), round(1 / scale)
        nty, ntx = h // tile, w // tile
        # [tiles, pixels per tile, 3], tiles in row-major order of the tile grid
        tiled = rays.reshape(nty, tile, ntx, tile, 3).transpose(0, 2, 1, 3, 4)
        self.rays = tiled.reshape(nty * ntx, tile * tile, 3)
        centre = self.rays.mean(axis=1)
        self.tile_dir = centre / np.linalg.norm(centre, axis=-1, keepdims=True)
        cos_max = np.einsum("tpc,tc->tp", self.rays, self.tile_dir).min(1)
        self.tile_sin = np.sqrt(np.clip(1 - cos_max**2, 0, 1)) + 1e-3  # sine of the tile's half-angle
        yy, xx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        pix = np.stack([xx, yy], -1).reshape(nty, tile, ntx, tile, 2).transpose(0, 2, 1, 3, 4)
        self.pixel_xy = pix.reshape(-1, 2)  # render-pixel (x, y) of each flat tile-major pixel
        self.rays_t = np.ascontiguousarray(self.rays.reshape(-1, 3).T, dtype=np.float32)
        self.room = room
        self.light = np.array([0.0, 0.0, room.height - 0.05])
        self.textures = texture.WrappedTexture(np.stack([texture.floor_texture(rng), texture.wall_texture(rng)]))
        self.cloth_tex = texture.WrappedTexture(texture.cloth_texture(rng))
        self.floor_m, self.wall_m = 2.0, 4.0  # metres covered by one texture repeat

    @property
    def num_pixels(self) -> int:
        return self.rays_t.shape[1]

    # ---- background ---------------------------------------------------------------------
    def _room_intensity(self, cam_pos: np.ndarray, cam_rot: np.ndarray) -> np.ndarray:
        # Component arrays [N] rather than [N, 3] (numpy reduces short last axes slowly)
        # and float32 throughout: this pass runs for every pixel of every render and
        # dominated generation time.
        c = cam_pos.astype(np.float32)
        # World directions [3, N], written out: a BLAS matmul with an inner size of 3 is
        # slower than nine multiply-adds, and its thread pool fights the generator's
        # worker processes for the cores.
        rot, rays = cam_rot.astype(np.float32), self.rays_t
        d = rot[:, :1] * rays[0]
        d += rot[:, 1:2] * rays[1]
        d += rot[:, 2:] * rays[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / d
        half_x, half_y, height = (np.float32(x) for x in (self.room.half_x, self.room.half_y, self.room.height))
        t_x = (np.copysign(half_x, d[0]) - c[0]) * inv[0]
        t_y = (np.copysign(half_y, d[1]) - c[1]) * inv[1]
        up = d[2] > 0
        t_z = (up * height - c[2]) * inv[2]
        t_z[t_z <= 0] = np.inf  # a ray with d_z == +0.0 is horizontal: it meets a wall, not the floor
        t_wall = np.minimum(t_x, t_y)
        on_x, flat = t_x <= t_y, t_z <= t_wall  # hit an x wall (if not flat); floor/ceiling
        t = np.minimum(t_wall, t_z)
        p = d * t
        p += c[:, None]
        # Texture layer 0 (floor tiles) for floor and ceiling, layer 1 for walls: the
        # horizontal coordinate runs along the wall, offset so facing walls differ.
        k_floor, k_wall = np.float32(self.textures.shape[0] / self.floor_m), np.float32(self.textures.shape[0] / self.wall_m)
        along = np.where(on_x, p[1] + np.float32(7.3) * np.sign(p[0]), p[0] + np.float32(3.1) * np.sign(p[1]))
        u = np.where(flat, p[0] * k_floor, along * k_wall)
        v = np.where(flat, p[1] * k_floor, p[2] * k_wall)
        albedo = self.textures.sample(u, v, layer=(~flat).astype(np.int32))
        ceiling = flat & up
        albedo[ceiling] *= np.float32(0.6)
        # Lambert with the light inside the room: cos(incidence) = distance from the light
        # to the hit plane / distance to the hit point.
        p -= self.light.astype(np.float32)[:, None]
        dist2 = p[0] * p[0]
        dist2 += p[1] * p[1]
        dist2 += p[2] * p[2]
        plane_dist = np.abs(np.where(flat, p[2], np.where(on_x, p[0], p[1])))
        return albedo * self._lambert(plane_dist / np.sqrt(dist2), dist2)

    @staticmethod
    def _lambert(cos: np.ndarray, dist2: np.ndarray) -> np.ndarray:
        return (AMBIENT + (1 - AMBIENT) * np.clip(cos, 0, None) * 6.0 / (6.0 + dist2)).astype(np.float32)

    def _light(self, p: np.ndarray, normal: np.ndarray, light: np.ndarray) -> np.ndarray:
        to_light = light - p
        dist2 = np.einsum("nc,nc->n", to_light, to_light)
        return self._lambert(np.einsum("nc,nc->n", normal, to_light) / np.sqrt(dist2), dist2)

    # ---- full frame ---------------------------------------------------------------------
    def render(self, cam_pos: np.ndarray, cam_rot: np.ndarray, capsules: np.ndarray, radii: np.ndarray,
               albedo: np.ndarray, forward_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Log intensity [N] and body mask [N] (tile-major pixel order) for one pose.

        capsules: [K, 2, 3] end points in the camera frame; radii, albedo: [K];
        forward_cam: the body's forward axis in the camera frame (cloth texture reference).
        """
        shade = self._room_intensity(cam_pos, cam_rot)
        depth = np.full(shade.shape, np.inf)
        light_cam = (self.light - cam_pos) @ cam_rot
        per_tile = np.arange(self.rays.shape[1])
        for k, ((a, b), r) in enumerate(zip(capsules, radii)):
            tiles = self._tiles_near(a, b, r)
            if tiles.size == 0:
                continue
            pix = (tiles[:, None] * per_tile.size + per_tile).ravel()
            rays = self.rays[tiles].reshape(-1, 3)
            t = intersect_capsule(rays, a, b, r)
            closer = t < depth[pix]
            if not closer.any():
                continue
            t_hit, pix = t[closer], pix[closer]
            p = rays[closer] * t_hit[:, None]
            s, on_axis = closest_on_segment(p, a, b)
            radial = p - on_axis
            depth[pix] = t_hit
            shade[pix] = albedo[k] * self._cloth(s, radial, a, b, forward_cam, k) * self._light(
                p, radial / r, light_cam)
        return np.log(LOG_EPS + shade), np.isfinite(depth)

    def _tiles_near(self, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
        """Tiles whose cone of rays can meet the capsule. A ray within angle alpha of the
        tile axis that touches the capsule passes within r of some segment point q, so q
        lies within r + (|q| + r) sin(alpha) of the axis line; test the closest segment
        point to each axis line against that bound (|q| bounded by the farther end)."""
        w = b - a
        a_u, w_u = self.tile_dir @ a, self.tile_dir @ w
        w_w, a_w, a_a = float(w @ w), float(a @ w), float(a @ a)
        denom = w_w - w_u * w_u
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.clip(np.where(denom > 1e-12, (a_u * w_u - a_w) / denom, 0.0), 0.0, 1.0)
        dist2 = a_a + 2 * s * a_w + s * s * w_w - (a_u + s * w_u) ** 2
        reach = r + (np.sqrt(max(a_a, float(b @ b))) + r) * self.tile_sin
        return np.flatnonzero(dist2 <= reach * reach)

    def _cloth(self, s: np.ndarray, radial: np.ndarray, a: np.ndarray, b: np.ndarray,
               forward: np.ndarray, k: int) -> np.ndarray:
        """Cloth texture at surface points given their fraction `s` along the limb and
        offset `radial` from its axis: u runs around the limb, v along it."""
        axis = b - a
        length = float(np.linalg.norm(axis))
        e = axis / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
        ref = forward - (forward @ e) * e
        if np.linalg.norm(ref) < 0.3:  # limb along the forward axis: any perpendicular will do
            ref = np.cross(e, forward)
        ref /= np.linalg.norm(ref)
        angle = np.arctan2(radial @ np.cross(e, ref), radial @ ref)
        size = self.cloth_tex.shape[0]
        return self.cloth_tex.sample(angle * (size / (2 * np.pi)), s * length * size / 0.5 + 17 * k)
