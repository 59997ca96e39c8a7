"""Small frozen dataclasses of tensors shared by every module.

Everything here lives in the user's world frame; `Normalization` is the one way in and out of the
unit cube that the models and metrics work in.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import InputError

if TYPE_CHECKING:
    import open3d
    import trimesh


def as_tensor(values, dtype: torch.dtype, name: str, columns: int | None = 3) -> Tensor:
    """Convert array-like `values` to a tensor, checking `(n, columns)` shape and finiteness."""
    try:
        tensor = torch.as_tensor(np.asarray(values) if not isinstance(values, Tensor) else values)
    except (TypeError, ValueError) as error:
        raise InputError(f"{name} must be an array of numbers, got {type(values).__name__}: {error}")
    tensor = tensor.to(dtype)
    if columns is not None and (tensor.ndim != 2 or tensor.shape[1] != columns):
        raise InputError(
            f"{name} must have shape (n, {columns}), got {tuple(tensor.shape)}; "
            f"reshape it to one row per element"
        )
    if tensor.is_floating_point() and not torch.isfinite(tensor).all():
        bad = int((~torch.isfinite(tensor)).any(dim=-1).sum()) if tensor.ndim == 2 else -1
        raise InputError(
            f"{name} contains NaN or inf ({bad} rows); remove or repair them before building the object"
        )
    return tensor


def _float_dtype(values) -> torch.dtype:
    """float64 when the input already is, else float32."""
    dtype = getattr(values, "dtype", None)
    return torch.float64 if dtype in (np.float64, torch.float64) else torch.float32


@dataclass(frozen=True)
class PointCloud:
    """A set of points in the world frame, with optional unit normals and colours."""

    points: Tensor
    """Float[Tensor, "n 3"]: positions in the world frame."""
    normals: Tensor | None = None
    """Float[Tensor, "n 3"] | None: unit outward normals, one per point."""
    colors: Tensor | None = None
    """Float[Tensor, "n 3"] | None: RGB in [0, 1], one per point."""

    def __post_init__(self) -> None:
        points = as_tensor(self.points, _float_dtype(self.points), "PointCloud.points")
        if len(points) == 0:
            raise InputError("PointCloud.points is empty; a point cloud needs at least one point")
        object.__setattr__(self, "points", points)
        for name in ("normals", "colors"):
            value = getattr(self, name)
            if value is None:
                continue
            value = as_tensor(value, points.dtype, f"PointCloud.{name}").to(points.device)
            if len(value) != len(points):
                raise InputError(
                    f"PointCloud.{name} has {len(value)} rows but there are {len(points)} points; "
                    f"give one {name[:-1]} per point or None"
                )
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def has_normals(self) -> bool:
        return self.normals is not None

    def to(self, device: torch.device | str) -> PointCloud:
        """The same cloud on `device`."""
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return PointCloud(move(self.points), move(self.normals), move(self.colors))

    def with_normals(self, normals: Tensor | None) -> PointCloud:
        """The same points with `normals` (n, 3) replacing the current ones."""
        return replace(self, normals=normals)

    def to_open3d(self) -> open3d.geometry.PointCloud:
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points.detach().cpu().double().numpy()))
        if self.normals is not None:
            cloud.normals = o3d.utility.Vector3dVector(self.normals.detach().cpu().double().numpy())
        if self.colors is not None:
            cloud.colors = o3d.utility.Vector3dVector(self.colors.detach().cpu().double().numpy())
        return cloud

    @classmethod
    def from_open3d(cls, cloud: open3d.geometry.PointCloud, dtype=torch.float64) -> PointCloud:
        optional = lambda has, values: torch.as_tensor(np.asarray(values)).to(dtype) if has else None  # noqa: E731
        return cls(torch.as_tensor(np.asarray(cloud.points)).to(dtype),
                   optional(cloud.has_normals(), cloud.normals), optional(cloud.has_colors(), cloud.colors))

    def select(self, index: Tensor) -> PointCloud:
        """The subset of points picked by `index` (a boolean mask or integer indices)."""
        pick = lambda t: None if t is None else t[index]  # noqa: E731
        return PointCloud(self.points[index], pick(self.normals), pick(self.colors))


def merged_vertex_ids(vertices: Tensor) -> Tensor:
    """Long[Tensor, "v"]: the same id for Float[Tensor, "v 3"] vertices equal to 8 decimals (trimesh's
    `merge_vertices`), ids in lexicographic order of the rounded coordinates."""
    keys = (vertices.detach().cpu().double() * 1e8).round().long()
    order = torch.arange(len(keys))
    for axis in (2, 1, 0):  # lexicographic: stable sorts from the last coordinate (torch.unique(dim=0): 12x slower)
        order = order[keys[order, axis].argsort(stable=True)]
    ordered = keys[order]
    new = torch.ones(len(keys), dtype=torch.bool)
    new[1:] = (ordered[1:] != ordered[:-1]).any(1)
    return torch.empty_like(order).index_put_((order,), new.cumsum(0) - 1)


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in the world frame: the one mesh type of every method."""

    vertices: Tensor
    """Float[Tensor, "v 3"]: vertex positions (float32 or float64, kept as given)."""
    faces: Tensor
    """Int[Tensor, "f 3"]: counter-clockwise vertex indices seen from outside (int64)."""
    vertex_colors: Tensor | None = None
    """Float[Tensor, "v 3"] | None: RGB in [0, 1]."""

    def __post_init__(self) -> None:
        vertices = as_tensor(self.vertices, _float_dtype(self.vertices), "Mesh.vertices")
        faces = as_tensor(self.faces, torch.int64, "Mesh.faces")
        if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
            raise InputError(
                f"Mesh.faces index vertices outside [0, {len(vertices)}): "
                f"min {int(faces.min())}, max {int(faces.max())}; check the face array"
            )
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces.to(vertices.device))
        if self.vertex_colors is not None:
            colors = as_tensor(self.vertex_colors, vertices.dtype, "Mesh.vertex_colors")
            if len(colors) != len(vertices):
                raise InputError(
                    f"Mesh.vertex_colors has {len(colors)} rows for {len(vertices)} vertices"
                )
            object.__setattr__(self, "vertex_colors", colors.to(vertices.device))

    @property
    def is_empty(self) -> bool:
        return len(self.faces) == 0

    @property
    def is_watertight(self) -> bool:
        """Closed and consistently oriented: after merging coincident vertices (`merged_vertex_ids`; STL
        and per-face vertex arrays duplicate them), every edge is shared by exactly two faces with
        opposite directions (as trimesh's `merge_vertices`, `is_watertight` and
        `is_winding_consistent`, in about a third of their time)."""
        if self.is_empty:
            return False
        ends = merged_vertex_ids(self.vertices)[self.faces.cpu()][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        edges = ends.min(1).values * len(self.vertices) + ends.max(1).values
        order = edges.argsort()
        edges = edges[order]
        if len(edges) % 2 or not torch.equal(edges[0::2], edges[1::2]) or bool((edges[2::2] == edges[1:-1:2]).any()):
            return False  # an edge of one face, or of more than two
        first, second = ends[order[0::2]], ends[order[1::2]]
        return bool((first[:, 1] == second[:, 0]).all())

    @property
    def bounds(self) -> Tensor:
        """Float[Tensor, "2 3"]: min and max corner."""
        return torch.stack([self.vertices.min(0).values, self.vertices.max(0).values])

    def face_normals(self) -> Tensor:
        """Float[Tensor, "f 3"]: unit normals of the faces."""
        a, b, c = self.vertices[self.faces].unbind(1)
        return torch.nn.functional.normalize(torch.linalg.cross(b - a, c - a), dim=-1)

    def face_areas(self) -> Tensor:
        """Float[Tensor, "f"]: triangle areas."""
        a, b, c = self.vertices[self.faces].unbind(1)
        return 0.5 * torch.linalg.cross(b - a, c - a).norm(dim=-1)

    def to(self, device: torch.device | str) -> Mesh:
        colors = None if self.vertex_colors is None else self.vertex_colors.to(device)
        return Mesh(self.vertices.to(device), self.faces.to(device), colors)

    def transformed(self, transform: Tensor) -> Mesh:
        """The mesh moved by a 4x4 rigid or similarity `transform`."""
        t = torch.as_tensor(transform, dtype=self.vertices.dtype, device=self.vertices.device)
        return replace(self, vertices=self.vertices @ t[:3, :3].T + t[:3, 3])

    # conversions: exact in both directions (float64 vertices stay float64)
    def to_trimesh(self) -> trimesh.Trimesh:
        import trimesh

        colors = None if self.vertex_colors is None else self.vertex_colors.cpu().numpy()
        return trimesh.Trimesh(
            self.vertices.detach().cpu().numpy(),
            self.faces.cpu().numpy(),
            vertex_colors=colors,
            process=False,
        )

    @classmethod
    def from_trimesh(cls, mesh: trimesh.Trimesh) -> Mesh:
        colors = None
        visual = getattr(mesh, "visual", None)
        if getattr(visual, "kind", None) == "vertex":
            colors = np.asarray(visual.vertex_colors)[:, :3] / 255.0
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), colors)

    def to_open3d(self) -> open3d.geometry.TriangleMesh:
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices.detach().cpu().double().numpy()),
            o3d.utility.Vector3iVector(self.faces.cpu().int().numpy()),
        )
        if self.vertex_colors is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors.cpu().double().numpy())
        return mesh

    @classmethod
    def from_open3d(cls, mesh: open3d.geometry.TriangleMesh, dtype=torch.float64) -> Mesh:
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        vertices = torch.as_tensor(np.asarray(mesh.vertices)).to(dtype)
        return cls(vertices, np.asarray(mesh.triangles).astype(np.int64), colors)


