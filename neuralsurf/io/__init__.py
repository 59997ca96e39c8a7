"""File I/O: point clouds (.ply .xyz .npy .pcd), meshes (.ply .obj .off .stl .glb), RGB-D folders
(7-Scenes, TUM, Redwood) and aligned range scans (Stanford .conf).

`read_*` return the structures of `neuralsurf.structures` in the file's frame; `write_*` create
missing parent folders. Every failure is a `NeuralsurfError` (FileFormatError or InputError, and
ConfigError for a bad argument value) whose message names the file.
"""

from neuralsurf.io.meshes import SUPPORTED as MESH_EXTENSIONS
from neuralsurf.io.meshes import read_mesh, write_mesh
from neuralsurf.io.pointclouds import SUPPORTED as POINT_CLOUD_EXTENSIONS
from neuralsurf.io.pointclouds import read_point_cloud, write_point_cloud
from neuralsurf.io.range_scans import (
    read_range_scan,
    read_range_scan_conf,
    read_range_scan_frames,
    read_range_scan_meshes,
    read_range_scans,
)
from neuralsurf.io.rgbd import FORMATS as RGBD_FORMATS
from neuralsurf.io.rgbd import read_rgbd_folder
from neuralsurf.io.photometric import read_image_list, read_photometric, write_photometric  # noqa: F401

__all__ = [
    "MESH_EXTENSIONS",
    "POINT_CLOUD_EXTENSIONS",
    "RGBD_FORMATS",
    "read_mesh",
    "read_point_cloud",
    "read_range_scan",
    "read_range_scan_conf",
    "read_range_scan_frames",
    "read_range_scan_meshes",
    "read_range_scans",
    "read_rgbd_folder",
    "write_mesh",
    "write_point_cloud",
]
