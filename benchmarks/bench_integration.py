"""Normal integration with depth discontinuities: least squares against bilateral normal integration,
per scene, on exact perspective views of analytic solids (`discontinuity_scene`: a step, a sphere in
front of a plane, stacked boxes, a box on the ground), from the true normals and from measured-like
ones (Gaussian noise, then 8-bit storage: `degrade_normals`).

    python benchmarks/bench_integration.py [--size 128] [--sigma 0.01] [--threads 2]

Errors are mean |dz| in millimetres (depths 2-5 m) after a least-squares scale per piece
(`continuous_pieces`: parts joined to the rest by no normal have a scale normals cannot tell), over
every scored pixel ("all") and over the pixels within 2 of a discontinuity ("at disc.",
`discontinuities`). Times: CPU seconds of each integrator once (process time, all threads), and the
ratio bilateral / least squares.
"""

from __future__ import annotations

import argparse
import time

import torch
from scipy import ndimage

from neuralsurf.photometric import (
    continuous_pieces,
    depth_error,
    discontinuities,
    integrate_bilateral,
    integrate_least_squares,
)
from neuralsurf.scenes.photometric_rig import DISCONTINUITY_SCENES, degrade_normals, discontinuity_scene


def scores(result, depth: torch.Tensor, mask: torch.Tensor, pieces: torch.Tensor, band: torch.Tensor):
    """(mean |dz| over the scored pixels, at the discontinuities), each piece scale-aligned on its own."""
    error = depth_error(result.depth, depth, mask, align="scale", pieces=pieces)
    return error.mean_abs, float((error.aligned.double() - depth).abs()[band].mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128, help="image width and height in pixels")
    parser.add_argument("--sigma", type=float, default=0.01, help="normal noise before the 8-bit storage")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{args.size}x{args.size}, fov 40 deg; mean |dz| in mm, each piece scale-aligned")
    print(f"{'scene':16s} {'normals':14s} {'LS all':>8s} {'BiNI all':>8s} {'LS disc.':>9s} {'BiNI disc.':>10s} "
          f"{'BiNI/LS disc.':>13s} {'iters':>5s} {'LS cpu s':>8s} {'BiNI cpu s':>10s} {'ratio':>6s}")
    for name in DISCONTINUITY_SCENES:
        depth, normals, mask, K = discontinuity_scene(name, args.size)
        pieces = continuous_pieces(depth, normals, mask, K=K)
        band = torch.from_numpy(ndimage.binary_dilation(discontinuities(depth, normals, mask, K=K).numpy(),
                                                        iterations=2)) & (pieces >= 0)
        for label, given in (("exact", normals), (f"{args.sigma:g} + 8-bit", degrade_normals(normals, mask, args.sigma))):
            start = time.process_time()
            ls = integrate_least_squares(given, mask, K=K)
            ls_seconds = time.process_time() - start
            start = time.process_time()
            bini = integrate_bilateral(given, mask, K=K)
            bini_seconds = time.process_time() - start
            (ls_all, ls_band), (bini_all, bini_band) = (scores(r, depth, mask, pieces, band) for r in (ls, bini))
            print(f"{name:16s} {label:14s} {1e3 * ls_all:8.2f} {1e3 * bini_all:8.2f} {1e3 * ls_band:9.2f} "
                  f"{1e3 * bini_band:10.2f} {bini_band / ls_band:13.3f} {bini.iterations:5d} {ls_seconds:8.2f} "
                  f"{bini_seconds:10.2f} {bini_seconds / ls_seconds:6.1f}", flush=True)


if __name__ == "__main__":
    main()
