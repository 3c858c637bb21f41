"""Procedural floor and wall textures (concrete, tiles, wood, paint, brick, with doors, windows, shelves)."""

from __future__ import annotations

import cv2
import numpy as np


def _noise(rng: np.random.Generator, shape: tuple[int, int], cell: float) -> np.ndarray:
    """Smooth value noise (~N(0, 1)) with features about `cell` texels across."""
    h, w = shape
    gh, gw = max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)
    grid = rng.standard_normal((gh, gw), dtype=np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def _fractal(rng, shape, cells=(64, 16, 4), weights=(1.0, 0.5, 0.25)) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for c, wt in zip(cells, weights):
        out += wt * _noise(rng, shape, c)
    return out


def floor_texture(rng: np.random.Generator, size: int, ppm: float) -> np.ndarray:
    """A size x size RGB texture covering size/ppm metres of floor (tiles seamlessly every few metres)."""
    kind = rng.choice(["concrete", "concrete", "concrete", "epoxy", "epoxy", "tiles", "tiles", "wood", "wood", "vinyl",
                       "checker"])
    shape = (size, size)
    if kind == "concrete":
        base = np.full(3, rng.uniform(0.42, 0.68)) * (1 + rng.normal(0, 0.03, 3))
        tex = base * (1 + 0.07 * _fractal(rng, shape)[..., None])
        tex *= 1 - 0.12 * np.clip(_noise(rng, shape, 90), 0, None)[..., None]
        step = int(ppm * rng.choice([1.0, 2.0, 4.0])) or size
        tex[::step, :] *= 0.6
        tex[:, ::step] *= 0.6
    elif kind == "epoxy":
        base = [np.array([0.45, 0.52, 0.45]), np.array([0.42, 0.47, 0.55]), np.array([0.58, 0.58, 0.56]),
                np.array([0.55, 0.33, 0.28]), np.array([0.35, 0.42, 0.35])][rng.integers(5)]
        tex = base * (1 + 0.04 * _fractal(rng, shape, (48, 8, 2))[..., None])
        tex += 0.05 * (rng.random(shape, dtype=np.float32) > 0.97)[..., None]
    elif kind == "tiles":
        n_tiles = int(rng.choice([5, 8, 10, 16]))
        cell = (np.arange(size) * n_tiles) // size
        base = np.full(3, rng.uniform(0.5, 0.85)) * (1 + rng.normal(0, 0.05, 3))
        tone = 1 + rng.normal(0, 0.04, (n_tiles, n_tiles)).astype(np.float32)
        tex = base * tone[cell[:, None], cell[None, :]][..., None]
        tex *= 1 + 0.025 * _fractal(rng, shape, (32, 6))[..., None]
        edge = np.flatnonzero(np.diff(cell, prepend=-1))
        g = max(1, size // n_tiles // 40)
        grout = rng.uniform(0.3, 0.9) * base
        for i in edge:
            tex[i:i + g, :] = grout
            tex[:, i:i + g] = grout
    elif kind == "wood":
        n_planks = int(rng.choice([20, 25, 32, 40]))
        cell = (np.arange(size) * n_planks) // size
        base = np.array([0.62, 0.45, 0.28]) * rng.uniform(0.6, 1.15)
        grain = cv2.resize(rng.standard_normal((size // 2, 12), dtype=np.float32), (size, size),
                           interpolation=cv2.INTER_CUBIC)
        tone = (1 + rng.normal(0, 0.08, n_planks).astype(np.float32))[cell]
        tex = base * (tone[:, None] * (1 + 0.06 * grain))[..., None]
        edge = np.flatnonzero(np.diff(cell, prepend=-1))
        tex[edge, :] *= 0.55
        for lo, hi in zip(edge, list(edge[1:]) + [size]):
            cut = int(rng.integers(0, size))
            tex[lo:hi, cut:cut + 2] *= 0.6
        if rng.random() < 0.5:
            tex = np.ascontiguousarray(tex.transpose(1, 0, 2))
    elif kind == "vinyl":
        base = np.clip(np.array([0.75, 0.74, 0.70]) * (1 + rng.normal(0, 0.06, 3)), 0, 1)
        tex = base * (1 + 0.05 * _fractal(rng, shape, (24, 6, 2))[..., None])
        tex += 0.08 * (rng.random(shape, dtype=np.float32) > 0.985)[..., None] * (rng.random(3) - 0.5)
    else:  # checker lab floor
        n = int(rng.choice([8, 10, 16]))
        cell = (np.arange(size) * n) // size
        a, b = np.full(3, rng.uniform(0.06, 0.2)), np.full(3, rng.uniform(0.65, 0.85))
        ii = cell[:, None] + cell[None, :]
        tex = np.where((ii % 2 == 0)[..., None], a, b) * (1 + 0.03 * _fractal(rng, shape, (32, 4))[..., None])
    return np.clip(tex, 0, 1).astype(np.float32)


_WALL_PAINT = np.array([[0.92, 0.91, 0.88], [0.88, 0.86, 0.78], [0.78, 0.80, 0.80], [0.70, 0.78, 0.85],
                        [0.74, 0.84, 0.74], [0.90, 0.84, 0.62], [0.62, 0.64, 0.66], [0.85, 0.75, 0.72],
                        [0.55, 0.62, 0.72], [0.95, 0.95, 0.95]])


def wall_texture(rng: np.random.Generator, length: float, height: float, ppm: float) -> np.ndarray:
    """RGB texture of one wall (length x height m): paint, brick or block, plus doors, windows, boards, shelves."""
    w, h = max(8, int(length * ppm)), max(8, int(height * ppm))
    kind = rng.choice(["paint", "paint", "paint", "brick", "block", "panel"])
    if kind == "brick":
        base = [np.array([0.62, 0.30, 0.22]), np.array([0.80, 0.78, 0.74]), np.array([0.55, 0.42, 0.35])][
            rng.integers(3)]
        bw, bh = int(0.23 * ppm), int(0.075 * ppm)
        rows = h // bh + 1
        cols = w // bw + 2
        tone = 1 + rng.normal(0, 0.07, (rows, cols)).astype(np.float32)
        tex = np.empty((h, w, 3), np.float32)
        for r in range(rows):
            off = (bw // 2) * (r % 2)
            line = np.repeat(tone[r], bw)[off:off + w]
            tex[r * bh:(r + 1) * bh] = base * line[None, :, None]
        mortar = np.array([0.75, 0.74, 0.70]) * rng.uniform(0.6, 1.0)
        tex[::bh] = mortar
        for r in range(rows):
            off = (bw // 2) * (r % 2)
            tex[r * bh:(r + 1) * bh, (bw - off) % bw::bw] = mortar
    elif kind == "block":
        base = np.full(3, rng.uniform(0.55, 0.8)) * (1 + rng.normal(0, 0.03, 3))
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        bw, bh = int(0.4 * ppm), int(0.2 * ppm)
        tex[::bh] *= 0.75
        for r in range(h // bh + 1):
            off = (bw // 2) * (r % 2)
            tex[r * bh:(r + 1) * bh, off::bw] *= 0.75
    elif kind == "panel":
        base = [np.array([0.80, 0.80, 0.78]), np.array([0.65, 0.50, 0.35]), np.array([0.55, 0.60, 0.62])][
            rng.integers(3)]
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        step = int(rng.uniform(0.6, 1.25) * ppm)
        tex[:, ::step] *= 0.6
    else:
        base = _WALL_PAINT[rng.integers(len(_WALL_PAINT))] * (1 + rng.normal(0, 0.03, 3))
        tex = np.broadcast_to(base, (h, w, 3)).astype(np.float32).copy()
        if rng.random() < 0.35:  # two-tone wall
            band = int(rng.uniform(0.9, 1.3) * ppm)
            tex[h - band:] = _WALL_PAINT[rng.integers(len(_WALL_PAINT))] * 0.85
    tex *= 1 + 0.03 * _fractal(rng, (h, w), (48, 12))[..., None]

    def rect(x0, y0, x1, y1, color, edge=None):
        """A rectangle in metres from the wall's left end and from the floor."""
        p0 = (int(x0 * ppm), int(h - y1 * ppm))
        p1 = (int(x1 * ppm), int(h - y0 * ppm))
        cv2.rectangle(tex, p0, p1, tuple(float(c) for c in color), -1)
        if edge is not None:
            cv2.rectangle(tex, p0, p1, tuple(float(c) for c in edge), max(1, int(0.02 * ppm)))

    x = rng.uniform(0.0, 1.0)
    while x < length - 0.5:
        kind = rng.choice(["door", "window", "board", "poster", "shelf", "pegboard", "cabinet", "gap", "gap"])
        if kind == "door" and height > 2.3:
            wd = rng.uniform(0.85, 1.6)
            col = rng.uniform(0.2, 0.9, 3)
            rect(x, 0.0, x + wd, 2.1, col, col * 0.6)
            cv2.circle(tex, (int((x + wd - 0.1) * ppm), int(h - 1.0 * ppm)), max(1, int(0.03 * ppm)),
                       (0.7, 0.7, 0.7), -1)
            x += wd
        elif kind == "window" and height > 2.2:
            wd = rng.uniform(0.8, 2.5)
            y0 = rng.uniform(0.9, 1.2)
            y1 = min(height - 0.2, y0 + rng.uniform(0.8, 1.4))
            sky = np.array([0.85, 0.9, 0.97]) * rng.uniform(0.9, 1.1)
            rect(x, y0, x + wd, y1, sky, (0.3, 0.3, 0.32) if rng.random() < 0.5 else (0.9, 0.9, 0.9))
            xm = int((x + wd / 2) * ppm)
            cv2.line(tex, (xm, int(h - y1 * ppm)), (xm, int(h - y0 * ppm)), (0.5, 0.5, 0.5), max(1, int(0.03 * ppm)))
            x += wd
        elif kind in ("board", "poster"):
            wd = rng.uniform(0.4, 1.8) if kind == "board" else rng.uniform(0.3, 0.7)
            ht = rng.uniform(0.4, 1.1)
            y0 = rng.uniform(0.9, 1.4)
            col = np.array([0.93, 0.93, 0.92]) if kind == "board" else rng.uniform(0.1, 0.95, 3)
            rect(x, y0, x + wd, y0 + ht, col, (0.4, 0.4, 0.42))
            for k in range(int(rng.integers(0, 7))):  # writing / print lines
                yy = y0 + ht * (0.85 - 0.12 * k)
                if yy <= y0 + 0.05:
                    break
                rect(x + 0.05, yy, x + 0.05 + rng.uniform(0.1, wd - 0.1), yy + 0.015, rng.uniform(0, 0.6, 3))
            x += wd
        elif kind == "shelf":
            wd = rng.uniform(0.8, 2.0)
            for level in np.arange(rng.uniform(0.4, 0.8), min(height - 0.3, 2.2), rng.uniform(0.35, 0.5)):
                xx = x
                while xx < x + wd - 0.15:
                    bw = rng.uniform(0.1, 0.4)
                    rect(xx, level, min(xx + bw, x + wd), level + rng.uniform(0.1, 0.3), rng.uniform(0.1, 0.9, 3))
                    xx += bw + rng.uniform(0.0, 0.15)
                rect(x, level - 0.03, x + wd, level, (0.3, 0.3, 0.32))
            x += wd
        elif kind == "pegboard":
            wd, y0, ht = rng.uniform(0.8, 1.6), rng.uniform(0.9, 1.1), rng.uniform(0.6, 1.0)
            rect(x, y0, x + wd, y0 + ht, np.array([0.75, 0.6, 0.42]) * rng.uniform(0.8, 1.1))
            for k in range(int(rng.integers(3, 9))):
                tx = x + rng.uniform(0.05, wd - 0.05)
                ty = y0 + rng.uniform(0.1, ht - 0.1)
                rect(tx, ty - rng.uniform(0.05, 0.25), tx + rng.uniform(0.02, 0.05), ty, rng.uniform(0, 0.9, 3))
            x += wd
        elif kind == "cabinet":
            wd = rng.uniform(0.4, 0.8)
            ht = rng.uniform(0.5, 0.9)
            y0 = rng.uniform(1.2, 1.6)
            rect(x, y0, x + wd, y0 + ht, np.array([0.78, 0.78, 0.76]) * rng.uniform(0.8, 1.05), (0.3, 0.3, 0.3))
            x += wd
        x += rng.uniform(0.2, 1.5)
    skirting = rng.uniform(0.0, 0.12)
    if skirting > 0.03:
        rect(0, 0, length, skirting, np.full(3, rng.uniform(0.1, 0.6)))
    return np.clip(tex, 0, 1).astype(np.float32)
