"""Read RGB-D sequences (Microsoft 7-Scenes, TUM RGB-D, Redwood) into `DepthFrames`.

Every reader returns depth in metres (float32, 0 = invalid: sensor codes such as 65535 are mapped
to 0), OpenCV intrinsics `K` and camera-to-world poses; colour (RGB in [0, 1]) when asked for.

Layouts:

- **7-Scenes**: `frame-XXXXXX.{color.png|color.jpg, depth.png, pose.txt}` directly in the folder or
  in its one subfolder that holds such frames (`frames/`, `seq-01/`, ...: several are an error asking
  to point at one); 16-bit depth in millimetres, 0 and 65535 invalid; `pose.txt` a 4x4
  camera-to-world; `camera-intrinsics.txt` a 3x3 K, looked for in the folder given, then in the
  frames' folder, then (when the folder given holds the frames itself) in its parent, which is
  logged (fx = fy = 585, cx = 320, cy = 240 with a warning when none is found). The Kinect's colour and depth cameras are *not* registered in 7-Scenes:
  colour is loaded as-is (resized to the depth's size if needed), so a pixel's colour is only an
  approximation of the colour of its depth sample; a warning says so whenever colour is loaded.
  Checked on redkitchen: successive frames (10 raw frames apart) back-projected through their poses
  agree with a median depth difference of ~6 mm; reading the poses as world-to-camera gives 13-240 mm.
- **TUM RGB-D**: `depth.txt`, `rgb.txt` (`timestamp path` lines) and `groundtruth.txt`
  (`timestamp tx ty tz qx qy qz qw`, the colour camera's pose in the world); depth is 16-bit with
  5000 units per metre, registered to the colour image. Each depth image takes the pose (and colour
  image) with the nearest timestamp; depth images without one within `tolerance` seconds are left
  out with a warning. K defaults to the calibration of freiburg1/2/3 when the folder name says
  which, else to the ROS default (525, 525, 319.5, 239.5) with a warning.
- **Redwood**: `depth/*.png` (16-bit millimetres), `image/` (or `rgb/`, `color/`) colour images,
  and one trajectory `*.log`: per frame a line `id id n` (the first number is the frame's index in
  the sorted depth files) then 4 lines of a 4x4 camera-to-world. K defaults to the PrimeSense
  (525, 525, 319.5, 239.5) that the Redwood data use. Colour is registered to depth.
"""

from __future__ import annotations

import logging
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from neuralsurf.cameras import quaternion_to_matrix
from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.io.pointclouds import PathLike
from neuralsurf.io.trajectories import sensor_intrinsics
from neuralsurf.progress import progress_bar
from neuralsurf.structures import DepthFrames, check_intrinsics

FORMATS = ("7scenes", "tum", "redwood")
"""RGB-D folder layouts `read_rgbd_folder` understands (plus "auto")."""

SEVEN_SCENES_K = ((585.0, 0.0, 320.0), (0.0, 585.0, 240.0), (0.0, 0.0, 1.0))
"""7-Scenes' published intrinsics, used when camera-intrinsics.txt is absent."""

TUM_K = {  # fx, fy, cx, cy of the TUM RGB-D colour cameras (the depth is registered to them)
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
    "default": (525.0, 525.0, 319.5, 239.5),
}
"""Per-sensor TUM intrinsics; "default" is the ROS default used when the folder names no sensor."""

COLOR_REGISTERED = {"7scenes": False, "tum": True, "redwood": True}
"""Whether a format's colour pixel (u, v) sees the same point as its depth pixel (u, v)."""

REDWOOD_K = ((525.0, 0.0, 319.5), (0.0, 525.0, 239.5), (0.0, 0.0, 1.0))
"""PrimeSense intrinsics of the Redwood data."""

_COLOR_FOLDERS = ("image", "rgb", "color")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_INTRINSICS = "camera-intrinsics.txt"  # 7-Scenes
_SEVEN_SCENES_DEPTH = "frame-*.depth.png"

