"""Photometric stereo speed, ours against a plain numpy least-squares reference in one run, and the
accuracy numbers (rig, bunny_specular_ps, normal integration, depth step).

    python benchmarks/bench_photometric.py [--lights 96] [--width 612] [--height 512] [--repeats 3]
                                           [--threads 2] [--accuracy] [--data <folder>]

Speed input: a DiLiGenT-sized capture (96 lights, 612x512, RGB float32) of analytic sphere normals
with a random albedo under `cap_lights`. Both methods solve every pixel (no mask), from the same
float32 images: ours is `least_squares_stereo` (normals, per-channel albedo and confidence); the
reference averages the channels and calls `numpy.linalg.lstsq` on all pixels at once, then
normalises and computes the per-channel albedo the same way. Each time is the best of `--repeats`.
The robust method's time is printed too, and on a CUDA GPU both methods' times there.

`--accuracy` renders the rig scenes and prints the mean/median angular errors and depth errors.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from neuralsurf.photometric import (
    angular_error,
    continuous_pieces,
    depth_error,
    integrate_bilateral,
    integrate_least_squares,
    least_squares_stereo,
    render_lambertian,
    robust_stereo,
    trimmed_stereo,
)
from neuralsurf.scenes.photometric_rig import SpecularLobe, cap_lights, render_photometric, ring_lights
from neuralsurf.scenes.recipes import data_root


def best_of(repeats: int, run):
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - start)
    return best, result


def speed_input(n: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Images Float32[n, h, w, 3], lights [n, 3] and true normals [h, w, 3] of a sphere on a tilted plane."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    radius = 0.45 * min(width, height)
    x, y = (u - width / 2) / radius, (v - height / 2) / radius
    inside = x**2 + y**2 < 1
    sphere = torch.stack([x, y, -torch.sqrt((1 - x**2 - y**2).clamp_min(0))], -1)
    plane = torch.nn.functional.normalize(torch.tensor([0.1, -0.2, -1.0], dtype=torch.float64), dim=0)
    normals = torch.where(inside[..., None], sphere, plane.expand_as(sphere))
    albedo = 0.3 + 0.6 * torch.rand(
        height, width, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    lights = cap_lights(n, 40.0)
    return render_lambertian(normals, albedo, lights).float(), lights.float(), normals


def numpy_reference(images: np.ndarray, lights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plain numpy Lambertian least squares: normals [h, w, 3] and per-channel albedo [h, w, 3]."""
    n, h, w, _ = images.shape
    gray = images.mean(-1).reshape(n, -1)
    g = np.linalg.lstsq(lights, gray, rcond=None)[0]  # (3, p)
    rho = np.linalg.norm(g, axis=0)
    normals = g / np.maximum(rho, 1e-12)
    shading = lights @ normals  # (n, p)
    albedo = (
        np.einsum("np,npc->pc", shading, images.reshape(n, -1, 3))
        / np.maximum((shading**2).sum(0), 1e-12)[:, None]
    )
    return normals.T.reshape(h, w, 3), albedo.reshape(h, w, 3)


def speed(args) -> None:
    images, lights, truth = speed_input(args.lights, args.width, args.height)
    images_np, lights_np = images.numpy(), lights.numpy()
    ours_s, ours = best_of(args.repeats, lambda: least_squares_stereo(images, lights))
    ref_s, (ref_normals, _) = best_of(args.repeats, lambda: numpy_reference(images_np, lights_np))
    robust_s, robust = best_of(max(1, args.repeats - 2), lambda: robust_stereo(images, lights))
    agreement = angular_error(
        ours.normals,
        torch.from_numpy(ref_normals).float(),
        torch.ones(args.height, args.width, dtype=torch.bool),
    )
    print(
        f"photometric stereo, {args.lights} lights, {args.width}x{args.height} RGB, all pixels, "
        f"{torch.get_num_threads()} threads, {platform.processor() or platform.machine()}, torch {torch.__version__}"
    )
    print(
        f"  ours least squares : {ours_s:7.3f} s   (error vs truth {angular_error(ours.normals, truth.float()).mean_deg:.2e} deg)"
    )
    print(f"  numpy lstsq        : {ref_s:7.3f} s")
    print(
        f"  ratio ours / numpy : {ours_s / ref_s:7.2f}   (normals agree to {agreement.mean_deg:.1e} deg mean)"
    )
    print(
        f"  ours robust (IRLS) : {robust_s:7.3f} s   (error vs truth {angular_error(robust.normals, truth.float()).mean_deg:.2e} deg)"
    )
    if torch.cuda.is_available():  # the same solves on the GPU, after a warm-up, synchronised
        gpu_images, gpu_lights = images.cuda(), lights.cuda()

        def on_gpu(method):
            def run():
                result = method(gpu_images, gpu_lights)
                torch.cuda.synchronize()
                return result
            return run

        on_gpu(least_squares_stereo)()
        gpu_s, _ = best_of(args.repeats, on_gpu(least_squares_stereo))
        gpu_robust_s, gpu_robust = best_of(max(1, args.repeats - 2), on_gpu(robust_stereo))
        print(f"  on {torch.cuda.get_device_name()}: least squares {gpu_s:.4f} s ({ours_s / gpu_s:.0f}x the CPU's), "
              f"robust {gpu_robust_s:.4f} s ({robust_s / gpu_robust_s:.0f}x; error vs truth "
              f"{angular_error(gpu_robust.normals.cpu(), truth.float()).mean_deg:.2e} deg)")


