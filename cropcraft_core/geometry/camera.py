"""Pinhole cameras (OpenCV convention: x right, y down, z forward; pixel centres at +0.5).

``cam_to_world`` is a (4, 4) rigid transform taking camera coordinates to world coordinates.
Depth everywhere in CropCraft is z-depth: the distance along the optical axis, in metres.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from cropcraft_core.errors import ConfigError

#: The paper's row camera: 994 × 738 pixels, 50° vertical field of view.
ROW_CAMERA_SIZE = (994, 738)
ROW_CAMERA_VFOV_DEG = 50.0


#: How far a pose's rotation may be from orthonormal (max |RᵀR − I|): float32 poses written
#: by phones' AR tracking are off by ~1e-7; a scaled or sheared one is refused.
RIGID_TOLERANCE = 1e-4


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    cam_to_world: np.ndarray  # (4, 4) float64

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
                raise ConfigError(f"camera {name} must be a whole number of pixels, got {v!r}")
            if not (math.isfinite(v) and v == int(v)):
                raise ConfigError(f"camera {name} must be a whole number of pixels, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"camera size must be positive, got {self.width}×{self.height}")
        if not all(math.isfinite(float(v)) for v in (self.fx, self.fy, self.cx, self.cy)):
            raise ConfigError(
                f"camera intrinsics must be finite, got fx={self.fx}, fy={self.fy}, "
                f"cx={self.cx}, cy={self.cy}"
            )
        if self.fx <= 0 or self.fy <= 0:
            raise ConfigError(f"camera focal lengths must be positive, got {self.fx}, {self.fy}")
        m = np.asarray(self.cam_to_world, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ConfigError("cam_to_world must be a finite (4, 4) matrix")
        r = m[:3, :3]
        if (
            np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9
            or np.abs(r.T @ r - np.eye(3)).max() > RIGID_TOLERANCE
            or np.linalg.det(r) <= 0
        ):  # a scaled or mirrored pose put a point 4 m away at 16 m: depths, points, LAI
            raise ConfigError(
                "cam_to_world must be a rigid transform (an orthonormal rotation of determinant "
                f"+1, last row 0 0 0 1), got {np.round(m, 4).tolist()}"
            )
        object.__setattr__(self, "cam_to_world", m)

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_vfov(
        cls, width: int, height: int, vfov_deg: float, cam_to_world: np.ndarray
    ) -> PinholeCamera:
        """Square pixels, principal point at the image centre."""
        if not 0 < vfov_deg < 180:
            raise ConfigError(f"vertical field of view must be in (0, 180) degrees, got {vfov_deg}")
        f = 0.5 * height / math.tan(math.radians(vfov_deg) / 2)
        return cls(width, height, f, f, width / 2, height / 2, cam_to_world)

    @classmethod
    def look_down(
        cls,
        center_xy: tuple[float, float] = (0.0, 0.0),
        height_m: float = 1.0,
        row_direction: tuple[float, float] = (1.0, 0.0),
        ground_z: float = 0.0,
        size: tuple[int, int] = ROW_CAMERA_SIZE,
        vfov_deg: float = ROW_CAMERA_VFOV_DEG,
    ) -> PinholeCamera:
        """The paper's row camera: straight down from ``height_m`` above the ground, image x along
        the row (``row_direction`` in the world xy plane)."""
        if height_m <= 0:
            raise ConfigError(f"camera height must be positive, got {height_m}")
        d = np.array([row_direction[0], row_direction[1], 0.0], dtype=np.float64)
        if np.linalg.norm(d) == 0:
            raise ConfigError("row direction must be non-zero")
        x = d / np.linalg.norm(d)
        z = np.array([0.0, 0.0, -1.0])
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
        m[:3, 3] = [center_xy[0], center_xy[1], ground_z + height_m]
        return cls.from_vfov(size[0], size[1], vfov_deg, m)

    # ----------------------------------------------------------------- properties
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def world_to_cam(self) -> np.ndarray:
        r = self.cam_to_world[:3, :3]
        t = self.cam_to_world[:3, 3]
        m = np.eye(4)
        m[:3, :3] = r.T
        m[:3, 3] = -r.T @ t
        return m

    @property
    def center(self) -> np.ndarray:
        return self.cam_to_world[:3, 3].copy()

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.height / self.fy))

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.width / self.fx))

    def scaled(self, factor: float) -> PinholeCamera:
        """The same camera with its image resampled by ``factor`` (e.g. 0.5 halves each side)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return PinholeCamera(
            w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.cam_to_world
        )

    def shifted(self, dx: float, dy: float) -> PinholeCamera:
        """The same camera moved ``dx`` along its own image x axis and ``dy`` along its image y
        axis (a row camera: ``dx`` along the row, ``dy`` across it), in the pose's units; the
        intrinsics and orientation are kept."""
        m = np.array(self.cam_to_world, dtype=np.float64, copy=True)
        m[:3, 3] += float(dx) * m[:3, 0] + float(dy) * m[:3, 1]
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, m)

    # ----------------------------------------------------------------- geometry
    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) world points → (n, 3) camera coordinates."""
        m = self.world_to_cam
        return points @ m[:3, :3].T + m[:3, 3]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) world points → ((n, 2) pixel coordinates, (n,) z-depth). Points behind the
        camera get non-finite pixel coordinates."""
        pc = self.to_camera(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[:, 0] / z + self.cx
            v = self.fy * pc[:, 1] / z + self.cy
        uv = np.stack([u, v], axis=1)
        uv[z <= 0] = np.nan
        return uv, z

    def ray_directions(self, normalized: bool = True) -> np.ndarray:
        """(height, width, 3) world-frame ray directions through the pixel centres. With
        ``normalized=False`` each has unit z in camera coordinates, so that t = z-depth."""
        u = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        d = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
        if normalized:
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d @ self.cam_to_world[:3, :3].T

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """(height, width) z-depth → (height, width, 3) world points (NaN where depth is not
        finite)."""
        d = self.ray_directions(normalized=False)
        return self.center + d * depth[..., None]

    def sees_spheres(self, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """(n,) bool: False only for the (n, 3) world spheres of (n,) ``radii`` that lie wholly
        outside the image's viewing pyramid (beyond one of its four side planes, through the
        image borders; the four together also exclude what is behind the camera), so that none
        of their points can project into the image. Conservative: a sphere near a plane (within
        1 mm more than its radius) counts as seen."""
        pc = self.to_camera(np.asarray(centres, dtype=np.float64).reshape(-1, 3))
        x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
        r = np.asarray(radii, dtype=np.float64) + 1e-3
        seen = np.ones(len(pc), dtype=bool)
        # inside ⇔ a·(x or y) + b·z >= 0 for each plane (u >= 0, u <= W, v >= 0, v <= H)
        for a, b, q in (
            (self.fx, self.cx, x),
            (-self.fx, self.width - self.cx, x),
            (self.fy, self.cy, y),
            (-self.fy, self.height - self.cy, y),
        ):
            seen &= (a * q + b * z) / math.hypot(a, b) >= -r
        return seen

    def ground_footprint(self, ground_z: float = 0.0) -> np.ndarray:
        """(4, 2) xy corners where the image corners' rays meet the plane z = ground_z."""
        corners = np.array(
            [[0, 0], [self.width, 0], [self.width, self.height], [0, self.height]], float
        )
        d = np.column_stack(
            [(corners[:, 0] - self.cx) / self.fx, (corners[:, 1] - self.cy) / self.fy, np.ones(4)]
        )
        dw = d @ self.cam_to_world[:3, :3].T
        c = self.center
        if np.any(dw[:, 2] >= 0):
            raise ConfigError("camera does not look down onto the ground at every image corner")
        if c[2] <= ground_z:  # its rays meet the plane behind it: a mirrored footprint
            raise ConfigError(f"camera at z = {c[2]:.3f} is not above the ground z = {ground_z}")
        t = (ground_z - c[2]) / dw[:, 2]
        return c[:2] + dw[:, :2] * t[:, None]

    # ----------------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "cam_to_world": self.cam_to_world.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> PinholeCamera:
        try:
            return cls(
                d["width"],  # checked as whole numbers there: int() cut 640.7 to 640
                d["height"],
                float(d["fx"]),
                float(d["fy"]),
                float(d["cx"]),
                float(d["cy"]),
                np.asarray(d["cam_to_world"], dtype=np.float64),
            )
        except KeyError as e:
            raise ConfigError(f"camera record is missing {e}") from None
        except (TypeError, ValueError) as e:
            raise ConfigError(f"camera record is malformed: {e}") from None

    def to_json(self) -> str:
        return json.dumps(self.to_dict())
