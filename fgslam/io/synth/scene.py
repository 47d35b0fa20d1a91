"""Scene geometry of the synthetic generator: a set of textured rectangles ("quads").

Every surface is a planar rectangle in the world frame W (z up, metres)::

    X_W(s, t) = origin_W + s * axis_u_W + t * axis_v_W,   0 <= s <= size_u, 0 <= t <= size_v

with orthonormal ``axis_u_W``, ``axis_v_W`` and normal ``normal_W = axis_u_W x axis_v_W``. ``(s, t)`` are
the surface coordinates in metres in which textures are defined, so texture is attached to the
surface. A box is six quads with outward normals (one-sided: only visible from the front side);
planes (room walls, ground) may be two-sided. Each quad carries a texture density (texels per metre)
and a texture style index used by :mod:`.texture`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Scene:
    """Growable list of quads; arrays are float64 (Q, 3) / (Q, 2) once :meth:`arrays` is called."""

    origins: list = field(default_factory=list)
    axes_u: list = field(default_factory=list)
    axes_v: list = field(default_factory=list)
    sizes: list = field(default_factory=list)
    two_sided: list = field(default_factory=list)
    densities: list = field(default_factory=list)
    styles: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.origins)

    def add_quad(self, origin, axis_u, axis_v, size_u: float, size_v: float, *, density: float,
                 style: int = 0, two_sided: bool = False) -> None:
        """Add the rectangle ``origin + s axis_u + t axis_v``; the axes are normalised here and
        ``axis_v`` is made orthogonal to ``axis_u`` (Gram-Schmidt)."""
        u = np.asarray(axis_u, dtype=np.float64)
        u = u / np.linalg.norm(u)
        v = np.asarray(axis_v, dtype=np.float64)
        v = v - u * (u @ v)
        v = v / np.linalg.norm(v)
        self.origins.append(np.asarray(origin, dtype=np.float64))
        self.axes_u.append(u)
        self.axes_v.append(v)
        self.sizes.append((float(size_u), float(size_v)))
        self.two_sided.append(bool(two_sided))
        self.densities.append(float(density))
        self.styles.append(int(style))

    def add_box(self, center, size, yaw: float = 0.0, *, density: float, style: int = 0,
                faces: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z"),
                face_density: dict[str, float] | None = None) -> None:
        """Add a box of full extents ``size = (sx, sy, sz)`` centred at ``center`` and rotated by
        ``yaw`` (rad) about the world z axis; faces are named by their outward local normal.
        ``face_density`` overrides the texture density of single faces."""
        c, s_ = np.cos(yaw), np.sin(yaw)
        R_WO = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        h = 0.5 * np.asarray(size, dtype=np.float64)
        center = np.asarray(center, dtype=np.float64)
        # (outward normal axis, sign) -> local (origin corner, u axis, v axis) with u x v = normal
        ex, ey, ez = np.eye(3)
        local = {
            "+x": (np.array([h[0], -h[1], -h[2]]), ey, ez, 2 * h[1], 2 * h[2]),
            "-x": (np.array([-h[0], h[1], -h[2]]), -ey, ez, 2 * h[1], 2 * h[2]),
            "+y": (np.array([h[0], h[1], -h[2]]), -ex, ez, 2 * h[0], 2 * h[2]),
            "-y": (np.array([-h[0], -h[1], -h[2]]), ex, ez, 2 * h[0], 2 * h[2]),
            "+z": (np.array([-h[0], -h[1], h[2]]), ex, ey, 2 * h[0], 2 * h[1]),
            "-z": (np.array([-h[0], h[1], -h[2]]), ex, -ey, 2 * h[0], 2 * h[1]),
        }
        for name in faces:
            o, u, v, su, sv = local[name]
            dens = density if face_density is None else face_density.get(name, density)
            self.add_quad(center + R_WO @ o, R_WO @ u, R_WO @ v, su, sv, density=dens, style=style)

    def arrays(self) -> "SceneArrays":
        """Frozen numpy view of the scene."""
        origins = np.array(self.origins, dtype=np.float64).reshape(-1, 3)
        axes_u = np.array(self.axes_u, dtype=np.float64).reshape(-1, 3)
        axes_v = np.array(self.axes_v, dtype=np.float64).reshape(-1, 3)
        return SceneArrays(
            origins=origins, axes_u=axes_u, axes_v=axes_v,
            normals=np.cross(axes_u, axes_v),
            sizes=np.array(self.sizes, dtype=np.float64).reshape(-1, 2),
            two_sided=np.array(self.two_sided, dtype=bool),
            densities=np.array(self.densities, dtype=np.float64),
            styles=np.array(self.styles, dtype=np.int64),
        )


@dataclass(frozen=True)
class SceneArrays:
    """Quads as arrays: origins/axes_u/axes_v/normals (Q, 3) world frame, sizes (Q, 2) metres,
    two_sided (Q,), densities (Q,) texels per metre, styles (Q,)."""

    origins: np.ndarray
    axes_u: np.ndarray
    axes_v: np.ndarray
    normals: np.ndarray
    sizes: np.ndarray
    two_sided: np.ndarray
    densities: np.ndarray
    styles: np.ndarray

    def __len__(self) -> int:
        return len(self.origins)

    def corners(self) -> np.ndarray:
        """(Q, 4, 3) corners in order (0,0), (su,0), (su,sv), (0,sv) of the surface coordinates."""
        du = self.axes_u * self.sizes[:, :1]
        dv = self.axes_v * self.sizes[:, 1:]
        o = self.origins
        return np.stack([o, o + du, o + du + dv, o + dv], axis=1)
