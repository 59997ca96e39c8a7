"""Built-in data: the Stanford bunny, analytic shapes with exact SDFs, synthetic scanners, scene recipes."""

from neuralsurf.scenes.analytic import Box, Sphere, Torus, analytic_shape
from neuralsurf.scenes.bunny import bunny, bunny_path
from neuralsurf.scenes.photometric_rig import SpecularLobe, cap_lights, render_photometric, ring_lights  # noqa: F401
from neuralsurf.scenes.recipes import (
    Scene,
    SceneUnavailable,
    analytic_scene,
    bunny_depth,
    bunny_points,
    bunny_specular_ps,
    data_root,
    depth_scene,
    extract_scene_mesh,
    file_scene,
    mesh_scene,
    redkitchen,
    rgbd_scene,
    rig_fusion,
    rig_lambertian,
    rig_specular,
    stanford_scans,
)
from neuralsurf.scenes.scanner import look_at, orbit_cameras, scan_depth

__all__ = ["Box", "Scene", "SceneUnavailable", "Sphere", "Torus", "analytic_scene", "analytic_shape", "bunny",
           "bunny_depth", "bunny_path", "bunny_points", "bunny_specular_ps", "data_root", "depth_scene", "extract_scene_mesh", "file_scene", "look_at",
           "mesh_scene", "orbit_cameras", "redkitchen", "rgbd_scene", "rig_fusion", "rig_lambertian", "rig_specular", "scan_depth",
           "stanford_scans"]
