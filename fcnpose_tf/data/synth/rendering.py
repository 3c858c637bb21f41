"""The renderer: Blinn-Phong shading, a painter's algorithm over facets, the ray-cast room and soft shadows."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from fcnpose_tf.data.synth.camera import Camera
from fcnpose_tf.data.synth.kinematics import PI
from fcnpose_tf.data.synth.primitives import (Box, Light, Material, Part, Sphere, Tube, cross3, part_points,
                                              perpendicular)
from fcnpose_tf.data.synth.textures import floor_texture, wall_texture


def _shade(material: Material, normals: np.ndarray, points: np.ndarray, light: Light, eye: np.ndarray) -> np.ndarray:
    """Blinn-Phong colour (N x 3) of surface points with unit normals under the key + hemispheric light."""
    view = eye - points
    view /= np.linalg.norm(view, axis=-1, keepdims=True) + 1e-12
    ndl = np.clip(normals @ light.direction, 0.0, None)
    half = light.direction + view
    half /= np.linalg.norm(half, axis=-1, keepdims=True) + 1e-12
    spec = np.clip((normals * half).sum(-1), 0.0, None) ** material.shininess
    hemi = 0.55 + 0.45 * normals[..., 2]  # sky above, darker floor bounce below
    rim = np.clip(1.0 - (normals * view).sum(-1), 0.0, 1.0) ** 3  # a faint environment reflection at grazing
    col = material.rgb * (light.ambient * hemi + light.diffuse * ndl)[..., None] * light.color
    col = col + (material.specular * spec * light.diffuse)[..., None] * light.color + 0.08 * material.specular * rim[..., None]
    if light.fill > 0.0:
        fill = np.clip(normals @ light.fill_direction, 0.0, None)
        col = col + material.rgb * (light.fill * fill)[..., None] * light.fill_color
    return np.clip(col, 0.0, 1.5)


class Painter:
    """Painter's algorithm over facets: parts are cut into small planar facets (cylinder strips, caps, box
    faces, whole spheres), which are sorted by depth and drawn back to front onto a float RGB canvas and
    an integer label map. Sorting facets rather than whole parts keeps long links, joints that touch and
    a person next to the robot in the right order."""

    SEGMENT_LENGTH = 0.08  # m; longer cylinders are cut along their length too

    def __init__(self, canvas: np.ndarray, labels: np.ndarray, cam: Camera, light: Light, shift: int = 3,
                 depth: np.ndarray | None = None):
        self.canvas, self.labels, self.cam, self.light = canvas, labels, cam, light
        self.depth = depth  # optional float32 map of each pixel's facet depth (m), for occlusion tests
        self.shift = shift
        self.one = 1 << shift
        self.items: list[tuple[float, int, object, object, int]] = []

    def add(self, part: Part, min_depth: float = 0.0) -> None:
        """Queue a part's visible facets; `min_depth` pushes them back (drawn before nearer facets)."""
        if isinstance(part, Tube):
            self._tube(part, min_depth)
        elif isinstance(part, Sphere):
            self._sphere(part, min_depth)
        else:
            self._box(part, min_depth)

    def _fixed(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates as OpenCV's fixed-point integers (`shift` fractional bits)."""
        return np.round(uv * self.one).astype(np.int32)

    def _queue(self, depth: float, shape, color, label: int) -> None:
        """Queue a polygon (fixed-point int32 points) or a Sphere."""
        self.items.append((depth, len(self.items), shape, color, label))

    def flush(self) -> None:
        """Draw everything queued, farthest first."""
        self.items.sort(key=lambda it: (-it[0], it[1]))
        canvas, labels, depth, shift = self.canvas, self.labels, self.depth, self.shift
        for z, _, shape, color, label in self.items:
            if isinstance(shape, Sphere):
                self._draw_sphere(shape, label, z)
            else:
                cv2.fillConvexPoly(canvas, shape, color, cv2.LINE_8, shift)
                cv2.fillConvexPoly(labels, shape, label, cv2.LINE_8, shift)
                if depth is not None:
                    cv2.fillConvexPoly(depth, shape, z, cv2.LINE_8, shift)
        self.items.clear()

    def _tube(self, t: Tube, min_depth: float) -> None:
        axis = t.p1 - t.p0
        length = float(np.linalg.norm(axis))
        if length < 1e-6:
            return
        a = axis / length
        u = perpendicular(a, t.u)
        v = cross3(a, u)
        n = t.segments
        m = max(1, int(math.ceil(length / self.SEGMENT_LENGTH)))
        th = np.arange(n) * (2 * PI / n)
        s = np.linspace(0.0, 1.0, m + 1)
        rx = t.r0[0] + (t.r1[0] - t.r0[0]) * s
        ry = t.r0[1] + (t.r1[1] - t.r0[1]) * s
        rings = (t.p0 + s[:, None] * axis)[:, None, :] + (rx[:, None, None] * np.cos(th)[None, :, None] * u
                                                          + ry[:, None, None] * np.sin(th)[None, :, None] * v)
        uv, z = self.cam.project(rings.reshape(-1, 3))
        if z.min() < 0.05:
            return
        uv = uv.reshape(m + 1, n, 2)
        thm = th + PI / n
        rxm, rym = 0.5 * (t.r0[0] + t.r1[0]), 0.5 * (t.r0[1] + t.r1[1])
        radial = (np.cos(thm) / rxm)[:, None] * u + (np.sin(thm) / rym)[:, None] * v
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        normals = radial + ((max(t.r0) - max(t.r1)) / length) * a
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        nxt = np.roll(np.arange(n), -1)
        centres = 0.25 * (rings[:-1] + rings[:-1, nxt] + rings[1:] + rings[1:, nxt])  # m x n x 3
        visible = ((self.cam.eye - centres) * normals).sum(-1) > 0
        if visible.any():
            colors = _shade(t.material, np.broadcast_to(normals, centres.shape), centres, self.light, self.cam.eye)
            depth = np.maximum(self.cam.to_camera(centres.reshape(-1, 3))[:, 2].reshape(m, n), min_depth)
            label = int(t.label)
            quads = self._fixed(np.stack([uv[:-1], uv[:-1, nxt], uv[1:, nxt], uv[1:]], axis=2))  # m x n x 4 x 2
            colors = colors.tolist()
            depth = depth.tolist()
            for j, i in zip(*np.nonzero(visible)):
                self._queue(depth[j][i], quads[j, i], tuple(colors[j][i]), label)
        cap_mat = t.cap_material or t.material
        z = z.reshape(m + 1, n)
        for capped, centre, normal, end in ((t.caps[0], t.p0, -a, 0), (t.caps[1], t.p1, a, -1)):
            if capped and (self.cam.eye - centre) @ normal > 0:
                col = _shade(cap_mat, normal[None], centre[None], self.light, self.cam.eye)[0]
                # a joint's end cap hides whatever is attached behind its plane (the link leaving the
                # housing's side), so it sorts by its nearest rim point rather than its centre
                depth = float(z[end].min()) if t.cap_in_front else float(self.cam.to_camera(centre[None])[0, 2])
                depth = max(depth, min_depth)
                self._queue(depth, self._fixed(uv[end]), tuple(col.tolist()), int(t.label))

    def _sphere(self, sp: Sphere, min_depth: float) -> None:
        depth = float(self.cam.to_camera(sp.centre[None])[0, 2])
        if depth > sp.radius + 0.05:
            self._queue(max(depth, min_depth), sp, None, int(sp.label))

    def _draw_sphere(self, sp: Sphere, label: int, z: float) -> None:
        pc = self.cam.to_camera(sp.centre[None])[0]
        K = self.cam.K
        cu, cv_ = K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2]
        rad = K[0, 0] * sp.radius / math.sqrt(max(pc @ pc - sp.radius ** 2, 1e-9))
        H, W = self.labels.shape
        x0, x1 = max(0, int(cu - rad - 1)), min(W, int(cu + rad + 2))
        y0, y1 = max(0, int(cv_ - rad - 1)), min(H, int(cv_ + rad + 2))
        if x0 >= x1 or y0 >= y1:
            return
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        dx, dy = (xx - cu) / rad, (yy - cv_) / rad
        r2 = dx * dx + dy * dy
        inside = r2 <= 1.0
        if not inside.any():
            return
        nz = -np.sqrt(np.clip(1.0 - r2[inside], 0.0, 1.0))
        n_world = np.stack([dx[inside], dy[inside], nz], 1) @ self.cam.R
        points = sp.centre + sp.radius * n_world
        self.canvas[y0:y1, x0:x1][inside] = _shade(sp.material, n_world, points, self.light, self.cam.eye)
        self.labels[y0:y1, x0:x1][inside] = label
        if self.depth is not None:
            self.depth[y0:y1, x0:x1][inside] = z

    _FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
    _FACE_AXIS = ((0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1))

    def _box(self, b: Box, min_depth: float) -> None:
        corners = b.corners()
        uv, z = self.cam.project(corners)
        if z.min() < 0.05:
            return
        for face, (ax, sign) in zip(self._FACES, self._FACE_AXIS):
            normal = sign * b.axes[:, ax] / np.linalg.norm(b.axes[:, ax])
            centre = b.centre + sign * b.axes[:, ax]
            if (self.cam.eye - centre) @ normal <= 0:
                continue
            mat = b.top_material if (b.top_material is not None and normal[2] > 0.9) else b.material
            col = _shade(mat, normal[None], centre[None], self.light, self.cam.eye)[0]
            depth = max(float(self.cam.to_camera(centre[None])[0, 2]), min_depth)
            if b.edges:  # a darker rim, as real edges and seams catch less light
                self._queue(depth, self._fixed(uv[list(face)]), tuple((col * 0.7).tolist()), int(b.label))
                inner = (corners[list(face)] - centre) * 0.97 + centre
                self._queue(depth - 1e-4, self._fixed(self.cam.project(inner)[0]), tuple(col.tolist()), int(b.label))
            else:
                self._queue(depth, self._fixed(uv[list(face)]), tuple(col.tolist()), int(b.label))


