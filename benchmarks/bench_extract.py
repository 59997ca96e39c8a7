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
    out = subprocess.run([sys.executable, __file__, "--one", json.dumps(config)], capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{config} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--fields", nargs="+", default=["analytic", "mlp"], choices=["analytic", "mlp"])
    parser.add_argument("--skip-dense-512", action="store_true",
                        help="do not run the MLP's dense 512 (~15 min on 2 CPU cores); estimate it instead")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(json.loads(args.one))))
        return

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; devices: {', '.join(devices)}")
    header = (f"{'device':6} {'field':8} {'res':>4} {'mode':5} {'seconds':>9} {'evaluations':>12} "
              f"{'evals/s':>9} {'peak MB':>8} {'extract MB':>10} {'faces':>9} {'speed-up':>8} {'same':>5}")
    print(header)
    print("-" * len(header))
    for device in devices:
        for field in args.fields:
            for resolution in args.resolutions:
                rows = {}
                for mode in ("dense", "c2f"):
                    config = {"field": field, "resolution": resolution, "mode": mode, "device": device}
                    skip = (mode == "dense" and resolution >= 512 and field == "mlp" and device == "cpu"
                            and args.skip_dense_512)
                    if skip and (field, resolution // 2) in estimates.get(device, {}):
                        rows[mode] = estimate(estimates[device][(field, resolution // 2)], resolution)
                    else:
                        rows[mode] = run_subprocess(config)
                        if mode == "dense":
                            estimates.setdefault(device, {})[(field, resolution)] = rows[mode]
                for mode in ("dense", "c2f"):
                    r = rows[mode]
                    speed = f"{rows['dense']['seconds'] / r['seconds']:.1f}x" if mode == "c2f" else ""
                    same = ("yes" if rows["c2f"]["digest"] == rows["dense"]["digest"] else "NO") if mode == "c2f" else ""
                    if rows["dense"].get("estimated") and mode == "c2f":
                        speed, same = speed + "*", "-"
                    secs = f"{r['seconds']:.1f}" + ("*" if r.get("estimated") else "")
                    mb = "-" if r.get("estimated") else f"{r['peak_mb']:.0f}"
                    dmb = "-" if r.get("estimated") else f"{r['extract_mb']:.0f}"
                    faces = "-" if r.get("estimated") else str(r["faces"])
                    print(f"{device:6} {field:8} {resolution:>4} {mode:5} {secs:>9} {r['evaluations']:>12,} "
                          f"{r['evaluations'] / r['seconds']:>9.3g} {mb:>8} {dmb:>10} {faces:>9} {speed:>8} {same:>5}",
                          flush=True)
    if any(r for r in estimates.values()) and args.skip_dense_512:
        print("* estimate: dense time scaled from the dense run at half the resolution by the number of grid "
              "points ((2n+1)^3 / (n+1)^3), not measured")


estimates: dict[str, dict[tuple[str, int], dict]] = {}


def estimate(half: dict, resolution: int) -> dict:
    """Dense cost at `resolution` from the dense run at resolution / 2, scaled by grid points."""
    scale = (resolution + 1) ** 3 / (resolution // 2 + 1) ** 3
    return {"seconds": half["seconds"] * scale, "evaluations": (resolution + 1) ** 3, "estimated": True}


if __name__ == "__main__":
    main()