@dataclass(frozen=True)
class Normalization:
    """A similarity between the world frame and the unit frame: `unit = (world - center) / scale`.

    Built from a bounding box, it centres the box and maps its longest side to length 1, so the
    shape lies in [-0.5, 0.5]^3. Signed distances scale by `scale` on the way back to the world.
    """

    center: Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    """Float[Tensor, "3"]: world position of the unit frame's origin."""
    scale: float = 1.0
    """World length of one unit."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", torch.as_tensor(self.center, dtype=torch.float64).reshape(3))
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise InputError(
                f"Normalization.scale must be positive and finite, got {self.scale}; "
                f"the input probably has all points at one location"
            )
        object.__setattr__(self, "scale", float(self.scale))

    @classmethod
    def from_points(cls, points: Tensor) -> Normalization:
        """Centre the bounding box of `points` (n, 3), longest side 1."""
        points = torch.as_tensor(points, dtype=torch.float64)
        lo, hi = points.min(0).values, points.max(0).values
        return cls(center=(lo + hi) / 2, scale=float((hi - lo).max()))

    def to_unit(self, x: Tensor) -> Tensor:
        """World points x[..., 3] -> unit-frame points, same dtype and device."""
        return (x - self.center.to(x)) / self.scale

    def to_world(self, u: Tensor) -> Tensor:
        """Unit-frame points u[..., 3] -> world points, same dtype and device."""
        return u * self.scale + self.center.to(u)

    def cloud_to_unit(self, cloud: PointCloud) -> PointCloud:
        return replace(cloud, points=self.to_unit(cloud.points))

    def mesh_to_unit(self, mesh: Mesh) -> Mesh:
        return replace(mesh, vertices=self.to_unit(mesh.vertices))

    def mesh_to_world(self, mesh: Mesh) -> Mesh:
        return replace(mesh, vertices=self.to_world(mesh.vertices))

    def state_dict(self) -> dict[str, Tensor]:
        return {"center": self.center.clone(), "scale": torch.tensor(self.scale, dtype=torch.float64)}

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor]) -> Normalization:
        return cls(center=state["center"], scale=float(state["scale"]))


def _check_rigid(cam_to_world: Tensor, name: str, tolerance: float = 1e-3) -> None:
    """Raise InputError unless every 4x4 matrix (n, 4, 4) is finite and a rigid motion (R^T R = I,
    det R = 1, last row 0 0 0 1)."""
    finite = torch.isfinite(cam_to_world).all(dim=(1, 2))
    if not finite.all():
        first = int((~finite).nonzero()[0])
        pose = cam_to_world[first]
        part = ("rotation" if not torch.isfinite(pose[:3, :3]).all() else
                "translation" if not torch.isfinite(pose[:3, 3]).all() else "last row")
        raise InputError(
            f"{name}[{first}] holds NaN or inf (in its {part}; {int((~finite).sum())} bad poses of "
            f"{len(cam_to_world)}); drop those frames or fix their poses (a failed tracking step?)"
        )
    rotation = cam_to_world[:, :3, :3].double()
    identity = torch.eye(3, dtype=torch.float64, device=cam_to_world.device)
    orthogonal_error = (rotation.transpose(1, 2) @ rotation - identity).abs().amax(dim=(1, 2))
    bottom = torch.tensor([0, 0, 0, 1], dtype=cam_to_world.dtype, device=cam_to_world.device)
    bad = (orthogonal_error > tolerance) | (torch.linalg.det(rotation) < 0) | (
        (cam_to_world[:, 3] - bottom).abs().amax(dim=1) > tolerance
    )
    if bad.any():
        first = int(bad.nonzero()[0])
        raise InputError(
            f"{name}[{first}] is not a rigid camera-to-world transform (|R^T R - I| = "
            f"{float(orthogonal_error[first]):.2e}, det R = {float(torch.linalg.det(rotation[first])):.3f}); "
            f"poses must be 4x4 [R t; 0 0 0 1] with R a rotation ({int(bad.sum())} bad poses)"
        )


def check_intrinsics(K: Tensor, width: int, height: int, name: str = "K") -> None:
    """Raise InputError when an entry of K (n, 3, 3) is NaN or inf, its bottom row is not [0 0 1], a
    principal point lies outside its width x height image or a focal length is not positive
    (intrinsics of another resolution or camera)."""
    finite = torch.isfinite(K).all(dim=(1, 2))
    if not finite.all():
        i = int((~finite).nonzero()[0])
        raise InputError(
            f"{name}[{i}] holds NaN or inf (fx={float(K[i, 0, 0]):g}, fy={float(K[i, 1, 1]):g}, "
            f"cx={float(K[i, 0, 2]):g}, cy={float(K[i, 1, 2]):g}; {int((~finite).sum())} bad matrices): "
            f"focal lengths and principal points must be finite numbers in pixels; check the calibration file"
        )
    bottom = torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype, device=K.device)
    bad_row = (K[:, 2] - bottom).abs().amax(dim=1) > 1e-6
    if bad_row.any():
        i = int(bad_row.nonzero()[0])
        raise InputError(
            f"{name}[{i}] has bottom row {K[i, 2].tolist()}, not [0, 0, 1]: a pinhole K is "
            f"[[fx, s, cx], [0, fy, cy], [0, 0, 1]]; divide K by K[2, 2] if it was scaled, or pass the "
            f"3x3 intrinsics rather than a projection matrix"
        )
    cx, cy = K[:, 0, 2], K[:, 1, 2]
    bad = (cx < 0) | (cx > width) | (cy < 0) | (cy > height) | (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0)
    if bad.any():
        i = int(bad.nonzero()[0])
        raise InputError(
            f"mismatched intrinsics: {name}[{i}] does not fit a {width}x{height} image: "
            f"fx={float(K[i, 0, 0]):g}, fy={float(K[i, 1, 1]):g}, "
            f"principal point ({float(cx[i]):g}, {float(cy[i]):g}) must lie inside [0, {width}] x [0, {height}]; "
            f"intrinsics calibrated at another resolution must be scaled with the image (fx, fy, cx, cy by the same factor)"
        )


def _check_real(values, name: str) -> None:
    """Raise InputError when `values` (a tensor or array) is complex: casting it to float would drop
    the imaginary part with nothing more than a cast warning."""
    if values is None:
        return
    is_complex = values.is_complex() if isinstance(values, Tensor) else np.iscomplexobj(values)
    if is_complex:
        raise InputError(
            f"{name} is complex ({getattr(values, 'dtype', type(values).__name__)}); it must hold real numbers: "
            f"pass its real part (values.real) if the imaginary part is zero, or its magnitude if that is the reading"
        )


def float_colors(colors: Tensor) -> Tensor:
    """Colours as Float[Tensor, "... 3"] in [0, 1]: UInt8[Tensor, "... 3"] divided by 255, floats as they are."""
    return colors.float() / 255 if colors.dtype == torch.uint8 else colors


@dataclass(frozen=True)
class DepthFrames:
    """A batch of depth images with OpenCV pinhole cameras (x right, y down, z forward)."""

    depth: Tensor
    """Float[Tensor, "n h w"]: z-depth in metres (float32), 0 where there is no reading."""
    K: Tensor
    """Float[Tensor, "n 3 3"]: intrinsics per frame (a single 3x3 is broadcast to all frames)."""
    cam_to_world: Tensor
    """Float[Tensor, "n 4 4"]: camera-to-world rigid poses."""
    colors: Tensor | None = None
    """Float[Tensor, "n h w 3"] RGB in [0, 1], or UInt8[Tensor, "n h w 3"] in [0, 255] as colour images hold it
    (a quarter of the memory), registered to the depth; None. `float_colors` reads either."""

    def __post_init__(self) -> None:
        for name in ("depth", "K", "cam_to_world", "colors"):
            _check_real(getattr(self, name), f"DepthFrames.{name}")
        depth = torch.as_tensor(self.depth, dtype=torch.float32)
        if depth.ndim == 2:
            depth = depth[None]
        if depth.ndim != 3 or depth.numel() == 0:
            raise InputError(f"DepthFrames.depth must have shape (n, h, w), got {tuple(depth.shape)}")
        if not torch.isfinite(depth).all() or (depth < 0).any():
            raise InputError("DepthFrames.depth has NaN, inf or negative values; use 0 for missing readings")
        n = len(depth)
        K = torch.as_tensor(self.K, dtype=torch.float32)
        K = K.expand(n, 3, 3).clone() if K.shape == (3, 3) else K
        if K.shape != (n, 3, 3):
            raise InputError(f"DepthFrames.K must be 3x3 or (n={n}, 3, 3), got {tuple(K.shape)}")
        check_intrinsics(K, depth.shape[2], depth.shape[1], "DepthFrames.K")
        pose = torch.as_tensor(self.cam_to_world, dtype=torch.float32)
        pose = pose[None] if pose.shape == (4, 4) else pose
        if pose.shape != (n, 4, 4):
            raise InputError(
                f"DepthFrames.cam_to_world must be (n={n}, 4, 4) to match {n} depth images, got {tuple(pose.shape)}"
            )
        _check_rigid(pose, "DepthFrames.cam_to_world")
        sample = depth[:, ::8, ::8]  # the units check needs no sort of every reading (a room: 60M)
        valid = sample[sample > 0]
        if len(valid) and float(valid.median()) > 50.0:
            warnings.warn(
                f"DepthFrames.depth has a median of {float(valid.median()):.0f}: depth must be in metres, "
                f"this looks like millimetres (divide by 1000) or raw sensor units (divide by the depth scale)",
                stacklevel=3,
            )
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "K", K.to(depth.device))
        object.__setattr__(self, "cam_to_world", pose.to(depth.device))
        if self.colors is not None:
            colors = torch.as_tensor(self.colors)
            colors = colors if colors.dtype == torch.uint8 else colors.float()
            if colors.shape != (*depth.shape, 3):
                raise InputError(
                    f"DepthFrames.colors must be (n, h, w, 3) = {(*depth.shape, 3)}, got {tuple(colors.shape)}"
                )
            object.__setattr__(self, "colors", colors.to(depth.device))

    def __len__(self) -> int:
        return len(self.depth)

    @property
    def height(self) -> int:
        return self.depth.shape[1]

    @property
    def width(self) -> int:
        return self.depth.shape[2]

    def to(self, device: torch.device | str) -> DepthFrames:
        colors = None if self.colors is None else self.colors.to(device)
        return DepthFrames(self.depth.to(device), self.K.to(device), self.cam_to_world.to(device), colors)

    def __getitem__(self, index) -> DepthFrames:
        """Frames picked by an int, a slice or an index tensor (always a DepthFrames)."""
        index = [index] if isinstance(index, int) else index
        colors = None if self.colors is None else self.colors[index]
        return DepthFrames(self.depth[index], self.K[index], self.cam_to_world[index], colors)


@dataclass(frozen=True)
class PhotometricCapture:
    """Images of one view under n distant lights, in the project's camera frame (OpenCV: x right,
    y down, z forward; the viewer looks along +z, so normals facing the camera have z < 0).

    Light directions point from the surface towards the light (a light behind the camera has
    z < 0). Images are linear intensities already divided by each light's intensity.
    """

    images: Tensor
    """Float[Tensor, "n h w 3"] or Float[Tensor, "n h w"]: linear intensities (float32), one per light."""
    light_directions: Tensor
    """Float[Tensor, "n 3"]: unit directions towards each light, camera frame."""
    light_intensities: Tensor | None = None
    """Float[Tensor, "n 3"] | None: the intensities the images were divided by (RGB); None = all 1."""
    mask: Tensor | None = None
    """Bool[Tensor, "h w"] | None: pixels of the object; None = every pixel."""
    normals: Tensor | None = None
    """Float[Tensor, "h w 3"] | None: ground-truth unit normals in the camera frame (0 outside the mask)."""
    K: Tensor | None = None
    """Float[Tensor, "3 3"] | None: pinhole intrinsics; None = orthographic (or unknown) camera."""
    depth: Tensor | None = None
    """Float[Tensor, "h w"] | None: ground-truth z-depth in metres, 0 outside the object (synthetic rigs)."""
    cam_to_world: Tensor | None = None
    """Float[Tensor, "4 4"] | None: OpenCV camera-to-world pose (synthetic rigs, multi-view captures)."""

    def __post_init__(self) -> None:
        images = torch.as_tensor(self.images).float()
        if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[-1] != 3) or images.numel() == 0:
            raise InputError(
                f"PhotometricCapture.images must have shape (n, h, w) or (n, h, w, 3), got {tuple(images.shape)}"
            )
        if not torch.isfinite(images).all():
            raise InputError("PhotometricCapture.images contain NaN or inf; repair or drop those images")
        n, h, w = images.shape[:3]
        lights = as_tensor(self.light_directions, torch.float32, "PhotometricCapture.light_directions")
        if len(lights) != n:
            raise InputError(
                f"PhotometricCapture has {n} images but {len(lights)} light directions; give one direction per image"
            )
        norms = lights.norm(dim=-1)
        if (norms < 1e-6).any():
            raise InputError(
                f"PhotometricCapture.light_directions[{int((norms < 1e-6).nonzero()[0])}] is zero; "
                f"every light needs a direction"
            )
        object.__setattr__(self, "images", images)
        object.__setattr__(self, "light_directions", (lights / norms[:, None]).to(images.device))
        if self.light_intensities is not None:
            intensities = torch.as_tensor(self.light_intensities).float()
            intensities = intensities[:, None].expand(-1, 3) if intensities.ndim == 1 else intensities
            if intensities.shape != (n, 3):
                raise InputError(
                    f"PhotometricCapture.light_intensities must be (n={n}, 3) or (n,), got {tuple(intensities.shape)}"
                )
            object.__setattr__(self, "light_intensities", intensities.to(images.device))
        if self.mask is not None:
            mask = torch.as_tensor(self.mask).bool()
            if mask.shape != (h, w):
                raise InputError(f"PhotometricCapture.mask must be (h, w) = {(h, w)}, got {tuple(mask.shape)}")
            object.__setattr__(self, "mask", mask.to(images.device))
        for name, shape in (("normals", (h, w, 3)), ("depth", (h, w)), ("K", (3, 3)), ("cam_to_world", (4, 4))):
            value = getattr(self, name)
            if value is None:
                continue
            value = torch.as_tensor(value).float()
            if tuple(value.shape) != shape:
                raise InputError(f"PhotometricCapture.{name} must have shape {shape}, got {tuple(value.shape)}")
            object.__setattr__(self, name, value.to(images.device))

    def __len__(self) -> int:
        return len(self.images)

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def width(self) -> int:
        return self.images.shape[2]

    @property
    def is_color(self) -> bool:
        return self.images.ndim == 4

    def gray(self) -> Tensor:
        """Float[Tensor, "n h w"]: the mean of the colour channels (the images themselves when grey)."""
        return self.images.mean(-1) if self.is_color else self.images

    def pixel_mask(self) -> Tensor:
        """Bool[Tensor, "h w"]: the mask, or every pixel when there is none."""
        if self.mask is not None:
            return self.mask
        return torch.ones(self.height, self.width, dtype=torch.bool, device=self.images.device)

    def to(self, device: torch.device | str) -> PhotometricCapture:
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return PhotometricCapture(*(move(getattr(self, f)) for f in (
            "images", "light_directions", "light_intensities", "mask", "normals", "K", "depth", "cam_to_world")))