MARKERS = {
    "7-Scenes": "frame-XXXXXX.depth.png + .pose.txt (+ camera-intrinsics.txt) in the folder or one subfolder",
    "TUM": "depth.txt + groundtruth.txt (+ rgb.txt) in the folder",
    "Redwood": "depth/*.png + a trajectory *.log in the folder",
}
"""What `detect_rgbd_format` looks for, per layout (named in its error)."""

log = logging.getLogger("neuralsurf")


@dataclass(frozen=True)
class _Listing:
    """What a folder holds, before any image is decoded."""

    depth_paths: list[Path]
    color_paths: list[Path] | None
    poses: np.ndarray  # (n, 4, 4) camera-to-world
    K: np.ndarray  # (3, 3)
    depth_scale: float  # file units per metre
    invalid: tuple[int, ...]  # raw codes meaning "no reading"
    registered: bool  # colour pixel (u, v) sees the same point as depth pixel (u, v)


# ---------------------------------------------------------------------------------------------
# public


def read_rgbd_folder(
    path: PathLike,
    format: str = "auto",
    stride: int = 1,
    max_frames: int | None = None,
    with_color: bool = True,
    K=None,
    tolerance: float = 0.02,
    progress: bool = True,
) -> DepthFrames:
    """Read an RGB-D sequence folder into DepthFrames (layouts in the module docstring).

    Args:
        path: the sequence folder; for 7-Scenes also a folder holding camera-intrinsics.txt and one
            subfolder of frames, or that subfolder (its parent's camera-intrinsics.txt is used, logged).
        format: "auto" (detected from the files), "7scenes", "tum" or "redwood".
        stride: keep every `stride`-th frame (in time order), starting with the first.
        max_frames: keep at most this many frames (after the stride), or None for all.
        with_color: also load colour into `DepthFrames.colors`.
        K: 3x3 intrinsics overriding the folder's (or the format's default).
        tolerance: TUM only, the largest timestamp difference (s) between a depth image and the
            pose or colour image it is associated with.
        progress: a progress bar over the images when decoding them lasts more than a few seconds
            (neuralsurf.progress); False for none.
    Returns:
        DepthFrames: depth (n, h, w) float32 metres, K (n, 3, 3), cam_to_world (n, 4, 4),
        colors (n, h, w, 3) in [0, 1] or None.
    Raises:
        FileFormatError for a missing folder or file, a folder without frames or an unreadable
        or non-16-bit depth image; InputError for mismatched depth/colour sizes, mismatched
        intrinsics (principal point outside the image) and non-rigid poses; ConfigError for an
        unknown format or a bad stride / max_frames.
    """
    path = Path(path)
    if not path.is_dir():
        why = "is a file, not a folder" if path.exists() else "not found"
        raise FileFormatError(f"RGB-D folder {str(path)!r} {why}; pass the folder holding the sequence")
    if not isinstance(stride, int) or stride < 1:
        raise ConfigError(f"stride must be a positive integer (keep every stride-th frame), got {stride!r}")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise ConfigError(f"max_frames must be a positive integer or None, got {max_frames!r}")
    format = detect_rgbd_format(path) if format == "auto" else format
    if format not in FORMATS:
        raise ConfigError(f"unknown RGB-D format {format!r}; use 'auto' or one of {', '.join(FORMATS)}")
    if format == "7scenes":
        listing = _list_7scenes(path, with_color, K)
    elif format == "tum":
        listing = _list_tum(path, with_color, tolerance, K)
    else:
        listing = _list_redwood(path, with_color, K)
    keep = np.arange(0, len(listing.depth_paths), stride)[:max_frames]
    return _load(listing, keep, with_color, path, progress)


