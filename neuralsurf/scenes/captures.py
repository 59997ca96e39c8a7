"""Real captures found by their folder under the data root: any RGB-D sequence `neuralsurf.io.read_rgbd_folder`
reads (7-Scenes, TUM RGB-D, Redwood), as a depth scene scored on held-out frames; the UW photometric set's
grey sphere, scored against the sphere its mask outlines."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import torch

from neuralsurf.io import read_image_list
from neuralsurf.photometric import calibrate_chrome_ball, sphere_from_mask
from neuralsurf.scenes.recipes import Scene, SceneUnavailable, data_path, scene_unavailable
from neuralsurf.structures import PhotometricCapture, PointCloud


def sphere_normals(mask) -> torch.Tensor:
    """Float[Tensor, "h w 3"]: the unit normals of the sphere whose silhouette is the disc of `mask`
    (`sphere_from_mask`: centroid and the radius of a disc of its area), seen orthographically, in the camera
    frame (towards the viewer: z < 0); 0 outside the mask. Pixels of the mask beyond the disc get the
    silhouette's normal (z = 0)."""

    mask = torch.as_tensor(mask).bool()
    centre, radius = sphere_from_mask(mask)
    v, u = torch.meshgrid(torch.arange(mask.shape[0]), torch.arange(mask.shape[1]), indexing="ij")
    x, y = (u - centre[0]) / radius, (v - centre[1]) / radius
    planar = torch.stack([x, y], -1)
    planar = planar / planar.norm(dim=-1, keepdim=True).clamp_min(1.0)  # beyond the disc: on its rim
    z = -(1 - (planar**2).sum(-1)).clamp_min(0).sqrt()
    normals = torch.cat([planar, z[..., None]], -1).float()
    return torch.where(mask[..., None], normals, 0.0)


@lru_cache(maxsize=2)
def uw_gray_sphere(name: str = "uw_gray_sphere", root: str | None = None, folder: str = "uw_photometric/psmImages",
                   sphere: str = "gray", chrome: str = "chrome") -> Scene:
    """The matte grey sphere of the UW CSE 576 photometric set under its 12 lights, the lights calibrated from
    the set's chrome ball (`calibrate_chrome_ball`); ground truth: the normals of the sphere its mask outlines
    (`sphere_normals`), so photometric stereo on a real capture is scored by angular error. Like
    `bunny_specular_ps` it has no camera: its cloud is the sphere's front in pixel units (orthographic)."""

    path = data_path(root, folder)
    lists = [path / f"{sphere}.txt", path / f"{chrome}.txt"]
    for needed in lists:
        if not needed.is_file():
            raise scene_unavailable(needed, Path(folder).parts[0])
    chrome_images, chrome_mask = read_image_list(lists[1])
    images, mask = read_image_list(lists[0])
    if chrome_mask is None or mask is None:
        raise SceneUnavailable(f"{lists[0]} and {lists[1]} must name their masks (a last line ending in mask.png)")
    lights = calibrate_chrome_ball(chrome_images, chrome_mask).directions
    normals = sphere_normals(mask)
    capture = PhotometricCapture(images, lights, mask=mask, normals=normals)
    v, u = torch.nonzero(mask, as_tuple=True)
    _, radius = sphere_from_mask(mask)
    points = torch.stack([u.double(), v.double(), radius * normals[v, u, 2].double()], -1)
    cloud = PointCloud(points, normals[v, u].double())
    return Scene(name, cloud, None, description=f"{len(capture)} lights calibrated from the chrome ball, "
                                                 f"{capture.width}x{capture.height}, real matte sphere ({path})",
                 photometric=(capture,), cloud_from_truth=True)
