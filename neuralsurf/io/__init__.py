"""File I/O: point clouds (.ply .xyz .npy .pcd) and meshes (.ply .obj .off .stl .glb).

`read_*` return the structures of `neuralsurf.structures` in the file's frame; `write_*` create
missing parent folders. Every failure is a `NeuralsurfError` (FileFormatError or InputError) whose
message names the file.
"""

from neuralsurf.io.meshes import SUPPORTED as MESH_EXTENSIONS
from neuralsurf.io.meshes import read_mesh, write_mesh
from neuralsurf.io.pointclouds import SUPPORTED as POINT_CLOUD_EXTENSIONS
from neuralsurf.io.pointclouds import read_point_cloud, write_point_cloud

__all__ = [
    "MESH_EXTENSIONS",
    "POINT_CLOUD_EXTENSIONS",
    "read_mesh",
    "read_point_cloud",
    "write_mesh",
    "write_point_cloud",
]
