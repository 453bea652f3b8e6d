"""Procedural solid textures for the synthetic environments and objects, deterministic from a seed.

Every texture is an `Albedo` (``shapes.py``): a function of the 3D hit point (object frame), so it
needs no UVs and looks the same from every view. Building blocks (`Noise`, one seeded table each):

- lattice value noise ``noise(p, cell)``: a periodic 64³ table of uniform [0, 1] values, seeded,
  sampled trilinearly (periodic) at ``R p / cell``;
  ``R`` is a fixed random rotation per call site (``octave``) so the lattice axes and its 64-cell
  period never line up with the scene's planes;
- ``fbm(p, cell, octaves)`` = Σₖ 0.5ᵏ noise(p, cell / 2ᵏ) / Σₖ 0.5ᵏ (fractal sum, in [0, 1]);
  ``fade`` (optional) multiplies octave k by ``clip(2 - |p_xy| k_fade / cell_k, 0, 1)`` so octaves
  finer than about ``|p_xy| / fade`` vanish far from the scene centre: a view-independent
  band limit (like a mip-map chosen by distance) that keeps far ground and backdrops from aliasing;
- ``cell_random(i)``: a uniform [0, 1] value per integer cell (the table at ``i mod 64``), used
  for per-tile, per-plank and per-brick colours.

Patterns (two in-plane coordinates ``u, v`` chosen by the caller, e.g. x, y on a floor): ``wood``
(planks along u of width ``plank`` with dark gaps; growth rings = bands of the distance to a
per-plank axis, warped by fbm; fine streaks = noise stretched 12x along u), ``tiles`` (square tiles with
grout lines, per-tile tint, fbm), ``bricks`` (running bond: rows of height ``h``, every other row
shifted by half a brick, mortar lines, per-brick tint), ``plaster`` (fbm of three octave groups),
``ground`` (cobbles: jittered-cell paving stones with dark joints, per-stone tint and fbm, band
limited with distance), ``facade`` (plaster or brick walls with a grid of dark windows, gravel
roofs), ``sky`` (a dome: gradient + fbm clouds above a mountain silhouette of fbm height in
azimuth), ``fine`` (a 2 mm-class pattern: crossed sine hatching times fine noise) and ``glaze``
(horizontal bands with speckles).
"""

from __future__ import annotations

import numpy as np

TABLE_SIZE = 64
MASK = TABLE_SIZE - 1


class Noise:
    """Seeded lattice noise (see the module docstring)."""

    def __init__(self, seed: int):
        rng = np.random.default_rng(seed)
        self.table = rng.uniform(0.0, 1.0, size=(TABLE_SIZE,) * 3).astype(np.float32)
        self.flat = self.table.ravel()
        self.rotations = [_random_rotation(rng) for _ in range(16)]

    def noise(self, points: np.ndarray, cell: float, octave: int = 0) -> np.ndarray:
        r = self.rotations[octave % 16] / cell
        x, y, z = _columns(points)
        corners = []
        for row, stride in zip(r, (TABLE_SIZE * TABLE_SIZE, TABLE_SIZE, 1)):
            q = x * row[0] + y * row[1] + z * row[2]
            i = np.floor(q)
            f = (q - i).astype(np.float32)
            i = i.astype(np.int32) & MASK
            corners.append((i * stride, ((i + 1) & MASK) * stride, f))
        (x0, x1, fx), (y0, y1, fy), (z0, z1, fz) = corners
        t = self.flat

        def lerp_z(base):
            v0 = np.take(t, base + z0)
            return v0 + (np.take(t, base + z1) - v0) * fz

        a = lerp_z(x0 + y0)
        a += (lerp_z(x0 + y1) - a) * fy
        b = lerp_z(x1 + y0)
        b += (lerp_z(x1 + y1) - b) * fy
        return (a + (b - a) * fx).astype(np.float64)

    def fbm(self, points: np.ndarray, cell: float, octaves: int = 4, fade: float | None = None) -> np.ndarray:
        total, norm = np.zeros(len(points)), 0.0
        reach = None if fade is None else np.linalg.norm(np.asarray(points)[:, :2], axis=1)
        for k in range(octaves):
            amp, c = 0.5**k, cell / 2**k
            value = self.noise(points, c, k)
            if reach is not None:
                weight = np.clip(2.0 - reach * fade / c, 0.0, 1.0)
                value = 0.5 + (value - 0.5) * weight
            total += amp * value
            norm += amp
        return total / norm

    def cell_random(self, *indices: np.ndarray) -> np.ndarray:
        idx = [np.mod(np.asarray(i, dtype=np.int64), TABLE_SIZE) for i in indices]
        while len(idx) < 3:
            idx.append(np.full_like(idx[0], 7 * len(idx)))
        return self.table[idx[0], idx[1], idx[2]].astype(np.float64)


