"""Photometric-stereo captures: the DiLiGenT folder layout and image lists (UW CSE 576 `psmImages`).

DiLiGenT layout (Shi et al., CVPR 2016), one folder per object:

- ``filenames.txt``: one image name per line, relative to the folder (or to its ``images/`` subfolder).
- ``light_directions.txt``: one unit direction per line (x y z), same order, towards the light.
- ``light_intensities.txt`` (optional): one RGB (or single) intensity per line; each image is divided
  by its row.
- ``mask.png`` (optional): non-zero on the object. Without it the mask is derived from the images
  (a black background): pixels whose brightest observation exceeds `mask_threshold`.
- ``Normal_gt.mat`` (variable ``Normal_gt``, h x w x 3) or ``Normal_gt.png`` (encoded (n + 1) / 2
  in 8 or 16 bits) (optional): ground-truth normals.
- images: 8- or 16-bit PNGs (grey or RGB), linear intensities.

**Axes.** DiLiGenT writes light directions and normals with x right, y up, z towards the camera
(the viewer sits at +z). neuralsurf's camera frame is OpenCV's: x right, y down, z forward (the
viewer looks along +z). A DiLiGenT vector (x, y, z) is the camera-frame vector (x, -y, -z):
`diligent_to_camera` converts (it is its own inverse). `read_photometric` returns camera-frame
vectors, `write_photometric` writes DiLiGenT ones, so files stay compatible with other tools.

Extras written by `write_photometric` so that synthetic captures round-trip (read when present):
``K.txt`` (3x3), ``cam_to_world.txt`` (4x4), ``depth.npy`` (h x w metres).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.structures import PhotometricCapture

_FLIP = torch.tensor([1.0, -1.0, -1.0])


def diligent_to_camera(vectors: Tensor) -> Tensor:
    """Float[Tensor, "... 3"] in DiLiGenT axes (x right, y up, z to the viewer) -> the OpenCV camera
    frame (x right, y down, z forward), and back (the map is its own inverse): (x, y, z) -> (x, -y, -z)."""
    vectors = torch.as_tensor(vectors)
    return vectors * _FLIP.to(vectors.device, vectors.dtype if vectors.is_floating_point() else torch.float32)


camera_to_diligent = diligent_to_camera


def read_image(path: str | Path) -> np.ndarray:
    """Float32 array "h w" or "h w 3" in [0, 1] of an 8- or 16-bit PNG (grey, RGB or RGBA: alpha dropped)."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"image {path} does not exist; check the file list that names it")
    image = o3d.t.io.read_image(str(path))
    if image.is_empty():
        raise FileFormatError(
            f"could not read image {path}: not a PNG/JPEG Open3D can decode; convert it to PNG"
        )
    array = image.as_tensor().numpy()
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(array.dtype)
    if scale is None:
        raise FileFormatError(
            f"image {path} has {array.dtype} pixels; photometric images must be 8- or 16-bit"
        )
    array = array.astype(np.float32) / scale
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    elif array.ndim == 3 and array.shape[2] == 4:
        array = array[..., :3]
    return array


def _write_png(path: Path, array: np.ndarray, bits: int) -> None:
    """Write a float array in [0, 1] ("h w" or "h w 3") as an 8- or 16-bit PNG."""
    import open3d as o3d

    dtype, scale = (np.uint8, 255.0) if bits == 8 else (np.uint16, 65535.0)
    data = np.rint(np.clip(array, 0.0, 1.0) * scale).astype(dtype)
    data = np.ascontiguousarray(data[..., None] if data.ndim == 2 else data)
    if not o3d.t.io.write_image(str(path), o3d.t.geometry.Image(o3d.core.Tensor(data))):
        raise FileFormatError(f"could not write {path}; check that the folder is writable")


def _read_rows(path: Path, columns: tuple[int, ...], what: str) -> np.ndarray:
    try:
        rows = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except ValueError as error:
        raise FileFormatError(
            f"{path} is not a table of numbers ({error}); write one {what} per line"
        ) from None
    if rows.shape[1] not in columns or not np.isfinite(rows).all():
        raise FileFormatError(
            f"{path} must hold one {what} per line with {' or '.join(map(str, columns))} finite numbers, "
            f"got rows of {rows.shape[1]}"
        )
    return rows


