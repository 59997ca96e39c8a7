"""Analytic shapes with exact signed distances, areas, volumes and surface samples: test oracles."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import Mesh, PointCloud


def _vec(values, n: int = 3) -> Tensor:
    return torch.as_tensor(values, dtype=torch.float64).reshape(n)


@dataclass(frozen=True)
class Sphere:
    """Sphere of `radius` around `center`."""

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.35

    def sdf(self, x: Tensor) -> Tensor:
        """x[..., 3] -> exact signed distance [...], negative inside."""
        return (x - _vec(self.center).to(x)).norm(dim=-1) - self.radius

    @property
    def area(self) -> float:
        return 4 * math.pi * self.radius**2

    @property
    def volume(self) -> float:
        return 4 / 3 * math.pi * self.radius**3

    def sample_surface(self, n: int, seed: int = 0) -> PointCloud:
        """n uniform surface points with exact outward normals."""
        g = torch.Generator().manual_seed(seed)
        normals = torch.nn.functional.normalize(torch.randn(n, 3, dtype=torch.float64, generator=g), dim=-1)
        return PointCloud(_vec(self.center) + self.radius * normals, normals)

    def mesh(self, subdivisions: int = 5) -> Mesh:
        """An icosphere inscribed in the sphere (vertices exactly on it)."""
        import trimesh

        m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=self.radius)
        return Mesh(m.vertices + _vec(self.center).numpy(), m.faces)


@dataclass(frozen=True)
class Torus:
    """Torus around the z axis through `center`: tube of radius `minor` at distance `major`."""

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    major: float = 0.3
    minor: float = 0.1

    def sdf(self, x: Tensor) -> Tensor:
        p = x - _vec(self.center).to(x)
        ring = torch.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2) - self.major
        return torch.sqrt(ring**2 + p[..., 2] ** 2) - self.minor

    @property
    def area(self) -> float:
        return 4 * math.pi**2 * self.major * self.minor

    @property
    def volume(self) -> float:
        return 2 * math.pi**2 * self.major * self.minor**2

    def sample_surface(self, n: int, seed: int = 0) -> PointCloud:
        """n area-uniform surface points (rejection on the tube angle) with exact normals."""
        g = torch.Generator().manual_seed(seed)
        chosen = torch.empty(0, dtype=torch.float64)
        while len(chosen) < n:  # area element is proportional to major + minor cos(v)
            v = 2 * math.pi * torch.rand(2 * n, dtype=torch.float64, generator=g)
            keep = torch.rand(2 * n, dtype=torch.float64, generator=g) * (self.major + self.minor) < (
                self.major + self.minor * torch.cos(v)
            )
            chosen = torch.cat([chosen, v[keep]])
        v = chosen[:n]
        u = 2 * math.pi * torch.rand(n, dtype=torch.float64, generator=g)
        normals = torch.stack([torch.cos(v) * torch.cos(u), torch.cos(v) * torch.sin(u), torch.sin(v)], -1)
        ring = torch.stack([torch.cos(u), torch.sin(u), torch.zeros_like(u)], -1) * self.major
        return PointCloud(_vec(self.center) + ring + self.minor * normals, normals)

    def mesh(self, sections: int = 128) -> Mesh:
        import trimesh

        m = trimesh.creation.torus(self.major, self.minor, major_sections=sections, minor_sections=sections // 2)
        return Mesh(m.vertices + _vec(self.center).numpy(), m.faces)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box with `half_extents` around `center`."""

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    half_extents: tuple[float, float, float] = (0.3, 0.2, 0.25)

    def sdf(self, x: Tensor) -> Tensor:
        q = (x - _vec(self.center).to(x)).abs() - _vec(self.half_extents).to(x)
        outside = q.clamp(min=0).norm(dim=-1)
        inside = q.max(dim=-1).values.clamp(max=0)
        return outside + inside

    @property
    def area(self) -> float:
        a, b, c = (2 * h for h in self.half_extents)
        return 2 * (a * b + b * c + a * c)

    @property
    def volume(self) -> float:
        return math.prod(2 * h for h in self.half_extents)

    def sample_surface(self, n: int, seed: int = 0) -> PointCloud:
        """n area-uniform points on the six faces, with the faces' normals."""
        g = torch.Generator().manual_seed(seed)
        h = _vec(self.half_extents)
        face_areas = torch.stack([h[1] * h[2], h[0] * h[2], h[0] * h[1]]).repeat(2)
        face = torch.multinomial(face_areas, n, replacement=True, generator=g)
        axis, sign = face % 3, torch.where(face < 3, 1.0, -1.0).double()
        points = (2 * torch.rand(n, 3, dtype=torch.float64, generator=g) - 1) * h
        rows = torch.arange(n)
        points[rows, axis] = sign * h[axis]
        normals = torch.zeros(n, 3, dtype=torch.float64)
        normals[rows, axis] = sign
        return PointCloud(_vec(self.center) + points, normals)

    def mesh(self) -> Mesh:
        import trimesh

        m = trimesh.creation.box(extents=[2 * e for e in self.half_extents])
        return Mesh(m.vertices + _vec(self.center).numpy(), m.faces)


SHAPES = {"sphere": Sphere, "torus": Torus, "box": Box}


def analytic_shape(name: str, **parameters) -> Sphere | Torus | Box:
    """Build an analytic shape by name (sphere, torus, box) with its dataclass parameters."""
    if name not in SHAPES:
        raise ConfigError(f"unknown analytic shape {name!r}; choose one of {sorted(SHAPES)}")
    try:
        return SHAPES[name](**parameters)
    except TypeError as error:
        raise InputError(f"bad parameters for {name}: {error}") from None