def detect_rgbd_format(path: PathLike) -> str:
    """The layout of an RGB-D folder: "7scenes", "tum" or "redwood" (module docstring; MARKERS).

    TUM and Redwood are recognised in `path` itself, 7-Scenes frames in `path` or in its one subfolder
    holding them. FileFormatError if none fits (naming each layout's markers and the folders checked),
    or if several subfolders hold 7-Scenes frames (naming them: point at one).
    """
    path = Path(path)
    if (path / "depth.txt").is_file() and (path / "groundtruth.txt").is_file():
        return "tum"
    if _seven_scenes_folder(path) is not None:
        return "7scenes"
    if (path / "depth").is_dir() and list(path.glob("*.log")):
        return "redwood"
    subfolders = _subfolders(path)
    checked = ", ".join(f"{p.name}/" for p in subfolders[:8]) + (f" and {len(subfolders) - 8} more"
                                                                  if len(subfolders) > 8 else "")
    raise FileFormatError(
        f"{str(path)!r} holds no RGB-D frames of a known layout. Looked for "
        + "; ".join(f"{name}: {markers}" for name, markers in MARKERS.items())
        + f". Checked {str(path)!r}" + (f" and its subfolders {checked}" if subfolders else " (no subfolders)")
        + "; point data.path= (read_rgbd_folder's path) at the folder of one sequence"
    )


def read_depth_png(path: PathLike, depth_scale: float, invalid: tuple[int, ...] = (0,)) -> np.ndarray:
    """A 16-bit depth PNG -> Float32[ndarray, "h w"] metres, `invalid` codes mapped to 0.

    `depth_scale` is the number of file units per metre (1000 for millimetres, 5000 for TUM).
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"depth image {str(path)!r} not found; the folder's frame list names it")
    try:
        with Image.open(path) as image:
            mode = image.mode
            raw = np.array(image) if mode.startswith("I;16") else None
    except (UnidentifiedImageError, OSError) as error:
        raise FileFormatError(f"cannot read depth image {str(path)!r}: {error}") from error
    if raw is None:
        raise FileFormatError(
            f"depth image {str(path)!r} is not 16-bit single-channel (PIL mode {mode!r}, expected 'I;16'); "
            f"depth must be stored as 16-bit PNG in sensor units, not as an 8-bit or colour picture"
        )
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    for code in invalid:
        depth[raw == code] = 0.0
    return depth


def read_color_image(path: PathLike, size: tuple[int, int] | None = None, as_bytes: bool = False) -> np.ndarray:
    """A colour image -> Float32[ndarray, "h w 3"] RGB in [0, 1] (`as_bytes`: UInt8[ndarray, "h w 3"] in
    [0, 255]), resized (bilinear) to `size` = (width, height) when given and different."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"colour image {str(path)!r} not found; the folder's frame list names it")
    try:
        with Image.open(path) as image:
            image = image.convert("RGB")
            if size is not None and image.size != size:
                image = image.resize(size, Image.BILINEAR)
            rgb = np.asarray(image, dtype=np.uint8)
            return rgb if as_bytes else rgb.astype(np.float32) / np.float32(255)
    except (UnidentifiedImageError, OSError) as error:
        raise FileFormatError(f"cannot read colour image {str(path)!r}: {error}") from error


def tum_trajectory_to_poses(table: np.ndarray) -> np.ndarray:
    """TUM trajectory rows (n, 7) `tx ty tz qx qy qz qw` -> camera-to-world (n, 4, 4) float64."""
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    for pose, row in zip(poses, table):
        pose[:3, :3] = quaternion_to_matrix(row[3:7])
        pose[:3, 3] = row[:3]
    return poses


def associate(queries: np.ndarray, stamps: np.ndarray, tolerance: float) -> np.ndarray:
    """Index into `stamps` (m,) of the nearest timestamp to each query (n,), -1 where it is more
    than `tolerance` away."""
    order = np.argsort(stamps)
    ordered = stamps[order]
    right = np.clip(np.searchsorted(ordered, queries), 0, len(ordered) - 1)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(queries - ordered[left]) <= np.abs(ordered[right] - queries), left, right)
    index = order[nearest]
    return np.where(np.abs(stamps[index] - queries) <= tolerance, index, -1)


# ---------------------------------------------------------------------------------------------
# listings: folder -> _Listing


def _subfolders(path: Path) -> list[Path]:
    """The visible subfolders of `path`, sorted by name."""
    return sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".")) if path.is_dir() else []


