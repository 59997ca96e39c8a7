"""Procedural shape classes: parameters drawn from a seed, signed distances by analytic CSG.

Each class is a frozen dataclass of its parameters (raw units, y up, standing on y = 0) with
`random(rng)`, `raw_sdf(p)` and `raw_bounds()`. A `Shape` puts one into the unit frame (its
bounding box centred, longest side 1: it lies in [-0.5, 0.5]^3) and is what the rest of neuralsurf
sees: `sdf`, `inside`, `mesh`, `sample_surface`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.extract import extract_mesh
from neuralsurf.priors import csg
from neuralsurf.structures import Mesh, Normalization

SPLITS = ("train", "val", "test")

UNIT_BOUNDS = torch.tensor([[-0.5] * 3, [0.5] * 3], dtype=torch.float64)
"""Float64[Tensor, "2 3"]: the unit frame of every shape of a collection, and so of a prior: the
cube [-0.5, 0.5]^3 (each shape's bounding box centred, longest side 1)."""


def padded_unit_bounds(padding: float) -> Tensor:
    """Float64[Tensor, "2 3"]: UNIT_BOUNDS grown by `padding` on every side."""
    return UNIT_BOUNDS + torch.tensor([[-padding], [padding]], dtype=torch.float64)


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


@dataclass(frozen=True)
class Chair:
    """A box seat on four legs (square or round), with an optional back rest."""

    seat_width: float
    seat_depth: float
    seat_thickness: float
    seat_height: float
    leg_half: float
    leg_inset: float
    round_legs: bool
    back_height: float
    """0: no back."""
    back_thickness: float

    @classmethod
    def random(cls, rng: np.random.Generator) -> Chair:
        has_back = rng.uniform() < 0.8
        return cls(seat_width=_u(rng, 0.4, 0.6), seat_depth=_u(rng, 0.4, 0.6), seat_thickness=_u(rng, 0.04, 0.09),
                   seat_height=_u(rng, 0.35, 0.55), leg_half=_u(rng, 0.03, 0.055), leg_inset=_u(rng, 0.0, 0.05),
                   round_legs=bool(rng.uniform() < 0.4), back_height=_u(rng, 0.3, 0.6) if has_back else 0.0,
                   back_thickness=_u(rng, 0.04, 0.07))

    def raw_sdf(self, p: Tensor) -> Tensor:
        w, d, t, h = self.seat_width / 2, self.seat_depth / 2, self.seat_thickness, self.seat_height
        parts = [csg.box(p, (0.0, h - t / 2, 0.0), (w, t / 2, d), rounding=0.01)]
        lx, lz = w - self.leg_inset - self.leg_half, d - self.leg_inset - self.leg_half
        leg_top = h - t / 2  # legs reach into the middle of the seat: one solid
        for sx in (-1, 1):
            for sz in (-1, 1):
                centre = (sx * lx, leg_top / 2, sz * lz)
                if self.round_legs:
                    parts.append(csg.cylinder(p, centre, self.leg_half, leg_top / 2))
                else:
                    parts.append(csg.box(p, centre, (self.leg_half, leg_top / 2, self.leg_half), rounding=0.005))
        if self.back_height > 0:
            b = self.back_thickness / 2
            parts.append(csg.box(p, (0.0, h - t / 2 + self.back_height / 2, -d + b),
                                 (w, self.back_height / 2, b), rounding=0.01))
        return csg.union(*parts)

    def raw_bounds(self) -> Tensor:
        w, d = self.seat_width / 2, self.seat_depth / 2
        top = self.seat_height + (self.back_height - self.seat_thickness / 2 if self.back_height > 0 else 0.0)
        return torch.tensor([[-w, 0.0, -d], [w, max(top, self.seat_height), d]], dtype=torch.float64)


@dataclass(frozen=True)
class Mug:
    """An open cylinder with a bottom and a torus handle."""

    radius: float
    height: float
    wall: float
    bottom: float
    handle_major: float
    handle_minor: float

    @classmethod
    def random(cls, rng: np.random.Generator) -> Mug:
        height = _u(rng, 0.6, 1.0)
        minor = _u(rng, 0.04, 0.065)
        return cls(radius=_u(rng, 0.3, 0.45), height=height, wall=_u(rng, 0.06, 0.1), bottom=_u(rng, 0.06, 0.12),
                   handle_major=_u(rng, max(0.18, minor + 0.1), 0.32 * height), handle_minor=minor)

    def raw_sdf(self, p: Tensor) -> Tensor:
        r, h = self.radius, self.height
        body = csg.cylinder(p, (0.0, h / 2, 0.0), r, h / 2)
        handle = csg.torus_z(p, (r, h / 2, 0.0), self.handle_major, self.handle_minor)
        depth = h - self.bottom
        cavity = csg.cylinder(p, (0.0, self.bottom + depth / 2 + 0.5, 0.0), r - self.wall, depth / 2 + 0.5)
        return csg.difference(csg.union(body, handle), cavity)

    def raw_bounds(self) -> Tensor:
        r, h, m = self.radius, self.height, self.handle_major + self.handle_minor
        return torch.tensor([[-r, 0.0, -r], [r + m, h, r]], dtype=torch.float64)


@dataclass(frozen=True)
class Lamp:
    """A disc base, a pole and a shade (a truncated cone, or a globe)."""

    base_radius: float
    base_half_height: float
    pole_radius: float
    pole_height: float
    shade_bottom: float
    shade_top: float
    shade_half_height: float
    globe: bool

    @classmethod
    def random(cls, rng: np.random.Generator) -> Lamp:
        return cls(base_radius=_u(rng, 0.15, 0.3), base_half_height=_u(rng, 0.025, 0.05),
                   pole_radius=_u(rng, 0.03, 0.05), pole_height=_u(rng, 0.45, 0.9), shade_bottom=_u(rng, 0.2, 0.35),
                   shade_top=_u(rng, 0.08, 0.2), shade_half_height=_u(rng, 0.1, 0.2),
                   globe=bool(rng.uniform() < 0.3))

    def _shade_centre(self) -> float:
        return 2 * self.base_half_height + self.pole_height

    def raw_sdf(self, p: Tensor) -> Tensor:
        base = csg.cylinder(p, (0.0, self.base_half_height, 0.0), self.base_radius, self.base_half_height)
        pole_top = self._shade_centre()
        pole = csg.cylinder(p, (0.0, pole_top / 2, 0.0), self.pole_radius, pole_top / 2)
        if self.globe:
            shade = csg.sphere(p, (0.0, pole_top, 0.0), self.shade_bottom * 0.8)
        else:
            shade = csg.capped_cone(p, (0.0, pole_top, 0.0), self.shade_half_height, self.shade_bottom,
                                    self.shade_top)
        return csg.union(base, pole, shade)

    def raw_bounds(self) -> Tensor:
        c = self._shade_centre()
        if self.globe:
            r = self.shade_bottom * 0.8
            top = c + r
        else:
            r = max(self.shade_bottom, self.shade_top)
            top = c + self.shade_half_height
        r = max(r, self.base_radius)
        return torch.tensor([[-r, 0.0, -r], [r, top, r]], dtype=torch.float64)


@dataclass(frozen=True)
class SlatChair:
    """A chair of thin parts: a seat on four legs joined by stretchers, and a back of vertical slats
    under a top rail (the slats and stretchers a few hundredths of the chair's height across)."""

    seat_width: float
    seat_depth: float
    seat_thickness: float
    seat_height: float
    leg_half: float
    stretcher_half: float
    stretcher_height: float
    back_height: float
    slats: int
    slat_width: float
    slat_half: float
    rail_half: float

    @classmethod
    def random(cls, rng: np.random.Generator) -> SlatChair:
        return cls(seat_width=_u(rng, 0.4, 0.55), seat_depth=_u(rng, 0.4, 0.55), seat_thickness=_u(rng, 0.03, 0.05),
                   seat_height=_u(rng, 0.4, 0.5), leg_half=_u(rng, 0.02, 0.03), stretcher_half=_u(rng, 0.014, 0.02),
                   stretcher_height=_u(rng, 0.1, 0.2), back_height=_u(rng, 0.35, 0.55), slats=int(rng.integers(2, 6)),
                   slat_width=_u(rng, 0.02, 0.04), slat_half=_u(rng, 0.014, 0.02), rail_half=_u(rng, 0.025, 0.035))

    def raw_sdf(self, p: Tensor) -> Tensor:
        w, d, t, h = self.seat_width / 2, self.seat_depth / 2, self.seat_thickness, self.seat_height
        parts = [csg.box(p, (0.0, h - t / 2, 0.0), (w, t / 2, d), rounding=0.005)]
        lx, lz, top = w - self.leg_half, d - self.leg_half, h - t / 2
        for sx in (-1, 1):
            for sz in (-1, 1):  # legs reach into the middle of the seat: one solid
                parts.append(csg.box(p, (sx * lx, top / 2, sz * lz), (self.leg_half, top / 2, self.leg_half)))
        s, y = self.stretcher_half, self.stretcher_height
        for sx in (-1, 1):  # side stretchers, front to back, and one across the front
            parts.append(csg.box(p, (sx * lx, y, 0.0), (s, s, lz)))
        parts.append(csg.box(p, (0.0, y, lz), (lx, s, s)))
        rail_y = h + self.back_height
        back_z = -lz  # the back rises from the rear legs
        for sx in (-1, 1):  # the rear legs go on up to the rail
            parts.append(csg.box(p, (sx * lx, (h + rail_y) / 2, back_z), (self.leg_half, (rail_y - h) / 2, self.leg_half)))
        parts.append(csg.box(p, (0.0, rail_y, back_z), (lx + self.leg_half, self.rail_half, self.slat_half * 1.5)))
        for i in range(self.slats):
            x = -lx + 2 * lx * (i + 1) / (self.slats + 1)
            parts.append(csg.box(p, (x, (h + rail_y) / 2, back_z), (self.slat_width / 2, (rail_y - h) / 2, self.slat_half)))
        return csg.union(*parts)

    def raw_bounds(self) -> Tensor:
        w, d = self.seat_width / 2, self.seat_depth / 2
        return torch.tensor([[-w, 0.0, -d], [w, self.seat_height + self.back_height + self.rail_half, d]],
                            dtype=torch.float64)


SHAPE_CLASSES = {"chair": Chair, "mug": Mug, "lamp": Lamp, "slat_chair": SlatChair}
"""Class name -> generator. The order fixes each class's seed stream: append, never reorder."""


def _class_of(kind: str):
    if kind not in SHAPE_CLASSES:
        raise ConfigError(f"unknown shape class {kind!r}; choose from {list(SHAPE_CLASSES)}")
    return SHAPE_CLASSES[kind]


@dataclass(frozen=True)
class ShapeRecord:
    """Which shape: its class, split, index within (class, split), and the collection seed."""

    kind: str
    split: str
    index: int
    collection_seed: int = 0

    @property
    def name(self) -> str:
        return f"{self.kind}_{self.split}_{self.index:04d}"

    @property
    def seed(self) -> int:
        """The shape's own seed; splits and classes draw from disjoint streams of the collection seed."""
        if self.split not in SPLITS:
            raise ConfigError(f"unknown split {self.split!r}; choose from {SPLITS}")
        _class_of(self.kind)
        kind_id = list(SHAPE_CLASSES).index(self.kind)
        entropy = [int(self.collection_seed), SPLITS.index(self.split), kind_id, int(self.index)]
        return int(np.random.SeedSequence(entropy).generate_state(1, dtype=np.uint64)[0] >> 1)


@dataclass(frozen=True)
class Shape:
    """A procedural shape in the unit frame: its bounding box centred, longest side 1."""

    record: ShapeRecord
    parameters: Chair | Mug | Lamp | SlatChair
    normalization: Normalization
    """Raw frame <-> unit frame."""

    @classmethod
    def from_record(cls, record: ShapeRecord) -> Shape:
        parameters = _class_of(record.kind).random(np.random.default_rng(record.seed))
        return cls(record, parameters, Normalization.from_points(parameters.raw_bounds()))

    @property
    def name(self) -> str:
        return self.record.name

    def sdf(self, x: Tensor) -> Tensor:
        """Unit-frame x[..., 3] -> signed distance [...] (float64 inside; same dtype out), negative
        inside: exact sign and zero set, exact distance outside (see `neuralsurf.priors.csg`)."""
        if x.shape[-1] != 3:
            raise InputError(f"Shape.sdf expects points of shape (..., 3), got {tuple(x.shape)}")
        raw = self.normalization.to_world(x.double())
        return (self.parameters.raw_sdf(raw) / self.normalization.scale).to(x.dtype)

    def inside(self, x: Tensor) -> Tensor:
        """Bool[Tensor, "..."]: occupancy of unit-frame points (exact)."""
        return self.sdf(x.double()) < 0

    def mesh(self, resolution: int = 128, padding: float = 0.05) -> Mesh:
        """Marching cubes of the analytic SDF over [-0.5 - padding, 0.5 + padding]^3 (unit frame,
        float32 vertices). Watertight when the shape is (see `check_shape`)."""
        half = 0.5 + padding
        bounds = np.array([[-half] * 3, [half] * 3])
        return extract_mesh(lambda x: self.sdf(x.double()).float(), resolution=resolution, bounds=bounds,
                            device="cpu")

    def project(self, points: Tensor, iterations: int = 4) -> tuple[Tensor, Tensor]:
        """Points moved onto the zero set along the SDF gradient (Newton steps), and the unit outward
        normals there. points: Float[Tensor, "n 3"] -> (Float64[Tensor, "n 3"], Float64[Tensor, "n 3"])."""
        x = points.double().detach()
        for _ in range(iterations + 1):
            x.requires_grad_(True)
            value = self.sdf(x)
            (gradient,) = torch.autograd.grad(value.sum(), x)
            normal = torch.nn.functional.normalize(gradient, dim=-1)
            step = value[:, None] * gradient / gradient.square().sum(-1, keepdim=True).clamp_min(1e-12)
            x = (x - step).detach()
        if not (torch.isfinite(x).all() and torch.isfinite(normal).all()):
            raise InputError(f"{self.name}: projecting points onto the surface gave NaN or inf; a bug in the "
                             f"SDF of {self.parameters}")
        return x, normal.detach()


def check_shape(shape: Shape, mesh: Mesh) -> None:
    """Raise InputError unless `mesh` (the shape's marching cubes) is watertight, consistently
    oriented, one piece, and lies in the unit cube."""
    if mesh.is_empty or not mesh.is_watertight:
        raise InputError(f"{shape.name}: the mesh of {shape.parameters} is not watertight; "
                         f"a generator bug: report the record {shape.record}")
    pieces = len(mesh.to_trimesh().split(only_watertight=False))
    if pieces != 1:
        raise InputError(f"{shape.name}: the shape falls into {pieces} pieces ({shape.parameters}); "
                         f"a generator bug: report the record {shape.record}")
    lo, hi = mesh.bounds.double()
    if lo.min() < -0.5 - 1e-2 or hi.max() > 0.5 + 1e-2 or math.isclose(float((hi - lo).max()), 0.0):
        raise InputError(f"{shape.name}: mesh bounds {mesh.bounds.tolist()} leave the unit cube")


def collection_records(kinds=("chair", "mug", "lamp"), n_train: int = 8, n_val: int = 2, n_test: int = 2,
                       seed: int = 0) -> list[ShapeRecord]:
    """Records of a collection: `n_train`, `n_val` and `n_test` shapes of each class in `kinds`,
    ordered by split, class, index (the order of latent codes of an auto-decoder)."""
    counts = {"train": n_train, "val": n_val, "test": n_test}
    for name, value in counts.items():
        if not (isinstance(value, int) and value >= 0):
            raise ConfigError(f"n_{name} must be an integer >= 0 (shapes per class), got {value!r}")
    for kind in kinds:
        _class_of(kind)
    if not kinds:
        raise ConfigError("a collection needs at least one shape class")
    return [ShapeRecord(kind, split, index, seed) for split in SPLITS for kind in kinds
            for index in range(counts[split])]
