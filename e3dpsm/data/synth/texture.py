"""Procedural grey-level textures (the event camera sees intensity only) and a wrapping
bilinear sampler. Textures are band-limited on purpose: detail finer than a few render
pixels would alias into flicker that a real lens and pixel area would blur away."""
from __future__ import annotations

import numpy as np


def sample_bilinear(tex: np.ndarray, u: np.ndarray, v: np.ndarray,
                    layer: np.ndarray | None = None) -> np.ndarray:
    """Sample `tex` [H, W] (or a stack [L, H, W] with a per-sample `layer`) at texel
    coordinates (u along W, v along H), wrapping around each texture's edges."""
    h, w = tex.shape[-2:]
    u0f, v0f = np.floor(u), np.floor(v)
    fu, fv = (u - u0f).astype(np.float32), (v - v0f).astype(np.float32)
    u0 = u0f.astype(np.int64) % w
    row0 = (v0f.astype(np.int64) % h) * w
    u1, row1 = (u0 + 1) % w, (row0 + w) % (h * w)
    if layer is not None:
        base = layer * (h * w)
        row0, row1 = row0 + base, row1 + base
    flat = tex.ravel()
    top = flat[row0 + u0] * (1 - fu) + flat[row0 + u1] * fu
    bottom = flat[row1 + u0] * (1 - fu) + flat[row1 + u1] * fu
    return top * (1 - fv) + bottom * fv


class WrappedTexture:
    """A texture (or a stack of same-sized layers) prepared for fast wrapping bilinear
    lookups: power-of-two sizes wrap with a bit mask, and one wrapped row and column of
    padding make the four taps fixed offsets from the first, so a lookup is integer
    arithmetic and four `take`s (about 3x faster than `sample_bilinear`)."""

    def __init__(self, tex: np.ndarray) -> None:
        stack = tex[None] if tex.ndim == 2 else tex
        _, h, w = stack.shape
        if h & (h - 1) or w & (w - 1):
            raise ValueError(f"texture size {h}x{w} is not a power of two")
        self.shape = (h, w)
        padded = np.concatenate([stack, stack[:, :1]], axis=1)
        padded = np.concatenate([padded, padded[:, :, :1]], axis=2)
        self._flat = np.ascontiguousarray(padded, dtype=np.float32).ravel()
        self._row, self._layer = w + 1, (h + 1) * (w + 1)

    def sample(self, u: np.ndarray, v: np.ndarray, layer: np.ndarray | None = None) -> np.ndarray:
        """Same as `sample_bilinear(tex, u, v, layer)`, in float32."""
        u = np.asarray(u, dtype=np.float32)
        v = np.asarray(v, dtype=np.float32)
        u0, v0 = np.floor(u), np.floor(v)
        fu, fv = u - u0, v - v0
        h, w = self.shape
        idx = (v0.astype(np.int32) & (h - 1)) * self._row
        idx += u0.astype(np.int32) & (w - 1)
        if layer is not None:
            idx += layer * self._layer
        flat = self._flat
        t00, t01 = flat.take(idx), flat.take(idx + 1)
        idx += self._row
        t10, t11 = flat.take(idx), flat.take(idx + 1)
        top = t00 + (t01 - t00) * fu
        bottom = t10 + (t11 - t10) * fu
        return top + (bottom - top) * fv


def value_noise(rng: np.random.Generator, size: int, cells: tuple[int, ...]) -> np.ndarray:
    """Sum of octaves of smoothly interpolated random lattices, scaled to [0, 1]; `cells`
    lists the lattice sizes (the coarsest first), each octave half the previous weight."""
    grid = np.arange(size, dtype=np.float64)
    uu, vv = np.meshgrid(grid, grid)
    out = np.zeros((size, size))
    for k, n in enumerate(cells):
        lattice = rng.uniform(size=(n, n))
        out += 0.5**k * sample_bilinear(lattice, uu * n / size, vv * n / size)
    out -= out.min()
    return (out / max(out.max(), 1e-9)).astype(np.float32)


def floor_texture(rng: np.random.Generator, size: int = 256, tiles: int = 4) -> np.ndarray:
    """Tiles with dark grout and per-tile brightness, over mottled noise."""
    tex = 0.65 + 0.15 * value_noise(rng, size, (8, 32))
    idx = np.arange(size) * tiles // size
    tex *= rng.uniform(0.85, 1.0, size=(tiles, tiles))[idx[:, None], idx[None, :]]
    grout = (np.arange(size) % (size // tiles)) < max(2, size // 128)
    tex[grout, :] *= 0.75
    tex[:, grout] *= 0.75
    return tex.astype(np.float32)


def wall_texture(rng: np.random.Generator, size: int = 256, n_boxes: int = 12) -> np.ndarray:
    """Plaster noise with rectangles standing for posters, doors and furniture."""
    tex = 0.55 + 0.2 * value_noise(rng, size, (4, 16))
    for _ in range(n_boxes):
        x0, y0 = rng.integers(0, size, 2)
        w, h = rng.integers(size // 16, size // 4, 2)
        ys, xs = np.arange(y0, y0 + h) % size, np.arange(x0, x0 + w) % size
        tex[np.ix_(ys, xs)] = rng.uniform(0.4, 0.8)
    return tex.astype(np.float32)


def cloth_texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    """Folds and stripes for clothing, mapped around and along each limb."""
    stripes = 0.5 + 0.5 * np.sin(np.arange(size) * 2 * np.pi * rng.integers(2, 6) / size)
    tex = 0.35 + 0.25 * value_noise(rng, size, (4, 8)) + 0.4 * stripes[:, None]
    return (tex / tex.max()).astype(np.float32)