def _stack_images(paths: list[Path], color: bool) -> np.ndarray:
    images, first = [], None
    for path in paths:
        image = read_image(path)
        if image.ndim == 3 and not color:
            image = image.mean(-1)
        elif image.ndim == 2 and color:
            image = np.repeat(image[..., None], 3, axis=-1)
        if first is None:
            first = (path, image.shape[:2])
        elif image.shape[:2] != first[1]:
            raise InputError(
                f"images of different sizes: {path.name} is {image.shape[1]}x{image.shape[0]} but "
                f"{first[0].name} is {first[1][1]}x{first[1][0]} (width x height); every image of a capture "
                f"must come from the same camera at the same resolution"
            )
        images.append(image)
    return np.stack(images)


def derive_mask(images: Tensor, threshold: float = 0.02) -> Tensor:
    """Bool[Tensor, "h w"]: pixels whose brightest observation over images [n, h, w(, 3)] exceeds
    `threshold` times the brightest pixel of the capture (for captures on a black background)."""
    brightest = images.amax(dim=0)
    brightest = brightest.amax(dim=-1) if brightest.ndim == 3 else brightest
    return brightest > threshold * brightest.max().clamp_min(1e-12)


def _decode_normals(array: np.ndarray, path: Path) -> np.ndarray:
    if array.ndim != 3 or array.shape[2] != 3:
        raise FileFormatError(f"{path} must hold an h x w x 3 normal map, got shape {array.shape}")
    norm = np.linalg.norm(array, axis=-1, keepdims=True)
    valid = norm[..., 0] > 0.5  # the background of an encoded map is (0.5, 0.5, 0.5) -> ~0, or exactly 0
    return np.where(valid[..., None], array / np.maximum(norm, 1e-12), 0.0)


def _find_image(folder: Path, name: str) -> Path:
    for candidate in (folder / name, folder / "images" / name):
        if candidate.is_file():
            return candidate
    raise FileFormatError(
        f"image {name!r} listed in {folder / 'filenames.txt'} is neither in {folder} nor in {folder / 'images'}"
    )


