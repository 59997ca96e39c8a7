"""The scenes of a shape collection's test shapes, in the prior's unit frame and canonical pose: noisy
clouds (`shapes_cloud`) and one depth view each (`shapes_one_view`), as scene sets (one row of an
evaluation, metrics averaged over the shapes)."""

from __future__ import annotations

from functools import lru_cache

from neuralsurf.errors import ConfigError
from neuralsurf.geometry import noisy_cloud
from neuralsurf.priors.collection import Collection, TestShape
from neuralsurf.scenes.recipes import Scene, SceneSet, depth_scene
from neuralsurf.scenes.scanner import ONE_VIEW_IMAGE, one_view_camera, scan_depth
from neuralsurf.structures import PointCloud


def _test_shapes(collection: Collection, limit: int | None) -> list[TestShape]:
    """The built collection's first `limit` test shapes. A collection without test shapes, or without
    meshes (Occupancy Networks' layout), is a ConfigError before anything is built."""
    if not collection.count("test"):
        raise ConfigError(f"{collection.description}: no test shapes to evaluate on; list some in test.lst or set "
                          f"test_fraction > 0 (a class needs two shapes for one to be held out)")
    if getattr(collection, "layout", "meshes") == "occupancy":
        raise ConfigError(f"{collection.source} is in Occupancy Networks' layout, which has no meshes to evaluate "
                          f"test shapes against; evaluate on a mesh folder of the same classes")
    collection.build(progress=False)
    return collection.test_shapes(limit)


@lru_cache(maxsize=4)
def shapes_cloud(collection, name: str = "shapes_cloud", n_points: int = 3000, noise: float = 0.005,
                 limit: int | None = None, seed: int = 0) -> SceneSet:
    """`n_points` surface points of each test shape of `collection` with N(0, noise^2) noise (unit
    frame: the shape's longest side is 1), no normals."""
    scenes = tuple(Scene(shape.name, PointCloud(noisy_cloud(shape.surface, n_points, noise, seed + i)), shape.mesh,
                         description=f"{n_points} points, noise {noise:g}")
                   for i, shape in enumerate(_test_shapes(collection, limit)))
    return SceneSet(name, scenes, f"{len(scenes)} test shapes of {collection.description}; {n_points} surface "
                                  f"points each, Gaussian noise {noise:g} (longest side 1)")


@lru_cache(maxsize=4)
def shapes_one_view(collection, name: str = "shapes_one_view", width: int = ONE_VIEW_IMAGE["width"],
                    height: int = ONE_VIEW_IMAGE["height"], fov_deg: float = ONE_VIEW_IMAGE["fov_deg"],
                    distance: float = 1.6, noise: float = 0.001, limit: int | None = None, seed: int = 0) -> SceneSet:
    """One synthetic depth view (Gaussian noise `noise`, unit frame) of each test shape of
    `collection`, from a random side (`one_view_camera`); point methods get its back-projection."""
    scenes = []
    for i, shape in enumerate(_test_shapes(collection, limit)):
        frames = scan_depth(shape.mesh, cam_to_world=one_view_camera(seed + i, distance)[None], width=width,
                            height=height, fov_deg=fov_deg, noise="gaussian" if noise > 0 else "none",
                            sigma=noise if noise > 0 else None, seed=seed + i)
        scenes.append(depth_scene(shape.name, frames, shape.mesh, description=f"noise {noise:g}"))
    return SceneSet(name, tuple(scenes), f"{len(scenes)} test shapes of {collection.description}; one "
                                         f"{width}x{height} depth view each, Gaussian noise {noise:g}")