def _has_seven_scenes_frames(folder: Path) -> bool:
    return next(folder.glob(_SEVEN_SCENES_DEPTH), None) is not None


def _seven_scenes_folder(path: Path) -> Path | None:
    """The folder of `path`'s 7-Scenes frames: `path` itself, else its one subfolder holding
    frame-*.depth.png; None if none does. FileFormatError naming them when several subfolders do."""
    if _has_seven_scenes_frames(path):
        return path
    found = [p for p in _subfolders(path) if _has_seven_scenes_frames(p)]
    if len(found) > 1:
        names = ", ".join(f"{p.name}/" for p in found)
        raise FileFormatError(
            f"{str(path)!r} holds 7-Scenes frames in {len(found)} subfolders ({names}): one sequence is read "
            f"at a time; point at one of them (data.path={found[0]}); a camera-intrinsics.txt in "
            f"{str(path)!r} serves the one you pick when it has none of its own"
        )
    return found[0] if found else None


def _seven_scenes_intrinsics(path: Path, frames: Path) -> Path | None:
    """camera-intrinsics.txt for frames in `frames`, given `path`: in `path`, else in `frames`, else,
    when `path` holds the frames itself, in its parent (logged); None if none of them has one."""
    for candidate in (path / _INTRINSICS, frames / _INTRINSICS):
        if candidate.is_file():
            return candidate
    parent = path.resolve().parent / _INTRINSICS
    if frames == path and parent.is_file():
        log.info("%s has no %s; using the parent folder's %s", path, _INTRINSICS, parent)
        return parent
    return None


def _list_7scenes(path: Path, with_color: bool, K) -> _Listing:
    folder = _seven_scenes_folder(path)
    depths = sorted(folder.glob(_SEVEN_SCENES_DEPTH)) if folder is not None else []
    if not depths:
        raise FileFormatError(
            f"7-Scenes folder {str(path)!r} has no frames: expected frame-XXXXXX.depth.png directly in the "
            f"folder or in one subfolder (frames/, seq-01/, ...)"
        )
    stems = [p.with_name(p.name[: -len(".depth.png")]) for p in depths]
    poses = np.stack(
        [_read_matrix(s.with_name(s.name + ".pose.txt"), (4, 4), "7-Scenes pose") for s in stems]
    )
    colors = None
    if with_color:
        colors = [_first_existing(s, (".color.png", ".color.jpg"), "7-Scenes colour image") for s in stems]
    intrinsics = _seven_scenes_intrinsics(path, folder) if K is None else None
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
    elif intrinsics is None:
        where = "neither it nor its frames' folder" if folder != path else "neither it nor its parent"
        warnings.warn(
            f"{str(path)!r}: {where} has a camera-intrinsics.txt; using 7-Scenes' published K "
            f"(fx = fy = 585, cx = 320, cy = 240); pass K= if the frames come from another camera",
            stacklevel=3,
        )
        K = np.array(SEVEN_SCENES_K)
    else:
        K = _read_matrix(intrinsics, (3, 3), "camera intrinsics")
    return _Listing(depths, colors, poses, K, 1000.0, (0, 65535), COLOR_REGISTERED["7scenes"])


def _list_tum(path: Path, with_color: bool, tolerance: float, K) -> _Listing:
    depth_stamps, depth_names = _read_stamped_list(path / "depth.txt", 1, "TUM depth list")
    truth, _ = _read_stamped_list(path / "groundtruth.txt", 7, "TUM ground truth", numeric=True)
    pose_index = associate(depth_stamps, truth[:, 0], tolerance)
    keep = pose_index >= 0
    colors = None
    if with_color:
        rgb_stamps, rgb_names = _read_stamped_list(path / "rgb.txt", 1, "TUM colour list")
        color_index = associate(depth_stamps, rgb_stamps, tolerance)
        keep &= color_index >= 0
    if not keep.all():
        warnings.warn(
            f"{str(path)!r}: {int((~keep).sum())} of {len(keep)} depth images have no pose"
            f"{' or colour image' if with_color else ''} within {tolerance} s and are left out",
            stacklevel=3,
        )
    if not keep.any():
        raise FileFormatError(
            f"TUM folder {str(path)!r} has no depth image with a ground-truth pose within {tolerance} s; "
            f"check groundtruth.txt covers the sequence or raise tolerance"
        )
    if with_color:
        colors = [path / rgb_names[i] for i in color_index[keep]]
    try:
        poses = tum_trajectory_to_poses(truth[pose_index[keep], 1:8])
    except InputError as error:
        raise InputError(f"{str(path / 'groundtruth.txt')!r}: {error}") from None
    depths = [path / name for name, kept in zip(depth_names, keep) if kept]
    K = tum_intrinsics(path) if K is None else np.asarray(K, dtype=np.float64)
    return _Listing(depths, colors, poses, K, 5000.0, (0,), COLOR_REGISTERED["tum"])