def piece_summary(pieces: torch.Tensor, mask: torch.Tensor) -> str:
    """The sizes of the continuous pieces and the share of the mask they cover, for a printed line."""
    sizes = torch.bincount(pieces[pieces >= 0]).tolist()
    return f"pieces of {sizes} pixels, {100 * sum(sizes) / int(mask.sum()):.1f} % of the mask"


def bunny_view(size: int):
    from neuralsurf.scenes import bunny, look_at

    mesh = bunny()
    lo, hi = mesh.bounds.double()
    center, extent = (lo + hi) / 2, float((hi - lo).max())
    pose = look_at(center + torch.tensor([0.0, 0.0, 2.5 * extent], dtype=torch.float64), center, up=(0, 1, 0))
    return mesh, pose, extent


def report_stereo(name: str, images, lights, mask, truth) -> None:
    errors = {}
    for method in (least_squares_stereo, trimmed_stereo, robust_stereo):
        e = angular_error(method(images, lights, mask).normals, truth, mask)
        errors[method.__name__] = e
        print(
            f"  {name:36s} {method.__name__:22s} mean {e.mean_deg:9.3g} deg  median {e.median_deg:9.3g} deg"
        )
    ratio = errors["robust_stereo"].mean_deg / errors["least_squares_stereo"].mean_deg
    print(f"  {name:36s} robust / least squares mean: {ratio:.3f}")


