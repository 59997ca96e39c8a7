"""Dense vs coarse-to-fine marching cubes, in one run: seconds, field evaluations, peak memory.

    python benchmarks/bench_extract.py                    # 256 and 512, analytic SDF and MLP field
    python benchmarks/bench_extract.py --skip-dense-512   # estimate the MLP's dense 512 from its 256

Fields: (a) the analytic sphere SDF (cheap: the bookkeeping shows), (b) a sphere SDF plus 0.01 x a
random MLP (width 128, 4 hidden Softplus layers; ~5 us per point on a CPU core, like a trained
DeepSDF). Every configuration runs in a fresh subprocess so that its peak RSS (getrusage) is its
own; "extract MB" is the peak minus the RSS before extraction. Both modes must give the same mesh:
the "same" column compares the coarse-to-fine mesh with the dense one (a digest of vertices and
faces). Runs on CPU, and on CUDA too when available.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
import subprocess
import sys
import time

import torch

BOUNDS = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]


class MLPField(torch.nn.Module):
    """sphere SDF + 0.01 * MLP(x): roughly an SDF, at the cost of a small neural field."""

    def __init__(self, width: int = 128, depth: int = 4, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        layers: list[torch.nn.Module] = []
        features = 3
        for _ in range(depth):
            layers += [torch.nn.Linear(features, width), torch.nn.Softplus(beta=100)]
            features = width
        layers.append(torch.nn.Linear(width, 1))
        self.mlp = torch.nn.Sequential(*layers)
        self.register_buffer("bounds", torch.tensor(BOUNDS, dtype=torch.float64))
        self.evaluations = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        self.evaluations += x.shape[0]
        return x.norm(dim=-1) - 0.35 + 0.01 * self.mlp(x).squeeze(-1)


class AnalyticField(torch.nn.Module):
    """The exact sphere SDF, as a module so that it carries a device and counts evaluations."""

    def __init__(self):
        super().__init__()
        self.register_buffer("bounds", torch.tensor(BOUNDS, dtype=torch.float64))
        self.evaluations = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        self.evaluations += x.shape[0]
        return x.norm(dim=-1) - 0.35


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def run_one(config: dict) -> dict:
    """One extraction in this process; returns its measurements."""
    from neuralsurf.extract import extract_mesh

    field = (MLPField() if config["field"] == "mlp" else AnalyticField()).to(config["device"])
    before = rss_mb()
    if config["device"] == "cuda":
        torch.cuda.synchronize()
    started = time.perf_counter()
    mesh = extract_mesh(field, resolution=config["resolution"], coarse_to_fine=config["mode"] == "c2f")
    if config["device"] == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - started
    digest = hashlib.sha1(mesh.vertices.numpy().tobytes() + mesh.faces.numpy().tobytes()).hexdigest()[:12]
    return {"seconds": seconds, "evaluations": field.evaluations, "faces": len(mesh.faces),
            "peak_mb": rss_mb(), "extract_mb": rss_mb() - before, "digest": digest,
            "watertight": mesh.is_watertight}


def run_subprocess(config: dict) -> dict:
    command = [sys.executable, __file__, "--one", json.dumps(config)]
    out = subprocess.run(command, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{config} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def estimate_dense(half: dict, resolution: int) -> dict:
    """Dense cost at `resolution` from the measured dense run at resolution / 2, scaled by grid points."""
    scale = (resolution + 1) ** 3 / (resolution // 2 + 1) ** 3
    return {"seconds": half["seconds"] * scale, "evaluations": (resolution + 1) ** 3, "estimated": True}


def format_row(device: str, field: str, resolution: int, mode: str, row: dict, dense: dict) -> str:
    """One table line; the coarse-to-fine line carries the speed-up and the same-mesh check."""
    guess = row.get("estimated", False)
    speed = same = ""
    if mode == "c2f":
        speed = f"{dense['seconds'] / row['seconds']:.1f}x" + ("*" if dense.get("estimated") else "")
        same = "-" if dense.get("estimated") else ("yes" if row["digest"] == dense["digest"] else "NO")
    seconds = f"{row['seconds']:.1f}" + ("*" if guess else "")
    peak, extract, faces = ("-", "-", "-") if guess else (
        f"{row['peak_mb']:.0f}", f"{row['extract_mb']:.0f}", str(row["faces"]))
    rate = row["evaluations"] / row["seconds"]
    return (f"{device:6} {field:8} {resolution:>4} {mode:5} {seconds:>9} {row['evaluations']:>12,} "
            f"{rate:>9.3g} {peak:>8} {extract:>10} {faces:>9} {speed:>8} {same:>5}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--fields", nargs="+", default=["analytic", "mlp"], choices=["analytic", "mlp"])
    parser.add_argument("--skip-dense-512", action="store_true",
                        help="do not run the MLP's dense 512 (~15 min on 2 CPU cores): estimate it from "
                             "its dense 256 (needs 256 among --resolutions)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(json.loads(args.one))))
        return

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; devices: {', '.join(devices)}")
    header = (f"{'device':6} {'field':8} {'res':>4} {'mode':5} {'seconds':>9} {'evaluations':>12} "
              f"{'evals/s':>9} {'peak MB':>8} {'extract MB':>10} {'faces':>9} {'speed-up':>8} {'same':>5}")
    print(header + "\n" + "-" * len(header))
    estimated = False
    for device in devices:
        for field in args.fields:
            dense_runs: dict[int, dict] = {}
            for resolution in sorted(args.resolutions):
                config = {"field": field, "resolution": resolution, "device": device}
                skip = args.skip_dense_512 and field == "mlp" and resolution >= 512
                if skip and resolution // 2 in dense_runs:
                    dense = estimate_dense(dense_runs[resolution // 2], resolution)
                    estimated = True
                else:
                    dense = dense_runs[resolution] = run_subprocess({**config, "mode": "dense"})
                print(format_row(device, field, resolution, "dense", dense, dense), flush=True)
                fine = run_subprocess({**config, "mode": "c2f"})
                print(format_row(device, field, resolution, "c2f", fine, dense), flush=True)
    print("peak MB: the subprocess's peak RSS (imports included); extract MB: its growth during extract_mesh")
    if estimated:
        print("* estimate, not measured: the dense time at half the resolution scaled by the number of grid "
              "points, (n+1)^3 / (n/2+1)^3")


if __name__ == "__main__":
    main()