def tum_intrinsics(path: PathLike) -> np.ndarray:
    """3x3 K of a TUM sequence, chosen by the freiburg1/2/3 in its folder's (or a parent's) name;
    the ROS default with a warning when none is named."""
    path = Path(path)
    names = re.findall(r"freiburg[123]", " ".join(p.name for p in (path, *path.resolve().parents)))
    sensor = names[0] if names else None
    if sensor is None:
        warnings.warn(
            f"{str(path)!r}: the folder name does not say freiburg1/2/3, so the ROS default intrinsics "
            f"(525, 525, 319.5, 239.5) are used; pass K= for the right camera",
            stacklevel=4,
        )
    fx, fy, cx, cy = TUM_K[sensor or "default"]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


def _list_redwood(path: Path, with_color: bool, K) -> _Listing:
    depths = sorted(p for p in (path / "depth").glob("*.png")) if (path / "depth").is_dir() else []
    if not depths:
        raise FileFormatError(f"Redwood folder {str(path)!r} has no depth/*.png images")
    logs = sorted(path.glob("*.log"))
    if len(logs) > 1:
        logs = [p for p in logs if "traj" in p.name.lower()] or logs
    if len(logs) != 1:
        raise FileFormatError(
            f"Redwood folder {str(path)!r} needs exactly one trajectory .log file, found "
            f"{[p.name for p in logs] or 'none'}; keep only the camera trajectory there"
        )
    ids, poses = read_trajectory_log(logs[0], frames=len(depths))
    colors = None
    if with_color:
        folder = next((path / f for f in _COLOR_FOLDERS if (path / f).is_dir()), None)
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES) if folder else []
        if len(images) != len(depths):
            raise FileFormatError(
                f"Redwood folder {str(path)!r} has {len(depths)} depth images but {len(images)} colour "
                f"images in {'/'.join(_COLOR_FOLDERS)}/; pass with_color=False to read depth only"
            )
        colors = [images[i] for i in ids]
    K = np.asarray(REDWOOD_K if K is None else K, dtype=np.float64)
    return _Listing([depths[i] for i in ids], colors, poses, K, 1000.0, (0,), COLOR_REGISTERED["redwood"])