@dataclass
class Room:
    """An axis-aligned room: floor z = 0, walls at x/y limits, ceiling at `height`."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    height: float


def render_background(rng: np.random.Generator, cam: Camera, room: Room, light: Light,
                       lamp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast floor, walls and ceiling: (H x W x 3 float32 RGB, H x W float32 floor mask)."""
    W, H = cam.width, cam.height
    K, R = cam.K, cam.R.astype(np.float32)
    a = ((np.arange(W, dtype=np.float32) - K[0, 2]) / K[0, 0])[None, :]
    b = ((np.arange(H, dtype=np.float32) - K[1, 2]) / K[1, 1])[:, None]
    d = [R[0, i] * a + R[1, i] * b + R[2, i] for i in range(3)]  # world ray directions, per pixel
    e = cam.eye.astype(np.float32)
    big = np.float32(1e6)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ts = []
        for i, (lo, hi) in enumerate(((room.xmin, room.xmax), (room.ymin, room.ymax), (0.0, room.height))):
            t = np.where(d[i] > 0, (hi - e[i]) / d[i], (lo - e[i]) / d[i])
            ts.append(np.where(np.isfinite(t) & (t > 0), t, big).astype(np.float32))
    # surface id: 0 floor, 1 ceiling, 2 wall x=xmin, 3 wall x=xmax, 4 wall y=ymin, 5 wall y=ymax
    hit_z = ts[2] <= np.minimum(ts[0], ts[1])
    wall_x = ~hit_z & (ts[0] <= ts[1])
    t = np.minimum(np.minimum(ts[0], ts[1]), ts[2])
    p = [e[i] + t * d[i] for i in range(3)]
    surf = np.where(hit_z, np.where(d[2] < 0, 0, 1),
                    np.where(wall_x, np.where(d[0] < 0, 2, 3), np.where(d[1] < 0, 4, 5))).astype(np.uint8)
    present = np.bincount(surf.ravel(), minlength=6) > 0
    wall_seeds = rng.integers(0, 2 ** 63, size=4)
    out = np.zeros((H, W, 3), np.float32)

    ppm_floor, size = 64.0, 256  # 4 m of floor, tiled
    floor_tex = floor_texture(rng, size, ppm_floor)
    floor = (surf == 0).astype(np.uint8)
    if present[0]:
        mx = np.mod(p[0] * ppm_floor, size).astype(np.float32)
        my = np.mod(p[1] * ppm_floor, size).astype(np.float32)
        cv2.copyTo(cv2.remap(floor_tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP), floor, out)
    ceiling_rgb = np.array([0.85, 0.85, 0.83], np.float32) * rng.uniform(0.8, 1.0)
    if present[1]:
        panel = (np.mod(p[0], 1.2) < 0.6) & (np.mod(p[1], 2.4) < 1.2)
        ceil = np.where(panel[..., None], np.float32(1.3), ceiling_rgb).astype(np.float32)
        cv2.copyTo(ceil, (surf == 1).astype(np.uint8), out)
    ppm_wall = 64.0
    for k, (coord, lo, hi) in enumerate(((1, room.ymin, room.ymax), (1, room.ymin, room.ymax),
                                         (0, room.xmin, room.xmax), (0, room.xmin, room.xmax))):
        if not present[2 + k]:
            continue
        tex = wall_texture(np.random.default_rng(int(wall_seeds[k])), hi - lo, room.height, ppm_wall)
        mx = ((p[coord] - lo) * ppm_wall).astype(np.float32)
        my = (tex.shape[0] - p[2] * ppm_wall).astype(np.float32)
        cv2.copyTo(cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
                   (surf == 2 + k).astype(np.uint8), out)
    # light: key light (constant per surface) + a ceiling lamp's falloff + darker corners
    normals = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float32)
    per_surface = light.ambient * (0.75 + 0.25 * normals[:, 2]) + light.diffuse * 0.8 * np.clip(
        normals @ light.direction.astype(np.float32), 0, None)
    lx, ly, lz = lamp.astype(np.float32)
    lamp_term = 1.0 / (1.0 + ((p[0] - lx) ** 2 + (p[1] - ly) ** 2 + (p[2] - lz) ** 2) / 9.0)
    corner = np.minimum(np.minimum(p[0] - room.xmin, room.xmax - p[0]), np.minimum(p[1] - room.ymin, room.ymax - p[1]))
    corner = np.minimum(corner, np.where(floor > 0, big, p[2]))
    ao = 1.0 - 0.3 * np.exp(-np.clip(corner, 0, None) / 0.3)
    shade = per_surface.astype(np.float32)[surf] * (0.55 + 0.8 * lamp_term) * ao
    filled = None
    if light.fill > 0.0:  # the fill light's share per surface, in its own colour
        fill = (light.fill * 0.8 * np.clip(normals @ light.fill_direction.astype(np.float32), 0, None))[surf] * ao
        filled = out * fill[..., None] * light.fill_color.astype(np.float32)
    out *= shade[..., None]
    out *= light.color.astype(np.float32)
    if filled is not None:
        out += filled
    return out, floor.astype(np.float32)


def shadow_mask(parts: Sequence[Part], light: Light, cam: Camera, shape: tuple[int, int]) -> np.ndarray:
    """Soft shadows (0..1, H x W float32) that `parts` cast on the floor plane along the key light."""
    mask = np.zeros(shape, np.uint8)
    l = light.direction
    for part in parts:
        pts = part_points(part)
        ground = pts - (pts[:, 2] / max(l[2], 0.2))[:, None] * l
        uv, z = cam.project(ground)
        if z.min() < 0.05:
            continue
        hull = cv2.convexHull(np.round(uv * 8).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 255, cv2.LINE_8, 3)
    sigma = max(1.0, 0.006 * shape[1])
    return cv2.GaussianBlur(mask.astype(np.float32) / 255.0, (0, 0), sigma)