def read_photometric(
    path: str | Path,
    *,
    color: bool = True,
    mask_threshold: float = 0.02,
    K=None,
) -> PhotometricCapture:
    """Read a DiLiGenT-layout folder (see the module docstring) into a `PhotometricCapture`.

    Args:
        path: the object's folder.
        color: keep RGB images (n, h, w, 3); False averages the channels to (n, h, w).
        mask_threshold: without ``mask.png``, the mask is every pixel whose brightest observation
            exceeds this fraction of the capture's brightest pixel (`derive_mask`).
        K: Float[Tensor, "3 3"] intrinsics to attach (overrides ``K.txt``); None: orthographic/unknown.
    Returns:
        PhotometricCapture in the camera frame (x right, y down, z forward): images divided by the
        light intensities, unit light directions (n, 3), mask (h, w), ground-truth normals (h, w, 3)
        when the folder has them (0 outside the object).
    """
    folder = Path(path)
    if not folder.is_dir():
        raise FileFormatError(f"photometric capture folder {folder} does not exist")
    if not 0 <= mask_threshold < 1:
        raise ConfigError(f"mask_threshold must lie in [0, 1), got {mask_threshold}")
    for required in ("filenames.txt", "light_directions.txt"):
        if not (folder / required).is_file():
            raise FileFormatError(
                f"{folder} has no {required}; a DiLiGenT-layout capture needs filenames.txt (one image per "
                f"line) and light_directions.txt (one x y z direction per line, same order)"
            )
    names = [line.strip() for line in (folder / "filenames.txt").read_text().splitlines() if line.strip()]
    if not names:
        raise FileFormatError(f"{folder / 'filenames.txt'} lists no images")
    lights = _read_rows(folder / "light_directions.txt", (3,), "light direction (x y z)")
    if len(lights) != len(names):
        raise InputError(
            f"{folder}: filenames.txt lists {len(names)} images but light_directions.txt has {len(lights)} "
            f"directions; the two files need one line per image, in the same order"
        )
    images = _stack_images([_find_image(folder, name) for name in names], color)
    intensities = None
    if (folder / "light_intensities.txt").is_file():
        intensities = _read_rows(folder / "light_intensities.txt", (1, 3), "light intensity (r g b)")
        if len(intensities) != len(names):
            raise InputError(
                f"{folder}: light_intensities.txt has {len(intensities)} rows for {len(names)} images; "
                f"give one intensity per image"
            )
        intensities = np.repeat(intensities, 3, axis=1) if intensities.shape[1] == 1 else intensities
        if (intensities <= 0).any():
            raise InputError(
                f"{folder / 'light_intensities.txt'} has non-positive intensities; they must be > 0"
            )
        images = images / (intensities[:, None, None, :] if color else intensities.mean(1)[:, None, None])
    images = torch.from_numpy(images.astype(np.float32))
    if (folder / "mask.png").is_file():
        mask = read_image(folder / "mask.png")
        mask = torch.from_numpy((mask.max(-1) if mask.ndim == 3 else mask) > 0)
        if mask.shape != images.shape[1:3]:
            raise InputError(
                f"{folder / 'mask.png'} is {mask.shape[1]}x{mask.shape[0]} but the images are "
                f"{images.shape[2]}x{images.shape[1]}; the mask must match the images"
            )
    else:
        mask = derive_mask(images, mask_threshold)
    normals = None
    if (folder / "Normal_gt.mat").is_file():
        from scipy.io import loadmat

        content = {k: v for k, v in loadmat(folder / "Normal_gt.mat").items() if not k.startswith("__")}
        array = content.get("Normal_gt", next(iter(content.values()), None) if len(content) == 1 else None)
        if array is None:
            raise FileFormatError(
                f"{folder / 'Normal_gt.mat'} has no variable Normal_gt (found {list(content)})"
            )
        normals = _decode_normals(np.asarray(array, dtype=np.float64), folder / "Normal_gt.mat")
    elif (folder / "Normal_gt.png").is_file():
        normals = _decode_normals(
            read_image(folder / "Normal_gt.png").astype(np.float64) * 2 - 1, folder / "Normal_gt.png"
        )
    if normals is not None:
        if normals.shape[:2] != tuple(images.shape[1:3]):
            raise InputError(
                f"{folder}: the ground-truth normal map is {normals.shape[:2]}, the images "
                f"{tuple(images.shape[1:3])}; they must match"
            )
        normals = diligent_to_camera(torch.from_numpy(normals).float()) * mask[..., None]
    if K is None and (folder / "K.txt").is_file():
        K = _read_rows(folder / "K.txt", (3,), "row of K")
    depth = (
        torch.from_numpy(np.load(folder / "depth.npy")).float() if (folder / "depth.npy").is_file() else None
    )
    pose = (
        _read_rows(folder / "cam_to_world.txt", (4,), "row of the pose")
        if (folder / "cam_to_world.txt").is_file()
        else None
    )
    return PhotometricCapture(
        images=images,
        light_directions=diligent_to_camera(torch.from_numpy(lights).float()),
        light_intensities=None if intensities is None else torch.from_numpy(intensities).float(),
        mask=mask,
        normals=normals,
        K=None if K is None else torch.as_tensor(np.asarray(K), dtype=torch.float32),
        depth=depth,
        cam_to_world=None if pose is None else torch.from_numpy(pose).float(),
    )


