"""Photometric captures on disk: the DiLiGenT layout (axes, intensities, masks, ground truth), the
round trip of a written capture, error messages, and the shared real sets when present."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralsurf.errors import FileFormatError, InputError
from neuralsurf.io import read_image_list, read_photometric, write_photometric
from neuralsurf.io.photometric import _write_png, camera_to_diligent, diligent_to_camera
from neuralsurf.photometric import angular_error, least_squares_stereo, robust_stereo
from neuralsurf.scenes.photometric_rig import cap_lights
from neuralsurf.structures import PhotometricCapture


def small_capture(color: bool = True, intensities: bool = True) -> PhotometricCapture:
    generator = torch.Generator().manual_seed(0)
    n, h, w = 5, 6, 7
    shape = (n, h, w, 3) if color else (n, h, w)
    mask = torch.zeros(h, w, dtype=torch.bool)
    mask[1:5, 2:6] = True
    normals = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=generator), dim=-1)
    normals[..., 2] = -normals[..., 2].abs()
    return PhotometricCapture(
        images=torch.rand(shape, generator=generator) * 0.9,
        light_directions=cap_lights(n, 40.0).float(),
        light_intensities=(0.5 + torch.rand(n, 3, generator=generator)) if intensities else None,
        mask=mask,
        normals=normals * mask[..., None],
        K=torch.tensor([[20.0, 0, 3.0], [0, 20.0, 2.5], [0, 0, 1]]),
        depth=torch.rand(h, w, generator=generator) * mask,
        cam_to_world=torch.eye(4),
    )


@pytest.mark.parametrize("color", [True, False])
def test_written_capture_reads_back(tmp_path, color):
    capture = small_capture(color)
    write_photometric(tmp_path / "capture", capture)
    back = read_photometric(tmp_path / "capture", color=color)
    assert back.images.shape == capture.images.shape
    # images divided by the intensities come back to 16-bit quantisation of the (scaled) raw images
    peak = float(
        (
            capture.images
            * (
                capture.light_intensities[:, None, None, :]
                if color
                else capture.light_intensities.mean(1)[:, None, None]
            )
        ).max()
    )
    tolerance = max(peak, 1.0) / 65535 / float(capture.light_intensities.min()) * 0.6
    torch.testing.assert_close(back.images, capture.images, atol=tolerance, rtol=0)
    torch.testing.assert_close(back.light_directions, capture.light_directions, atol=1e-7, rtol=0)
    assert torch.equal(back.mask, capture.mask)
    torch.testing.assert_close(back.normals, capture.normals, atol=1e-6, rtol=0)
    for name in ("K", "depth", "cam_to_world"):
        torch.testing.assert_close(getattr(back, name), getattr(capture, name), atol=1e-6, rtol=0)


def test_eight_bit_round_trip_without_intensities(tmp_path):
    capture = small_capture(intensities=False)
    write_photometric(tmp_path / "c8", capture, bits=8)
    back = read_photometric(tmp_path / "c8")
    assert not (tmp_path / "c8" / "light_intensities.txt").exists() and back.light_intensities is None
    torch.testing.assert_close(back.images, capture.images, atol=0.5 / 255 + 1e-6, rtol=0)


def write_diligent(folder: Path, images: np.ndarray, lights: np.ndarray, names=None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"{i + 1:03d}.png" for i in range(len(images))]
    for name, image in zip(names, images):
        _write_png(folder / name, image, 16)
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)


def test_diligent_axes_become_the_opencv_camera_frame(tmp_path):
    # DiLiGenT: x right, y up, z towards the viewer. A light straight at the viewer is (0, 0, 1) there
    # and (0, 0, -1) in the camera frame; a light from above is (0, 1, z) there, (0, -1, -z) here.
    lights = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8], [0.6, 0.0, 0.8]])
    write_diligent(tmp_path, np.full((3, 4, 4), 0.5), lights)
    # ground truth: a normal pointing up and towards the viewer, encoded (n + 1) / 2 in 16 bits
    up = np.array([0.0, 0.6, 0.8])
    _write_png(tmp_path / "Normal_gt.png", np.broadcast_to((up + 1) / 2, (4, 4, 3)).copy(), 16)
    capture = read_photometric(tmp_path)
    torch.testing.assert_close(
        capture.light_directions,
        torch.tensor([[0.0, 0, -1], [0, -0.6, -0.8], [0.6, 0, -0.8]]),
        atol=1e-6,
        rtol=0,
    )
    torch.testing.assert_close(capture.normals[2, 1], torch.tensor([0.0, -0.6, -0.8]), atol=1e-4, rtol=0)
    assert capture.normals[..., 1].max() < 0  # up in the picture is -y in the camera frame
    # the conversion is its own inverse
    v = torch.randn(5, 3)
    torch.testing.assert_close(camera_to_diligent(diligent_to_camera(v)), v)


def test_intensities_divide_the_images_and_a_mask_is_derived(tmp_path):
    images = np.zeros((3, 5, 6, 3))
    images[:, 1:4, 2:5] = [[[0.2, 0.4, 0.6]]]
    write_diligent(tmp_path, images, np.array([[0.0, 0, 1], [0.3, 0, 0.95], [0, 0.3, 0.95]]))
    np.savetxt(tmp_path / "light_intensities.txt", [[1.0, 2.0, 4.0], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5]])
    capture = read_photometric(tmp_path)
    expected = torch.tensor([[0.2, 0.2, 0.15], [0.1, 0.2, 0.3], [0.4, 0.8, 1.2]])
    torch.testing.assert_close(capture.images[:, 2, 3], expected, atol=1e-4, rtol=0)
    inside = torch.zeros(5, 6, dtype=torch.bool)
    inside[1:4, 2:5] = True
    assert torch.equal(capture.mask, inside)  # no mask.png: the lit pixels over a black background
    gray = read_photometric(tmp_path, color=False)
    assert gray.images.shape == (3, 5, 6)


def test_missing_light_file_count_mismatch_and_size_mismatch(tmp_path):
    write_diligent(tmp_path / "a", np.full((3, 4, 4), 0.5), np.tile([0.0, 0, 1], (3, 1)))
    (tmp_path / "a" / "light_directions.txt").unlink()
    with pytest.raises(FileFormatError, match="light_directions.txt"):
        read_photometric(tmp_path / "a")
    write_diligent(tmp_path / "b", np.full((3, 4, 4), 0.5), np.tile([0.0, 0, 1], (2, 1)))
    with pytest.raises(InputError, match="lists 3 images but light_directions.txt has 2"):
        read_photometric(tmp_path / "b")
    write_diligent(tmp_path / "c", np.full((2, 4, 4), 0.5), np.tile([0.0, 0, 1], (3, 1)))
    _write_png(tmp_path / "c" / "003.png", np.full((5, 4), 0.5), 16)
    (tmp_path / "c" / "filenames.txt").write_text("001.png\n002.png\n003.png\n")
    with pytest.raises(InputError, match="different sizes: 003.png is 4x5"):
        read_photometric(tmp_path / "c")
    (tmp_path / "c" / "filenames.txt").write_text("001.png\n002.png\nmissing.png\n")
    with pytest.raises(FileFormatError, match="missing.png"):
        read_photometric(tmp_path / "c")
    with pytest.raises(FileFormatError, match="does not exist"):
        read_photometric(tmp_path / "nowhere")
    with pytest.raises(InputError, match="3 images but 2 light directions"):
        PhotometricCapture(torch.zeros(3, 4, 4), torch.tensor([[0.0, 0, -1], [0, 0.1, -1]]))


# ---------------------------------------------------------------------------------------------- shared data


def test_bunny_specular_ground_truth_axes_and_robust_below_least_squares(shared_data):
    folder = shared_data / "bunny_specular_ps"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found")
    capture = read_photometric(folder)
    assert capture.images.shape == (50, 256, 256, 3) and capture.normals is not None
    assert 15000 < int(capture.mask.sum()) < 30000  # derived from the black background
    ls_normals = least_squares_stereo(capture.images, capture.light_directions, capture.mask).normals
    ls = angular_error(ls_normals, capture.normals, capture.mask)
    # the ground truth agrees with least squares in the camera frame: flipping y back costs ~50 deg
    assert ls.mean_deg < 20
    flipped = capture.normals * torch.tensor([1.0, -1.0, 1.0])
    assert angular_error(ls_normals, flipped, capture.mask).mean_deg > 40
    robust = angular_error(
        robust_stereo(capture.images, capture.light_directions, capture.mask).normals,
        capture.normals,
        capture.mask,
    )
    assert robust.mean_deg < ls.mean_deg


def test_uw_image_list(shared_data):
    list_file = shared_data / "uw_photometric" / "psmImages" / "chrome.txt"
    if not list_file.is_file():
        pytest.skip(f"{list_file} not found")
    images, mask = read_image_list(list_file)
    assert images.shape == (12, 340, 512, 3) and mask.shape == (340, 512) and mask.any()
