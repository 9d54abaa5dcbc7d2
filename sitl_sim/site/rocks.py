"""Rocks: faceted stones, each the intersection of planes tangent to a random ellipsoid.

A rock of height ``h`` stands on its base (the ground under its centre) with horizontal
semi-axes ``a`` (1.1-1.8 x ``h``) and ``b`` (0.65-1 x ``a``) turned to a random yaw; twelve planes
tangent to that ellipsoid cut it (six around its foot, five on its shoulders, one on its top, each
at a random place), so it has flat facets and straight edges — what a stone looks like from above
under a low sun — and stays convex: the height over a point is the lowest of the facet planes
there, a ray meets it where it enters all their half-spaces (Cyrus-Beck), both exact and cheap.

Local coordinates: x north, y east, z up from the base at the centre; a facet is ``normal . p
<= offset``. Pure numpy and math.
"""

from __future__ import annotations

import math

import numpy as np

from sitl_sim.site.convex import clip_ray

__all__ = ["PLANES", "Rocks"]

PLANES = 12
_ASPECT = (1.1, 1.8)  # a / h
_FLAT = (0.65, 1.0)  # b / a


class Rocks:
    """Every rock of a site: centres, bases (the ground under the centres), facet planes."""

    def __init__(
        self,
        north: np.ndarray,
        east: np.ndarray,
        base: np.ndarray,
        normals: np.ndarray,
        offsets: np.ndarray,
        drawn_height: np.ndarray,
    ) -> None:
        self.north = np.asarray(north, dtype=float)
        self.east = np.asarray(east, dtype=float)
        self.base = np.asarray(base, dtype=float)
        self.normals = np.asarray(normals, dtype=float).reshape(-1, PLANES, 3)
        """(rocks, PLANES, 3) outward unit normals, every one pointing a little up."""
        self.offsets = np.asarray(offsets, dtype=float).reshape(-1, PLANES)
        self.drawn_height = np.asarray(drawn_height, dtype=float)
        """The height each was drawn with (its ellipsoid's; the facets stand a little proud)."""
        angles = np.linspace(0.0, 2 * math.pi, 72, endpoint=False)
        self.extent = np.array([float(self.rim(k, angles).max()) for k in range(len(self))])
        """Each rock's largest distance from its centre at its foot (m)."""
        self.height = np.array([self.peak(k) for k in range(len(self))])
        """Each rock's highest point above its base (m)."""

    def __len__(self) -> int:
        return len(self.north)

    def subset(self, keep: np.ndarray) -> Rocks:
        """The rocks where ``keep`` is True."""
        return Rocks(
            self.north[keep],
            self.east[keep],
            self.base[keep],
            self.normals[keep],
            self.offsets[keep],
            self.drawn_height[keep],
        )

    @classmethod
    def draw(cls, rng: np.random.Generator, north, east, height, base_of) -> Rocks:
        """Rocks at ``north``/``east`` of drawn ``height``; ``base_of(n, e)``: the ground there."""
        count = len(north)
        normals = np.zeros((count, PLANES, 3))
        offsets = np.zeros((count, PLANES))
        a = np.asarray(height) * rng.uniform(*_ASPECT, count)
        b = a * rng.uniform(*_FLAT, count)
        yaw = rng.uniform(0.0, 2 * math.pi, count)
        for k in range(count):
            c, s = math.cos(yaw[k]), math.sin(yaw[k])
            turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            axes = np.array([a[k], b[k], height[k]])
            foot = (np.arange(6) + rng.uniform(-0.3, 0.3, 6)) * (2 * math.pi / 6)
            azimuth = np.concatenate([foot, rng.uniform(0.0, 2 * math.pi, 6)])
            elevation = np.radians(
                np.concatenate([rng.uniform(4.0, 14.0, 6), rng.uniform(25.0, 65.0, 5), [90.0]])
            )
            elevation[-1] = math.radians(rng.uniform(72.0, 90.0))
            w = np.stack(
                [
                    np.cos(elevation) * np.cos(azimuth),
                    np.cos(elevation) * np.sin(azimuth),
                    np.sin(elevation),
                ],
                axis=1,
            )
            point = (w * axes) @ turn.T  # on the ellipsoid
            normal = (w / axes) @ turn.T  # its outward normal there
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            normals[k] = normal
            offsets[k] = np.einsum("ij,ij->i", normal, point)
        north, east = np.asarray(north, dtype=float), np.asarray(east, dtype=float)
        return cls(north, east, base_of(north, east), normals, offsets, np.asarray(height))

    # ------------------------------------------------------------------ shape

    def local_height(self, k: int, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Rock ``k``'s top above its base at local (x, y) arrays (negative: off its foot) and
        the facet that makes it."""
        nrm, off = self.normals[k], self.offsets[k]
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        z = (off[:, None] - nrm[:, 0:1] * x.ravel() - nrm[:, 1:2] * y.ravel()) / nrm[:, 2:3]
        facet = np.argmin(z, axis=0)
        return z[facet, np.arange(z.shape[1])].reshape(x.shape), facet.reshape(x.shape)

    def rim(self, k: int, angles) -> np.ndarray:
        """Rock ``k``'s foot: the distance from its centre where it meets its base, per angle."""
        c, s = np.cos(angles), np.sin(angles)
        nrm, off = self.normals[k], self.offsets[k]
        along = nrm[:, 0:1] * c + nrm[:, 1:2] * s  # (planes, angles)
        with np.errstate(divide="ignore"):
            r = np.where(along > 1e-9, off[:, None] / along, np.inf)
        return r.min(axis=0)

    def peak(self, k: int) -> float:
        """Rock ``k``'s highest point above its base."""
        angles = np.linspace(0.0, 2 * math.pi, 24, endpoint=False)
        rim = self.rim(k, angles)
        f = np.linspace(0.0, 1.0, 12)[:, None]
        z, _ = self.local_height(k, f * rim * np.cos(angles), f * rim * np.sin(angles))
        return float(z.max())

    # ------------------------------------------------------------------ queries

    def top(self, k: int, n: float, e: float) -> float:
        """Rock ``k``'s surface height (up, absolute) over (n, e), -inf off its foot."""
        x, y = n - self.north[k], e - self.east[k]
        best = math.inf
        for (nx, ny, nz), d in zip(self.normals[k].tolist(), self.offsets[k].tolist(), strict=True):
            best = min(best, (d - nx * x - ny * y) / nz)
        return self.base[k] + best if best > 0.0 else -math.inf

    def ray(self, k: int, o, d) -> float:
        """Distance along ``d`` (NED, unit) from ``o`` (NED) into rock ``k`` (its facets and its
        base plane), inf if missed, 0 from inside."""
        px, py, pz = o[0] - self.north[k], o[1] - self.east[k], -o[2] - self.base[k]
        ux, uy, uz = d[0], d[1], -d[2]
        t_in, t_out = 0.0, math.inf
        if uz == 0.0:
            if pz < 0.0:
                return math.inf
        elif uz > 0.0:
            t_in = max(t_in, -pz / uz)  # the base plane z >= 0
        else:
            t_out = min(t_out, -pz / uz)
        planes = zip(self.normals[k].tolist(), self.offsets[k].tolist(), strict=True)
        return clip_ray(
            (
                (off - (nx * px + ny * py + nz * pz), nx * ux + ny * uy + nz * uz)
                for (nx, ny, nz), off in planes
            ),
            t_in,
            t_out,
        )

    def shadowed(self, k: int, x, y, z, toward_sun) -> np.ndarray:
        """Whether points (local x, y, z arrays) see rock ``k`` toward the sun (unit, x north,
        y east, z up): their cast shadow (vectorised Cyrus-Beck)."""
        ux, uy, uz = toward_sun
        t_in = np.zeros(np.shape(x))
        t_out = np.full(np.shape(x), np.inf)
        # the base plane z >= 0: the sun is above the horizon, uz > 0
        t_in = np.maximum(t_in, -np.asarray(z) / uz)
        for (nx, ny, nz), off in zip(self.normals[k], self.offsets[k], strict=True):
            num = off - (nx * x + ny * y + nz * z)
            den = nx * ux + ny * uy + nz * uz
            if abs(den) < 1e-12:
                t_out = np.where(num < 0.0, -np.inf, t_out)
                continue
            if den < 0.0:
                t_in = np.maximum(t_in, num / den)
            else:
                t_out = np.minimum(t_out, num / den)
        return (t_in < t_out) & (t_out > 1e-4)