def write_photometric(path: str | Path, capture: PhotometricCapture, bits: int = 16) -> Path:
    """Write `capture` as a DiLiGenT-layout folder that `read_photometric` reads back.

    Images are written as `bits`-bit PNGs (``001.png`` ...) after multiplying by the light
    intensities; when that exceeds 1, images and intensities are scaled down by the same factor (so
    reading and dividing gives the capture back, to the PNG's quantisation). Directions and normals
    are written in DiLiGenT axes; normals to ``Normal_gt.mat`` (exact) and ``Normal_gt.png``.
    Returns the folder.
    """
    if bits not in (8, 16):
        raise ConfigError(f"bits must be 8 or 16, got {bits}")
    if (capture.images < 0).any():
        raise InputError(
            "PhotometricCapture.images has negative intensities, which a PNG cannot store; "
            "clamp them to 0 before writing"
        )
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    images = capture.images.detach().cpu().double().numpy()
    intensities = (
        None if capture.light_intensities is None else capture.light_intensities.cpu().double().numpy()
    )
    raw = (
        images * (intensities[:, None, None, :] if capture.is_color else intensities.mean(1)[:, None, None])
        if intensities is not None
        else images
    )
    peak = float(raw.max())
    if peak > 1.0:  # scale images and intensities alike: the quotient read back is unchanged
        raw = raw / peak
        intensities = (np.ones((len(images), 3)) if intensities is None else intensities) / peak
    width = len(str(len(images)))
    names = [f"{i + 1:0{max(3, width)}d}.png" for i in range(len(images))]
    for name, image in zip(names, raw):
        _write_png(folder / name, image, bits)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(
        folder / "light_directions.txt",
        camera_to_diligent(capture.light_directions.cpu().double()).numpy(),
        fmt="%.9f",
    )
    if intensities is not None:
        np.savetxt(folder / "light_intensities.txt", intensities, fmt="%.9g")
    if capture.mask is not None:
        _write_png(folder / "mask.png", capture.mask.cpu().numpy().astype(np.float64), 8)
    if capture.normals is not None:
        from scipy.io import savemat

        normals = camera_to_diligent(capture.normals.cpu().double()).numpy()
        savemat(folder / "Normal_gt.mat", {"Normal_gt": normals})
        _write_png(
            folder / "Normal_gt.png",
            np.where(np.linalg.norm(normals, axis=-1, keepdims=True) > 0, (normals + 1) / 2, 0.5),
            16,
        )
    if capture.K is not None:
        np.savetxt(folder / "K.txt", capture.K.cpu().double().numpy(), fmt="%.9g")
    if capture.cam_to_world is not None:
        np.savetxt(folder / "cam_to_world.txt", capture.cam_to_world.cpu().double().numpy(), fmt="%.9g")
    if capture.depth is not None:
        np.save(folder / "depth.npy", capture.depth.cpu().numpy())
    return folder


def read_image_list(list_file: str | Path, color: bool = True) -> tuple[Tensor, Tensor | None]:
    """Images and mask of an image list in the UW CSE 576 ``psmImages`` format.

    The list file holds the image count, then one path per line (relative to the list's folder or
    to its parent); a further path ending in ``mask.png`` is the mask.

    Returns:
        images Float[Tensor, "n h w 3"] (or "n h w" when `color` is False) in [0, 1], and the mask
        Bool[Tensor, "h w"] (non-zero pixels) or None.
    """
    list_file = Path(list_file)
    if not list_file.is_file():
        raise FileFormatError(f"image list {list_file} does not exist")
    lines = [line.strip() for line in list_file.read_text().splitlines() if line.strip()]
    try:
        count = int(lines[0])
    except (IndexError, ValueError):
        raise FileFormatError(f"{list_file} must start with the number of images, got {lines[:1]}") from None
    if len(lines) - 1 < count:
        raise InputError(f"{list_file} announces {count} images but lists {len(lines) - 1} paths")

    def resolve(name: str) -> Path:
        for root in (list_file.parent, list_file.parent.parent):
            if (root / name).is_file():
                return root / name
        raise FileFormatError(
            f"{name!r} (listed in {list_file}) is in neither {list_file.parent} nor its parent"
        )

    images = torch.from_numpy(_stack_images([resolve(name) for name in lines[1 : 1 + count]], color))
    mask = None
    extra = [name for name in lines[1 + count :] if name.endswith("mask.png")]
    if extra:
        array = read_image(resolve(extra[0]))
        mask = torch.from_numpy((array.max(-1) if array.ndim == 3 else array) > 0.5)
        if mask.shape != images.shape[1:3]:
            raise InputError(f"mask {extra[0]} is {tuple(mask.shape)}, the images {tuple(images.shape[1:3])}")
    elif len(lines) - 1 > count:
        warnings.warn(
            f"{list_file}: ignoring {len(lines) - 1 - count} lines after the {count} images", stacklevel=2
        )
    return images, mask


__all__ = [
    "camera_to_diligent",
    "derive_mask",
    "diligent_to_camera",
    "read_image",
    "read_image_list",
    "read_photometric",
    "write_photometric",
]
