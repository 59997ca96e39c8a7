"""Multi-process training: 2 CPU processes (gloo) step exactly as one process with the same global batch,
and resume from rank 0's checkpoint."""

import functools
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
import trimesh

from neuralsurf.checkpoints import load_checkpoint
from neuralsurf.priors import ShapeRecord, deepsdf
from neuralsurf.priors.cache import CacheRecipe, build_collection
from neuralsurf.priors.observations import CollectionSDF, CollectionSDFSampler
from neuralsurf.structures import Normalization
from neuralsurf.training import default_optimizer, fit

pytestmark = pytest.mark.skipif(not dist.is_available(), reason="this PyTorch has no torch.distributed")

RECORDS = [ShapeRecord(kind, "train", i) for kind in ("chair", "mug") for i in range(2)]
STEPS = 12
TOLERANCE = 1e-5
"""Relative: two half-batch gradients averaged by DDP equal the full batch's up to float rounding."""


def _fit(root, run_dir=None, seed=0, **options):
    torch.manual_seed(seed)
    model = deepsdf(len(RECORDS), latent_dim=8, width=32, depth=3, skip_layers=(1,))
    observation = CollectionSDF(root, shapes_per_batch=4, samples_per_shape=128)
    return fit(model, observation, steps=STEPS, normalization=Normalization(), encoding_lr=None, device="cpu",
               progress=False, log_every=1, checkpoint_every=5, run_dir=run_dir, image_every=0,
               optimizer=functools.partial(default_optimizer, lr=5e-3), **options)


def _worker(rank, world, port, root, out, interrupt_at):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        run_dir = os.path.join(out, "run")
        if interrupt_at:
            draw, calls = CollectionSDFSampler.sample, []

            def interrupted(self, generator):  # both ranks stop while drawing the same batch
                calls.append(1)
                if len(calls) == interrupt_at:
                    raise KeyboardInterrupt
                return draw(self, generator)

            CollectionSDFSampler.sample = interrupted
            try:
                _fit(root, run_dir)
            except KeyboardInterrupt:
                pass
            CollectionSDFSampler.sample = draw
        result = _fit(root, run_dir, seed=1 if interrupt_at else 0)  # resumed: other weights, replaced
        with open(os.path.join(out, f"rank{rank}.json"), "w") as file:
            json.dump({"history": result.history, "steps": result.steps,
                       "code": result.model.codes.weight.tolist()}, file)
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(root, out, interrupt_at=0):
    out.mkdir()
    mp.spawn(_worker, args=(2, _free_port(), str(root), str(out), interrupt_at), nprocs=2, join=True)
    return [json.loads((out / f"rank{r}.json").read_text()) for r in range(2)]


@pytest.fixture(scope="module")
def collection(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp_shapes")
    build_collection(root, RECORDS, CacheRecipe(n_sdf=4000, n_occ=500, n_surface=500, mesh_resolution=32),
                     progress=False)
    return root


@pytest.mark.subprocess
@pytest.mark.slow
def test_two_processes_match_one_with_the_same_global_batch_and_resume(collection, tmp_path):
    single = _fit(collection)
    two = _spawn(collection, tmp_path / "straight")
    # every rank logs the mean over ranks, and holds the same (all-reduced) weights
    assert two[0]["history"]["total"] == two[1]["history"]["total"]
    assert two[0]["code"] == two[1]["code"]
    for key in ("total", "shapes/sdf", "shapes/code", "grad_norm"):
        assert two[0]["history"][key] == pytest.approx(single.history[key], rel=TOLERANCE), key
    assert single.history["total"][-1] < 0.8 * single.history["total"][0]  # it trains
    codes = torch.tensor(two[0]["code"])
    assert torch.allclose(codes, single.model.codes.weight.detach(), rtol=1e-4, atol=1e-6)  # codes all-reduced

    # interrupted at step 8 (checkpoint of step 5 by rank 0 alone), resumed by both ranks to step 12
    resumed = _spawn(collection, tmp_path / "resumed", interrupt_at=8)
    assert load_checkpoint(tmp_path / "resumed" / "run" / "checkpoints" / "last.pt")["step"] == STEPS
    assert resumed[0]["steps"] == STEPS
    assert resumed[0]["history"]["total"] == pytest.approx(two[0]["history"]["total"], rel=1e-6)
    assert torch.allclose(torch.tensor(resumed[0]["code"]), torch.tensor(two[0]["code"]), rtol=1e-5, atol=1e-7)
    assert not list((tmp_path / "straight").glob("rank*/")), "only rank 0 writes the run directory"


@pytest.mark.subprocess
@pytest.mark.slow
def test_torchrun_trains_a_prior_on_a_folder_each_rank_reading_its_own_shapes(tmp_path):
    """`torchrun --nproc_per_node 2 train.py data=shape_folder ...` (gloo, CPU): every step the two ranks
    read disjoint halves of the step's shapes from the caches, and the run finishes (rank 0's checkpoint
    and metrics)."""
    torchrun = shutil.which("torchrun", path=os.path.dirname(sys.executable)) or shutil.which("torchrun")
    if torchrun is None:
        pytest.skip("torchrun is not installed beside this Python")
    source = tmp_path / "shapes"
    for kind, mesh in (("box", trimesh.creation.box), ("ball", trimesh.creation.icosphere)):
        (source / kind).mkdir(parents=True)
        for i in range(3):
            shape = mesh((0.6 + 0.1 * i, 1.0, 0.5)) if kind == "box" else mesh(2, radius=0.5 + 0.1 * i)
            shape.export(source / kind / f"{kind}{i}.ply")
        (source / kind / "train.lst").write_text(f"{kind}0\n{kind}1\n")
        (source / kind / "test.lst").write_text(f"{kind}2\n")
    root = Path(__file__).resolve().parents[1]
    overrides = ["experiment=shapes_deepsdf_tiny", "data=shape_folder", f"data.source={source}",
                 f"data.root={tmp_path / 'cache'}", "data.workers=0", "data.n_sdf=4000", "data.n_occ=500",
                 "data.n_surface=500", "observation.shapes.shapes_per_batch=4", "trainer.steps=6",
                 "trainer.checkpoint_every=3", "trainer.progress=false", "score.latent_steps=3", "score.n_samples=1000",
                 "extract.resolution=24", f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(root)}
    done = subprocess.run([torchrun, "--nproc_per_node", "2", "--master_port", str(_free_port()),
                           str(root / "tests" / "torchrun_probe.py"), str(tmp_path / "read"), *overrides],
                          check=False, cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    ranks = [json.loads((tmp_path / f"read.rank{rank}.json").read_text()) for rank in range(2)]
    assert len(ranks[0]) == len(ranks[1]) == 6
    for first, second in zip(*ranks):  # the step's 4 shapes: 2 on each rank, none on both
        assert len(first) == len(second) == 2 and not set(first) & set(second)
        assert set(first) | set(second) == {0, 1, 2, 3}
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")["step"] == 6
    assert "chamfer_l1_exact" in json.loads((tmp_path / "run" / "metrics.json").read_text())