def accuracy(args) -> None:
    from neuralsurf.scenes import look_at

    size = args.rig_size
    mesh, pose, extent = bunny_view(size)
    lights = cap_lights(96, 45.0)
    print(f"rig: bunny, {size}x{size}, 96 DiLiGenT-like lights within 45 deg, fov 30")
    lambertian = render_photometric(
        mesh, lights, cam_to_world=pose, width=size, height=size, fov_deg=30, shadows=False
    )[0]
    report_stereo(
        "rig_lambertian (attached shadows)",
        lambertian.images,
        lambertian.light_directions,
        lambertian.mask,
        lambertian.normals,
    )
    lit = lambertian.mask & (lambertian.images > 0).all(0)
    e = angular_error(
        least_squares_stereo(lambertian.images, lambertian.light_directions, lambertian.mask).normals,
        lambertian.normals,
        lit,
    )
    print(
        f"  {'rig_lambertian, pixels lit by all':36s} least_squares_stereo   mean {e.mean_deg:9.3g} deg  "
        f"({int(lit.sum())} of {int(lambertian.mask.sum())} pixels)"
    )
    linear = render_photometric(
        mesh,
        lights,
        cam_to_world=pose,
        width=size,
        height=size,
        fov_deg=30,
        shadows=False,
        attached_shadows=False,
    )[0]
    e = angular_error(
        least_squares_stereo(linear.images, linear.light_directions, linear.mask).normals,
        linear.normals,
        linear.mask,
    )
    print(
        f"  {'rig_lambertian, no attached shadows':36s} least_squares_stereo   mean {e.mean_deg:9.3g} deg  "
        f"median {e.median_deg:7.3f} deg (unclamped n . l: no shadow of any kind)"
    )
    specular = render_photometric(
        mesh,
        lights,
        cam_to_world=pose,
        width=size,
        height=size,
        fov_deg=30,
        specular=SpecularLobe("blinn_phong", strength=0.6, shininess=40.0),
        shadows=True,
    )[0]
    report_stereo(
        "rig_specular (Blinn-Phong, shadows)",
        specular.images,
        specular.light_directions,
        specular.mask,
        specular.normals,
    )
    cook = render_photometric(
        mesh,
        lights,
        cam_to_world=pose,
        width=size,
        height=size,
        fov_deg=30,
        specular=SpecularLobe("cook_torrance", strength=1.0, roughness=0.3),
        shadows=True,
        noise_sigma=0.005,
        bits=16,
        seed=0,
    )[0]
    report_stereo(
        "rig_specular (Cook-Torrance, noise)", cook.images, cook.light_directions, cook.mask, cook.normals
    )

    folder = Path(args.data) / "bunny_specular_ps"
    if folder.is_dir():
        from neuralsurf.io import read_photometric

        capture = read_photometric(folder)
        report_stereo(
            "bunny_specular_ps", capture.images, capture.light_directions, capture.mask, capture.normals
        )
    else:
        print(f"  bunny_specular_ps: {folder} not found, skipped")

    print("normal integration of the rig's ground-truth normals (perspective, depth up to scale; 'per piece':")
    print("each continuous_pieces piece scaled on its own, as a part joined to the rest only across an")
    print("occluding contour, e.g. an ear, has a depth offset that normals cannot tell):")
    pieces = continuous_pieces(lambertian.depth, lambertian.normals, lambertian.mask, K=lambertian.K)
    print(f"  {piece_summary(pieces, lambertian.mask)}")
    for integrate in (integrate_least_squares, integrate_bilateral):
        start = time.perf_counter()
        result = integrate(lambertian.normals, lambertian.mask, K=lambertian.K)
        seconds = time.perf_counter() - start
        error = depth_error(result.depth, lambertian.depth, lambertian.mask, align="scale")
        by_piece = depth_error(result.depth, lambertian.depth, lambertian.mask, align="scale", pieces=pieces)
        print(
            f"  bunny {size}x{size} {integrate.__name__:24s} mean |dz| {100 * error.mean_abs / extent:.3f} % of the "
            f"bunny's size, per piece {100 * by_piece.mean_abs / extent:.3f} % ({seconds:.1f} s)"
        )
    print("  the same from six directions around the bunny (mean |dz| in % of the bunny's size):")
    lo, hi = mesh.bounds.double()
    center = (lo + hi) / 2
    for direction in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0.6, 0.3, 0.75]):
        unit = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float64), dim=0)
        view = render_photometric(
            mesh,
            ring_lights(3, 30.0),
            cam_to_world=look_at(center + 2.5 * extent * unit, center),
            width=size,
            height=size,
            fov_deg=30,
            shadows=False,
        )[0]
        pieces = continuous_pieces(view.depth, view.normals, view.mask, K=view.K)
        line = f"    camera along {[round(float(x), 2) for x in unit]!s:22s}"
        for integrate in (integrate_least_squares, integrate_bilateral):
            result = integrate(view.normals, view.mask, K=view.K)
            error = depth_error(result.depth, view.depth, view.mask, align="scale")
            by_piece = depth_error(result.depth, view.depth, view.mask, align="scale", pieces=pieces)
            line += (f" {integrate.__name__[10:]:13s} {100 * error.mean_abs / extent:6.3f}, "
                     f"per piece {100 * by_piece.mean_abs / extent:5.3f}")
        print(f"{line}; {piece_summary(pieces, view.mask)}")
    from neuralsurf.scenes import Sphere

    sphere = Sphere((0.0, 0.0, 2.0), 0.4)
    view = render_photometric(
        sphere.mesh(6),
        ring_lights(3, 30.0),
        cam_to_world=torch.eye(4),
        width=size,
        height=size,
        fov_deg=30,
        shadows=False,
    )[0]
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(view.normals, view.mask, K=view.K)
        error = depth_error(result.depth, view.depth, view.mask, align="scale")
        print(
            f"  sphere {size}x{size} {integrate.__name__:23s} mean |dz| {error.mean_abs:.5f} = "
            f"{100 * error.mean_abs / 0.8:.3f} % of the sphere's size"
        )

    print("depth step: a dome on a ground plane seen obliquely (its far rim occludes the ground):")
    import trimesh
    from scipy import ndimage

    from neuralsurf.structures import Mesh

    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    dome = trimesh.Trimesh(ball.vertices, ball.faces[ball.vertices[ball.faces].mean(1)[:, 1] > 0])
    ground = trimesh.Trimesh([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3]], [[0, 2, 1], [0, 3, 2]])
    scene = trimesh.util.concatenate([dome, ground])
    step = render_photometric(
        Mesh(scene.vertices, scene.faces),
        ring_lights(3, 30.0),
        cam_to_world=look_at((0.0, 0.7, -1.3), (0.0, 0.1, 0.0), up=(0, 1, 0)),
        width=128,
        height=96,
        fov_deg=40,
        shadows=False,
    )[0]
    depth, mask = step.depth, step.mask
    jump = torch.zeros_like(mask)
    for axis in (0, 1):
        a = depth.narrow(axis, 1, depth.shape[axis] - 1)
        b = depth.narrow(axis, 0, depth.shape[axis] - 1)
        across = (a - b).abs() > 0.03 * a
        jump.narrow(axis, 1, depth.shape[axis] - 1).logical_or_(across)
        jump.narrow(axis, 0, depth.shape[axis] - 1).logical_or_(across)
    band = torch.from_numpy(ndimage.binary_dilation(jump.numpy(), iterations=2)) & mask
    for integrate in (integrate_least_squares, integrate_bilateral):
        result = integrate(step.normals, mask, K=step.K)
        aligned = depth_error(result.depth, depth, mask, align="scale")
        at_step = float((aligned.aligned - depth).abs()[band].mean())
        print(
            f"  {integrate.__name__:24s} mean |dz| at the step {at_step:.4f} m ({int(band.sum())} pixels), "
            f"everywhere {aligned.mean_abs:.4f} m, iterations {result.iterations}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--lights", type=int, default=96)
    parser.add_argument("--width", type=int, default=612)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--accuracy", action="store_true", help="also print the rig's accuracy numbers")
    parser.add_argument("--rig-size", type=int, default=256)
    parser.add_argument(
        "--data",
        default=str(data_root()),
        help="the folder of real captures (default: $NEURALSURF_DATA, else the fetch cache)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    speed(args)
    if args.accuracy:
        accuracy(args)


if __name__ == "__main__":
    main()
