"""Photometric stereo on the UW CSE 576 set: calibrate the 12 lights from the chrome ball, then
recover normals, albedo and depth of the six objects.

    python benchmarks/uw_photometric.py [--data <folder>] [--out docs/images/photometric]
                                        [--method robust] [--scale 0.5]

Lights: `calibrate_chrome_ball` on chrome/ (highlight centroid, mirror reflection of the view
direction, orthographic viewer). Objects: `robust_stereo` (or `--method least_squares`) inside each
object's mask, then `integrate_least_squares` (orthographic, depth in pixels up to an offset).
There is no ground truth: the script prints, per object, the mean absolute difference between the
photographs and the images re-rendered from the recovered normals and albedo (I = albedo max(0, n . l),
no cast shadows), over the mask, all 12 images and 3 channels, in 8-bit grey levels and relative to
the mean intensity; and it saves one picture per object (normal map | albedo | integrated depth),
cropped to the mask and scaled by `--scale`, under `--out`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from neuralsurf.io import read_image_list
from neuralsurf.io.photometric import camera_to_diligent
from neuralsurf.photometric import (
    calibrate_chrome_ball,
    integrate_least_squares,
    least_squares_stereo,
    render_lambertian,
    robust_stereo,
)
from neuralsurf.scenes.recipes import data_root

OBJECTS = ("buddha", "cat", "gray", "horse", "owl", "rock")


def normal_picture(normals: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """RGB of normals in DiLiGenT colours ((n + 1) / 2 with y up, z to the viewer), white background."""
    colors = (camera_to_diligent(normals) + 1) / 2
    return np.where(mask[..., None].numpy(), colors.numpy(), 1.0)


def albedo_picture(albedo: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    values = albedo[mask]
    top = float(torch.quantile(values.flatten().float(), 0.99)) if len(values) else 1.0
    picture = (albedo / max(top, 1e-6)).clamp(0, 1).numpy()
    return np.where(mask[..., None].numpy(), picture, 1.0)


def depth_picture(depth: torch.Tensor, mask: torch.Tensor) -> np.ndarray:
    """Grey levels of the integrated depth: near is bright (2nd to 98th percentile over the mask)."""
    values = depth[mask]
    lo, hi = (float(torch.quantile(values.double(), q)) for q in (0.02, 0.98))
    grey = ((hi - depth.double()) / max(hi - lo, 1e-9)).clamp(0, 1).numpy()
    grey = np.where(mask.numpy(), 0.1 + 0.9 * grey, 1.0)
    return np.repeat(grey[..., None], 3, axis=-1)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--data",
        default=str(data_root()),
        help="the folder of real captures (default: $NEURALSURF_DATA, else the fetch cache)",
    )
    parser.add_argument(
        "--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "images" / "photometric")
    )
    parser.add_argument("--method", choices=("robust", "least_squares"), default="robust")
    parser.add_argument("--scale", type=float, default=0.5, help="size of the saved pictures")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    root = Path(args.data) / "uw_photometric" / "psmImages"
    if not root.is_dir():
        raise SystemExit(f"UW photometric set not found at {root}; pass --data or set NEURALSURF_DATA")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    chrome, chrome_mask = read_image_list(root / "chrome.txt")
    calibration = calibrate_chrome_ball(chrome, chrome_mask)
    lights = calibration.directions
    print(
        f"chrome ball: centre (u, v) = ({float(calibration.center[0]):.1f}, {float(calibration.center[1]):.1f}), "
        f"radius {calibration.radius:.1f} px"
    )
    print("calibrated lights (towards the light; camera frame x right, y down, z forward | DiLiGenT axes):")
    for i, (light, spot) in enumerate(zip(lights, calibration.highlights)):
        d = camera_to_diligent(light)
        print(
            f"  {i:2d}: highlight ({float(spot[0]):6.1f}, {float(spot[1]):6.1f})  "
            f"camera ({float(light[0]):+.4f}, {float(light[1]):+.4f}, {float(light[2]):+.4f})  "
            f"diligent ({float(d[0]):+.4f}, {float(d[1]):+.4f}, {float(d[2]):+.4f})"
        )

    print(
        f"\n{'object':8s} {'pixels':>7s} {'LS |I - I_hat|':>15s} {'robust |I - I_hat|':>19s} "
        f"{'relative (robust)':>18s} {'seconds':>8s}"
    )
    total_bytes = 0
    for name in OBJECTS:
        images, mask = read_image_list(root / f"{name}.txt")
        start = time.perf_counter()
        results = {
            "least_squares": least_squares_stereo(images, lights, mask),
            "robust": robust_stereo(images, lights, mask),
        }
        errors = {}
        for key, result in results.items():
            rerendered = render_lambertian(result.normals, result.albedo, lights)
            difference = (rerendered - images).abs()[:, mask]  # (12, p, 3)
            errors[key] = (float(difference.mean()), float(difference.mean() / images[:, mask].mean()))
        result = results[args.method]
        depth = integrate_least_squares(result.normals, result.mask).depth
        seconds = time.perf_counter() - start
        print(
            f"{name:8s} {int(mask.sum()):7d} {255 * errors['least_squares'][0]:12.2f} /255 "
            f"{255 * errors['robust'][0]:15.2f} /255 {100 * errors['robust'][1]:16.1f} % {seconds:8.1f}"
        )
        rows, cols = np.nonzero(mask.numpy())
        crop = (slice(max(rows.min() - 4, 0), rows.max() + 5), slice(max(cols.min() - 4, 0), cols.max() + 5))
        panel = np.concatenate(
            [
                picture[crop]
                for picture in (
                    normal_picture(result.normals, result.mask),
                    albedo_picture(result.albedo, result.mask),
                    depth_picture(depth, result.mask),
                )
            ],
            axis=1,
        )
        image = Image.fromarray(np.round(panel * 255).astype(np.uint8))
        image = image.resize(
            (max(1, round(image.width * args.scale)), max(1, round(image.height * args.scale))), Image.LANCZOS
        )
        path = out / f"uw_{name}.png"
        image.save(path, optimize=True)
        total_bytes += path.stat().st_size
    print(
        f"\nsaved {len(OBJECTS)} pictures (normal map | albedo | depth) under {out}: {total_bytes / 1024:.0f} KiB"
    )


if __name__ == "__main__":
    main()