def read_trajectory_log(path: PathLike, frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A Redwood / Open3D trajectory .log: (frame ids (n,) int64, camera-to-world (n, 4, 4) float64).

    Each frame is a line `id id n` (the first number is the frame id) then 4 rows of the matrix. Ids
    must be distinct and >= 0 (and < `frames`, the number of depth images, when given); FileFormatError
    naming the line otherwise.
    """
    path = Path(path)
    lines = [(i, line.split()) for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1)]
    lines = [(i, words) for i, words in lines if words]
    if not lines or len(lines) % 5:
        raise FileFormatError(
            f"trajectory {str(path)!r} has {len(lines)} non-empty lines; expected 5 per frame "
            f"(a line 'id id n' then 4 rows of a 4x4 matrix)"
        )
    ids, poses, seen = [], [], set()
    for start in range(0, len(lines), 5):
        number, header = lines[start]
        rows = [words for _, words in lines[start + 1 : start + 5]]
        try:
            ids.append(int(header[0]))
            poses.append(np.array(rows, dtype=np.float64).reshape(4, 4))
        except (ValueError, IndexError):
            raise FileFormatError(
                f"trajectory {str(path)!r} lines {number}-{number + 4} are not 'id id n' + a 4x4 matrix"
            ) from None
        if ids[-1] < 0 or (frames is not None and ids[-1] >= frames) or ids[-1] in seen:
            limit = "" if frames is None else f" and below {frames} (the depth images in depth/)"
            raise FileFormatError(
                f"trajectory {str(path)!r} line {number} names frame {ids[-1]}; ids must be distinct, >= 0{limit}"
            )
        seen.add(ids[-1])
    return np.array(ids, dtype=np.int64), np.stack(poses)



def has_poses(path: PathLike) -> bool:
    """Whether `read_rgbd_folder` finds a layout with camera poses in `path` (7-Scenes, TUM, Redwood)."""
    try:
        detect_rgbd_format(path)
    except FileFormatError:
        return False
    return True


def read_depth_frames(
    path: PathLike,
    K=None,
    sensor: str | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    with_color: bool = True,
    depth_scale: float = 1000.0,
    progress: bool = True,
) -> DepthFrames:
    """Read a capture without poses: `depth/*.png` (16-bit, `depth_scale` units per metre, 0 invalid) and,
    with `with_color`, registered colour images in `image/`, `rgb/` or `color/` (one per depth image).

    Intrinsics: `K` (3x3), else the folder's camera-intrinsics.txt (a 3x3 table), else the named
    `sensor` (`io.trajectories.SENSORS`); ConfigError naming the options when there is none.
    Returns DepthFrames whose `cam_to_world` is the identity for every frame: placeholders for a
    tracker's estimate (`baselines.tracking.track_frames`).
    """
    path = Path(path)
    depths = sorted((path / "depth").glob("*.png")) if (path / "depth").is_dir() else []
    if not depths:
        raise FileFormatError(f"{str(path)!r} has no depth/*.png images; a capture without poses keeps its "
                              f"16-bit depth images there (and colour in image/, rgb/ or color/)")
    if not isinstance(stride, int) or stride < 1:
        raise ConfigError(f"stride must be a positive integer (keep every stride-th frame), got {stride!r}")
    colors = None
    if with_color:
        folder = next((path / f for f in _COLOR_FOLDERS if (path / f).is_dir()), None)
        colors = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES) if folder else []
        if len(colors) != len(depths):
            raise FileFormatError(
                f"{str(path)!r} has {len(depths)} depth images but {len(colors)} colour images in "
                f"{'/'.join(_COLOR_FOLDERS)}/; pass with_color=False to read depth only"
            )
    if K is None and (path / _INTRINSICS).is_file():
        K = _read_matrix(path / _INTRINSICS, (3, 3), "camera intrinsics")
    if K is None:
        height, width = read_depth_png(depths[0], depth_scale).shape
        K = sensor_intrinsics(sensor, width, height)
    poses = np.tile(np.eye(4), (len(depths), 1, 1))
    listing = _Listing(depths, colors, poses, np.asarray(K, dtype=np.float64), depth_scale, (0,), True)
    keep = np.arange(0, len(depths), stride)[:max_frames]
    return _load(listing, keep, with_color, path, progress)


# ---------------------------------------------------------------------------------------------
# loading


def _load(listing: _Listing, keep: np.ndarray, with_color: bool, path: Path, progress: bool = False) -> DepthFrames:
    with_color = with_color and listing.color_paths is not None
    bar = progress_bar(desc=f"RGB-D {path.name}", total=len(keep) * (2 if with_color else 1), unit="image",
                       enabled=progress)
    first = read_depth_png(listing.depth_paths[keep[0]], listing.depth_scale, listing.invalid)
    bar.update()
    height, width = first.shape
    check_intrinsics(torch.from_numpy(listing.K)[None], width, height, f"the intrinsics of {str(path)!r}")  # before decoding the rest
    depth = np.empty((len(keep), height, width), dtype=np.float32)  # filled in place: no stacking copy
    depth[0] = first
    for slot, i in enumerate(keep[1:], start=1):
        image = read_depth_png(listing.depth_paths[i], listing.depth_scale, listing.invalid)
        if image.shape != first.shape:
            raise InputError(
                f"depth images in {str(path)!r} differ in size: {str(listing.depth_paths[i])!r} is "
                f"{image.shape[1]}x{image.shape[0]}, the first is {width}x{height}; a sequence needs one size"
            )
        depth[slot] = image
        bar.update()
    colors = None
    if with_color:
        if not listing.registered:
            warnings.warn(
                f"{str(path)!r}: colour and depth come from different, unregistered cameras (7-Scenes); "
                f"colours are loaded as-is and are only approximate per depth pixel",
                stacklevel=3,
            )
        colors = np.empty((len(keep), height, width, 3), dtype=np.uint8)  # as the images hold them
        for slot, i in enumerate(keep):
            image = read_color_image(listing.color_paths[i], None if listing.registered else (width, height),
                                     as_bytes=True)
            if image.shape[:2] != (height, width):
                raise InputError(
                    f"mismatched depth/colour sizes: {str(listing.color_paths[i])!r} is "
                    f"{image.shape[1]}x{image.shape[0]} but its depth image is {width}x{height}; "
                    f"registered colour must match the depth pixel for pixel"
                )
            colors[slot] = image
            bar.update()
        colors = torch.from_numpy(colors)
    bar.close()
    poses = torch.from_numpy(listing.poses[keep])
    if not torch.isfinite(poses).all():
        bad = [str(listing.depth_paths[i]) for i, p in zip(keep, poses) if not torch.isfinite(p).all()]
        raise InputError(f"{len(bad)} poses are NaN or inf (first for {bad[0]!r}); drop those frames")
    return DepthFrames(torch.from_numpy(depth), torch.from_numpy(listing.K).float(), poses.float(), colors)


def _read_matrix(path: Path, shape: tuple[int, int], what: str) -> np.ndarray:
    if not path.is_file():
        raise FileFormatError(f"{what} file {str(path)!r} not found; every frame needs one")
    try:
        matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise FileFormatError(f"{what} file {str(path)!r} is not a table of numbers: {error}") from error
    if matrix.shape != shape:
        raise FileFormatError(f"{what} file {str(path)!r} holds a {matrix.shape} table, expected {shape}")
    return matrix


def _first_existing(stem: Path, suffixes: tuple[str, ...], what: str) -> Path:
    for suffix in suffixes:
        candidate = stem.with_name(stem.name + suffix)
        if candidate.is_file():
            return candidate
    raise FileFormatError(
        f"{what} for {stem.name!r} not found (looked for {', '.join(suffixes)}); "
        f"pass with_color=False to skip colour"
    )


def _read_stamped_list(path: Path, columns: int, what: str, numeric: bool = False):
    """TUM lists: `timestamp value...` rows, `#` comments. Returns (timestamps (n,), names) or, with
    `numeric`, (table (n, 1 + columns), None)."""
    if not path.is_file():
        raise FileFormatError(
            f"{what} {str(path)!r} not found; a TUM folder has depth.txt, rgb.txt, groundtruth.txt"
        )
    rows = [(i, line.split()) for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1)]
    rows = [(i, words) for i, words in rows if words and not words[0].startswith("#")]
    if not rows:
        raise FileFormatError(f"{what} {str(path)!r} lists nothing")
    for number, words in rows:
        if len(words) != 1 + columns:
            raise FileFormatError(
                f"{what} {str(path)!r} line {number} has {len(words)} fields, expected {1 + columns}: "
                f"{' '.join(words)!r}"
            )
    try:
        if numeric:
            return np.array([words for _, words in rows], dtype=np.float64), None
        return np.array([words[0] for _, words in rows], dtype=np.float64), [words[1] for _, words in rows]
    except ValueError as error:
        raise FileFormatError(
            f"{what} {str(path)!r} has a timestamp or value that is not a number: {error}"
        ) from None