def _columns(points: np.ndarray):
    """x, y, z as contiguous float64 arrays (strided column access is several times slower)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).T)
    return p[0], p[1], p[2]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _mix(a, b, t):
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a + (b - a) * np.asarray(t)[:, None]


def _line(coord: np.ndarray, width: float) -> np.ndarray:
    """1 on a line of the given width (in cell units) at every integer of ``coord``, else 0, smooth edges."""
    d = np.abs(coord - np.round(coord))
    return np.clip((width - d) / (0.35 * width) + 0.5, 0.0, 1.0)


def _axes(points, axes):
    return points[:, axes[0]], points[:, axes[1]]


def wood(seed: int, light=(0.78, 0.56, 0.34), dark=(0.42, 0.25, 0.12), plank=0.25, ring=0.03, axes=(0, 1)):
    """Planked wood (see the module docstring); ``plank`` and ``ring`` in object units."""
    n = Noise(seed)

    def albedo(points, tri, bary):
        u, v = _axes(points, axes)
        k = np.floor(v / plank)
        r0 = n.cell_random(k, np.zeros_like(k)) * 2.0 + 0.5
        shift = n.cell_random(k, np.ones_like(k)) * 10.0
        dist = np.hypot((v / plank - k - 0.5) * plank, r0 * plank) + 0.15 * plank * n.fbm(points, 2 * plank, 3)
        rings = 0.5 + 0.5 * np.cos(2 * np.pi * (dist / ring + 0.3 * np.sin(u * 3.0 + shift)))
        streak = n.noise(np.stack([u / 12.0, v, points[:, 2]], axis=1), ring / 6, 5)
        t = np.clip(0.55 * rings + 0.45 * streak, 0.0, 1.0) ** 1.3
        tint = 0.85 + 0.3 * n.cell_random(k, np.full_like(k, 2))
        gap = _line(v / plank, 0.012)
        color = _mix(light, dark, t) * tint[:, None]
        return np.clip(color * (1.0 - 0.7 * gap)[:, None], 0.0, 1.0)

    return albedo


def tiles(seed: int, base=(0.7, 0.68, 0.62), accent=(0.35, 0.42, 0.5), tile=0.4, grout=0.03, axes=(0, 1)):
    """Square tiles of side ``tile`` with grout lines of width ``grout`` (fraction of a tile)."""
    n = Noise(seed)

    def albedo(points, tri, bary):
        u, v = _axes(points, axes)
        iu, iv = np.floor(u / tile), np.floor(v / tile)
        pick = n.cell_random(iu, iv) > 0.7
        color = np.where(pick[:, None], np.asarray(accent, float), np.asarray(base, float))
        color = color * (0.8 + 0.3 * n.cell_random(iu + 17, iv))[:, None]
        color = color * (0.75 + 0.5 * n.fbm(points, tile / 3, 4))[:, None]
        g = np.maximum(_line(u / tile, grout), _line(v / tile, grout))
        return np.clip(_mix(color, (0.2, 0.19, 0.18), g), 0.0, 1.0)

    return albedo


def bricks(seed: int, brick=(0.25, 0.08), color=(0.62, 0.3, 0.2), mortar=(0.78, 0.76, 0.7), axes=(0, 2)):
    """Running-bond bricks ``brick`` = (width, height) with mortar lines."""
    n = Noise(seed)
    w, h = brick

    def albedo(points, tri, bary):
        u, v = _axes(points, axes)
        row = np.floor(v / h)
        s = u / w + 0.5 * (row % 2)
        col = np.floor(s)
        tint = 0.7 + 0.5 * n.cell_random(col, row)
        c = np.asarray(color, float) * tint[:, None] * (0.8 + 0.4 * n.fbm(points, h / 2, 3))[:, None]
        m = np.maximum(_line(s, 0.04), _line(v / h, 0.09))
        return np.clip(_mix(c, mortar, m), 0.0, 1.0)

    return albedo


def plaster(seed: int, color=(0.85, 0.83, 0.78), cell=0.3, contrast=0.5):
    """Plaster / wallpaper: fbm at three scales around ``cell``."""
    n = Noise(seed)

    def albedo(points, tri, bary):
        f = 0.5 * n.fbm(points, cell, 3) + 0.5 * n.fbm(points, cell / 12, 3)
        return np.clip(np.asarray(color, float) * (1.0 - contrast / 2 + contrast * f)[:, None], 0.0, 1.0)

    return albedo


def ground(seed: int, stone=0.12, light=(0.62, 0.58, 0.5), dark=(0.38, 0.36, 0.3), fade: float | None = 0.08):
    """Cobblestone paving in the xy plane: jittered square stones of side ``stone``, band limited by distance."""
    n = Noise(seed)

    def albedo(points, tri, bary):
        u, v = points[:, 0] / stone, points[:, 1] / stone
        row = np.floor(v)
        s = u + 0.5 * n.cell_random(row, np.full_like(row, 5))
        col = np.floor(s)
        t = n.cell_random(col, row)
        c = _mix(light, dark, t) * (0.7 + 0.6 * n.fbm(points, stone / 2, 5, fade=fade))[:, None]
        joint = np.maximum(_line(s, 0.05), _line(v, 0.05))
        if fade is not None:
            reach = np.linalg.norm(points[:, :2], axis=1)
            joint = joint * np.clip(2.0 - reach * fade / (0.1 * stone), 0.0, 1.0)
        return np.clip(_mix(c, (0.15, 0.14, 0.12), 0.8 * joint), 0.0, 1.0)

    return albedo


def facade(seed: int, normals: np.ndarray, color=(0.8, 0.72, 0.6), window=(0.1, 0.12), floor_height=0.2, brick=False):
    """Walls of axis-aligned blocks: plaster or bricks with a grid of dark windows; roofs (triangles
    whose unit ``normals`` have z > 0.7) are gravel (fbm).

    The horizontal wall coordinate is ``x + y`` (on a face x = const it runs along y, on y = const
    along x), so one function serves every vertical face of an axis-aligned box.
    """
    n = Noise(seed)
    wall = bricks(seed + 1, brick=(floor_height / 5, floor_height / 12), color=color) if brick else plaster(seed + 1, color, 0.2)
    roof = plaster(seed + 2, (0.45, 0.42, 0.4), 0.02, contrast=0.9)

    def albedo(points, tri, bary):
        u, v = points[:, 0] + points[:, 1], points[:, 2]
        c = wall(np.stack([u, points[:, 1], v], axis=1), tri, bary)
        fu, fv = u / (2 * window[0]), v / floor_height
        inside = (np.abs(fu - np.floor(fu) - 0.5) < 0.25) & (np.abs(fv - np.floor(fv) - 0.55) < window[1] / floor_height / 2)
        glass = np.asarray((0.18, 0.22, 0.28)) * (0.6 + 0.8 * n.cell_random(np.floor(fu), np.floor(fv)))[:, None]
        c = np.where(inside[:, None], glass, c)
        up = normals[tri, 2] > 0.7
        if np.any(up):
            c[up] = roof(points[up], tri[up], bary[up])
        return c

    return albedo


def sky(seed: int, centre=(0.0, 0.0, 0.0)):
    """A dome seen from inside: mountains (fbm height in azimuth) below, sky with fbm clouds above."""
    n = Noise(seed)
    c0 = np.asarray(centre, dtype=np.float64)

    def albedo(points, tri, bary):
        d = points - c0
        rho = np.linalg.norm(d, axis=1)
        elev = np.arcsin(np.clip(d[:, 2] / rho, -1.0, 1.0))
        az = np.arctan2(d[:, 1], d[:, 0])
        ring = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], axis=1)
        peak = 0.05 + 0.16 * n.fbm(ring, 0.5, 5)
        rock = _mix((0.3, 0.3, 0.3), (0.6, 0.57, 0.52), n.fbm(d / rho[:, None], 0.02, 4))
        rock = _mix(rock, (0.62, 0.67, 0.74), np.full(len(rock), 0.3))  # aerial haze
        snow = np.clip((elev - peak + 0.04) / 0.02, 0, 1) * (peak > 0.14)
        rock = _mix(rock, (0.92, 0.93, 0.95), snow)
        blue = _mix((0.62, 0.74, 0.9), (0.3, 0.45, 0.78), np.clip(elev / 1.2, 0, 1))
        cloud = np.clip((n.fbm(d / rho[:, None] * np.array([1.0, 1.0, 3.0]), 0.15, 5) - 0.45) * 3.0, 0, 1)
        air = _mix(blue, (0.95, 0.95, 0.96), cloud)
        return np.where((elev < peak)[:, None], rock, air)

    return albedo


def fine(seed: int, base=(0.86, 0.8, 0.66), ink=(0.2, 0.24, 0.42), period=0.02):
    """High-frequency pattern: crossed sine hatching of ``period`` (object units) times fine noise."""
    n = Noise(seed)
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(3, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)

    def albedo(points, tri, bary):
        waves = np.sin(2 * np.pi * points @ dirs.T / (period * np.array([1.0, 1.3, 0.8])))
        hatch = np.clip(0.5 + 0.8 * waves[:, 0] * waves[:, 1] + 0.3 * waves[:, 2], 0.0, 1.0)
        speck = n.noise(points, period / 2.5, 3)
        t = np.clip(0.7 * hatch + 0.5 * (speck - 0.5), 0.0, 1.0)
        return np.clip(_mix(base, ink, t), 0.0, 1.0)

    return albedo


def glaze(seed: int, base=(0.3, 0.5, 0.62), band=(0.88, 0.82, 0.7), period=0.08):
    """Ceramic glaze: horizontal colour bands of ``period`` (warped by fbm) with dark speckles."""
    n = Noise(seed)

    def albedo(points, tri, bary):
        z = points[:, 2] / period + 0.6 * n.fbm(points, 0.2, 3)
        t = np.clip(0.5 + 1.5 * np.sin(2 * np.pi * z), 0.0, 1.0)
        speck = np.clip((n.noise(points, 0.006, 2) - 0.72) * 5.0, 0.0, 1.0)
        c = _mix(base, band, t) * (0.85 + 0.3 * n.fbm(points, 0.05, 3))[:, None]
        return np.clip(_mix(c, (0.1, 0.08, 0.07), speck), 0.0, 1.0)

    return albedo
