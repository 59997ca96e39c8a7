"""Learned shape priors end to end, without Hydra: the collection a run trains on, the models built
for it, the trained prior read back from a checkpoint, and shape completion with it.

- `ShapeCollection`: a procedural collection (`neuralsurf.shapes`) as plain settings; `build()` writes
  its caches (or finds them) under `root`, by default `<cache>/shapes/<hash of the settings>`.
- `deepsdf(n_shapes, ...)`, `occupancy_network(n_shapes, ...)`: the two priors, sized for a collection
  of `n_shapes` training shapes (one latent code each for DeepSDF; the encoder gives OccNet its codes).
- `load_prior(path)`: the trained model of a run's checkpoint, rebuilt from the allowlist of
  `neuralsurf.models.spec` (weights_only; nothing in the file chooses code to run).
- `complete_cloud`, `complete_view`: a test shape's field from a (noisy, partial) cloud or one depth
  view; `score_completions`: mean metrics over test shapes from noisy clouds (train.py's metrics).

Everything lives in the collection's unit frame (each shape in [-0.5, 0.5]^3).
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from neuralsurf.errors import CheckpointError, ConfigError, NeuralsurfError
from neuralsurf.models import SDFMLP, AutoDecoder, CBNDecoder, LatentCodes, OccupancyNetwork, PointNetEncoder
from neuralsurf.shapes.cache import CacheRecipe, build_collection, cache_path, load_cache, read_manifest
from neuralsurf.shapes.procedural import ShapeRecord, collection_records
from neuralsurf.structures import DepthFrames, Mesh, PointCloud

UNIT_BOUNDS = np.array([[-0.55] * 3, [0.55] * 3])
"""Extraction box of a prior's shapes: the unit cube plus the caches' padding."""


@dataclass(frozen=True)
class TestShape:
    """One held-out shape: its name, ground-truth mesh and exact surface samples (unit frame)."""

    name: str
    mesh: Mesh
    surface: Tensor
    """Float[Tensor, "n 3"]: points on the analytic surface."""


@dataclass(frozen=True)
class ShapeCollection:
    """A procedural shape collection as plain settings (train.py's `data` for the prior experiments)."""

    classes: tuple[str, ...] = ("chair", "mug", "lamp")
    n_train: int = 64
    """Training shapes per class (one latent code each)."""
    n_val: int = 0
    n_test: int = 8
    """Test shapes per class (never trained on)."""
    seed: int = 0
    """Collection seed; a shape's own seed depends on it, its split, class and index only, so the test
    shapes are the same whatever n_train is."""
    n_sdf: int = 100_000
    n_occ: int = 50_000
    n_surface: int = 20_000
    mesh_resolution: int = 128
    root: str | None = None
    """Folder of the caches; None: `<$NEURALSURF_CACHE or ~/.cache/neuralsurf>/shapes/<settings hash>`."""
    workers: int = 2
    """Processes that build missing caches (0: this one)."""
    name: str = "shapes"

    def __post_init__(self) -> None:
        object.__setattr__(self, "classes", tuple(self.classes))
        collection_records(self.classes, self.n_train, self.n_val, self.n_test, self.seed)  # checks the counts
        self.recipe  # noqa: B018 - checks the recipe

    @property
    def recipe(self) -> CacheRecipe:
        return CacheRecipe(n_sdf=self.n_sdf, n_occ=self.n_occ, n_surface=self.n_surface,
                           mesh_resolution=self.mesh_resolution)

    @property
    def description(self) -> str:
        return (f"{len(self.classes)} procedural classes ({', '.join(self.classes)}): {self.n_train} train, "
                f"{self.n_val} val, {self.n_test} test shapes per class, seed {self.seed}")

    @property
    def folder(self) -> Path:
        if self.root is not None:
            return Path(self.root).expanduser()
        from neuralsurf.data import cache_dir

        key = {k: v for k, v in asdict(self).items() if k not in ("root", "workers", "name")}
        digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
        return cache_dir() / "shapes" / digest

    def records(self, split: str | None = None) -> list[ShapeRecord]:
        """The shapes of `split` (all when None), in latent-code order."""
        records = collection_records(self.classes, self.n_train, self.n_val, self.n_test, self.seed)
        return [r for r in records if split is None or r.split == split]

    def count(self, split: str) -> int:
        return len(self.records(split))

    def build(self, progress: bool = True) -> Path:
        """Write every missing cache (resumable; shapes already cached are skipped); returns the folder.
        A folder holding another collection (other shapes or recipe) is a ConfigError."""
        if (self.folder / "collection.json").is_file():
            records, recipe = read_manifest(self.folder)
            if records != self.records() or recipe != self.recipe:
                raise ConfigError(f"{self.folder} holds another shape collection ({len(records)} shapes, {recipe}); "
                                  f"give this one another root (or root=null: a folder per settings)")
        build_collection(self.folder, self.records(), self.recipe, workers=self.workers, progress=progress)
        return self.folder

    def test_shapes(self, limit: int | None = None) -> list[TestShape]:
        """The first `limit` test shapes (all when None), read from the built caches."""
        shapes = []
        for record in self.records("test")[:limit]:
            arrays = load_cache(cache_path(self.folder, record))
            mesh = Mesh(torch.from_numpy(arrays["mesh_vertices"]).double(), torch.from_numpy(arrays["mesh_faces"]))
            shapes.append(TestShape(record.name, mesh, torch.from_numpy(arrays["surface_points"]).double()))
        if not shapes:
            raise ConfigError(f"{self.description}: no test shapes; set n_test >= 1")
        return shapes


# ----------------------------------------------------------------------------- models


def deepsdf(n_shapes: int, latent_dim: int = 64, width: int = 256, depth: int = 8, skip_layers=(4,),
            weight_norm: bool = True, activation: str = "relu", init_radius: float = 0.25,
            code_std: float = 0.01) -> AutoDecoder:
    """A DeepSDF auto-decoder for `n_shapes` training shapes: an SDFMLP decoder taking codes of
    `latent_dim` entries (DeepSDF: 8 x 512, skip at layer 4, weight norm) and one code per shape,
    initialised N(0, code_std^2)."""
    decoder = SDFMLP(width=width, depth=depth, skip_layers=tuple(skip_layers), weight_norm=weight_norm,
                     activation=activation, latent_dim=latent_dim, init_radius=init_radius)
    return AutoDecoder(decoder, LatentCodes(n_shapes, latent_dim, init_std=code_std))


def occupancy_network(n_shapes: int, latent_dim: int = 128, encoder_hidden: int = 128, hidden: int = 256,
                      blocks: int = 5, threshold: float = 0.2, plane_dim: int = 0,
                      plane_resolution: int = 32) -> OccupancyNetwork:
    """An Occupancy Network (PointNet encoder with ResNet blocks, CBN decoder), codes of `latent_dim`
    entries, its field's zero level at occupancy probability `threshold` (the paper's 0.2); with
    `plane_dim > 0` also feature planes of that many channels (`plane_resolution`^2 cells, ConvONet).
    `n_shapes` is unused: the encoder computes each shape's code (the argument keeps one signature
    for both priors)."""
    planes = {"plane_dim": plane_dim, "plane_resolution": plane_resolution}
    return OccupancyNetwork(PointNetEncoder(latent_dim, encoder_hidden, **planes),
                            CBNDecoder(latent_dim, hidden, blocks, **planes), threshold=threshold)


def train_prior(run_dir: str | Path, collection: ShapeCollection, model: Callable[..., nn.Module],
                observations: list[Callable], *, optimizer: Callable | None = None, trainer: dict | None = None,
                seed: int = 0, device: str = "cpu", config: dict | None = None) -> Path:
    """Train `model(n_shapes=...)` over `collection` (built here if needed) with the observations
    `observations[i](collection)` and `fit`'s `trainer` options, into `run_dir` (resumed there; a
    finished run is reused as it is). Returns its checkpoint, for `load_prior`. Processes that ask for
    the same `run_dir` together (the jobs of an evaluation sweep) train it once: the first holds the
    lock `<run_dir>.lock` while it trains, the others wait and then reuse its checkpoint."""
    from neuralsurf.locks import file_lock
    from neuralsurf.structures import Normalization
    from neuralsurf.training import CHECKPOINT_NAME, default_optimizer, fit, load_checkpoint

    trainer = {"progress": False, "image_every": 0, "mesh_every": 0, **(trainer or {})}
    path = Path(run_dir) / "checkpoints" / CHECKPOINT_NAME
    with file_lock(Path(run_dir).with_name(f"{Path(run_dir).name}.lock")):
        if path.is_file() and load_checkpoint(path).get("step", 0) >= trainer.get("steps", 2000):
            return path
        collection.build(progress=False)
        fit(model(n_shapes=collection.count("train")), [build(collection) for build in observations],
            optimizer=optimizer or default_optimizer, device=device, seed=seed, run_dir=run_dir, config=config,
            normalization=Normalization(), **trainer)
    return path


def load_prior(path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """The trained prior (an AutoDecoder or OccupancyNetwork, unit frame, eval mode) of a run's
    `checkpoints/last.pt`. Rebuilt from the allowlist of model classes (`models.spec`)."""
    from neuralsurf.models.spec import REBUILDABLE, build_checked
    from neuralsurf.training import PRIOR_CLASSES, load_checkpoint, stored_class

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"prior checkpoint {path} not found; pass the checkpoints/last.pt of a "
                              f"train.py experiment=shapes_* run")
    state = load_checkpoint(path)
    if not isinstance(state.get("model_spec"), dict) or "model" not in state:
        raise CheckpointError(f"{path} holds no rebuildable model; it was not written by a neuralsurf fit")
    name = stored_class(state)
    if name in REBUILDABLE and name not in PRIOR_CLASSES:
        raise CheckpointError(f"{path} holds a {name}, not a learned prior (AutoDecoder or OccupancyNetwork): a "
                              f"single-shape field; load it with neuralsurf.load_field")
    model = build_checked(state["model_spec"], state["model"], f"{path}: model")
    return model.to(device).eval()


# ----------------------------------------------------------------------------- completion

UNIT_FRAME_REACH = 0.75
"""|coordinate| beyond which a cloud is taken to lie outside a prior's unit frame (the cube
[-0.5, 0.5]^3, plus room for noise)."""


def warn_outside_unit_frame(points: Tensor, where: str) -> None:
    """Warn when the finite points of Float[Tensor, "n 3"] reach beyond UNIT_FRAME_REACH: a prior
    knows only shapes in its unit cube, so a cloud in world units (metres, millimetres) completes to
    nonsense. Malformed clouds are left to the completion's own checks."""
    if not (isinstance(points, Tensor) and points.ndim == 2 and points.shape[-1] == 3):
        return
    finite = points[torch.isfinite(points).all(dim=1)]
    if not len(finite):
        return
    low, high = finite.min(dim=0).values.tolist(), finite.max(dim=0).values.tolist()
    if max(map(abs, low + high)) > UNIT_FRAME_REACH:
        bounds = ", ".join(f"[{lo:.3g}, {hi:.3g}]" for lo, hi in zip(low, high))
        warnings.warn(f"{where}: the cloud spans x, y, z = {bounds}, outside the prior's unit frame (its shapes lie "
                      f"in [-0.5, 0.5]^3): the completion will be meaningless. Normalise the cloud first: "
                      f"n = neuralsurf.structures.Normalization.from_points(points); complete n.to_unit(points), "
                      f"and map the result back with n.to_world", stacklevel=3)


def complete_cloud(prior: nn.Module, points: Tensor, *, latent_steps: int = 200, lr: float = 1e-2,
                   seed: int = 0, device: str = "cpu") -> nn.Module:
    """The unit-frame world field (negative inside) of the shape whose surface points (noisy, possibly
    partial) are `points` (Float[Tensor, "n 3"]): DeepSDF fits a code under the frozen decoder
    (`PointSamples`: surface and near-surface terms + code prior); OccNet encodes the cloud.
    The cloud is not projected onto its local quadrics first (PointSamples' `denoise`): the frozen
    decoder averages the noise, and the projection merges the two sides of thin walls (24 test
    shapes from 3,000 points: mean IoU 0.70 with it, 0.89 without; mugs 0.44 and 0.96)."""
    from neuralsurf.observations import PointSamples
    from neuralsurf.shapes.completion import reconstruct_latent

    warn_outside_unit_frame(points, "complete_cloud")
    if isinstance(prior, OccupancyNetwork):
        return prior.to(device).field_from_cloud(points)
    if isinstance(prior, AutoDecoder):
        observation = PointSamples(PointCloud(points.double()), weights={"surface": 1.0, "sdf": 1.0},
                                   normals="estimate", denoise=False, batch_size=2048, n_near=60_000,
                                   n_free=15_000)
        return reconstruct_latent(prior.decoder, [observation], steps=latent_steps, lr=lr, seed=seed,
                                  device=device).field
    raise ConfigError(f"complete_cloud takes an AutoDecoder or OccupancyNetwork, got {type(prior).__name__}")


# the one-view latent fit's ray terms and options (the README's shapes_one_view figures). No eikonal term:
# under a frozen ReLU decoder its gradient in the code is zero (grad_x f is piecewise constant in it), so
# it only cost a double backward (same meshes, 28 s instead of 49 s a shape on the 2-core CPU).
COMPLETION_RAY_WEIGHTS = {"surface": 1.0, "band": 1.0, "free": 1.0, "carve": 1.0}
COMPLETION_RAY_OPTIONS = {"hit_fraction": 0.0, "carve_margin": 0.0, "winding_points": 0, "denoise_k": 0}


def complete_view(prior: nn.Module, frames: DepthFrames, points: Tensor, *, latent_steps: int = 200,
                  lr: float = 1e-2, cloud_points: int = 3000, sigma: float = 0.002, seed: int = 0,
                  device: str = "cpu") -> nn.Module:
    """The field of a shape seen in one depth view: DeepSDF fits a code to the view's rays (surface,
    band and free space, `DepthRays`, constant noise `sigma`); OccNet encodes `cloud_points` of the
    back-projected `points` (Float[Tensor, "n 3"])."""
    from neuralsurf.observations import DepthRays
    from neuralsurf.shapes.completion import reconstruct_latent

    warn_outside_unit_frame(points, "complete_view")
    if isinstance(prior, OccupancyNetwork):
        pick = torch.randperm(len(points), generator=torch.Generator().manual_seed(seed))[:cloud_points]
        return prior.to(device).field_from_cloud(points[pick])
    if isinstance(prior, AutoDecoder):
        rays = DepthRays(frames, weights=COMPLETION_RAY_WEIGHTS, noise_model="constant", sigma=sigma, n_rays=1024,
                         **COMPLETION_RAY_OPTIONS)
        return reconstruct_latent(prior.decoder, [rays], steps=latent_steps, lr=lr, seed=seed, device=device).field
    raise ConfigError(f"complete_view takes an AutoDecoder or OccupancyNetwork, got {type(prior).__name__}")


def interpolation_picture(prior: AutoDecoder, first: int, second: int, path: str | Path, steps: int = 5,
                          resolution: int = 64, size: int = 160) -> Path:
    """A PNG of the shapes of codes (1 - t) z_first + t z_second for `steps` values of t in [0, 1]
    (training shapes `first` and `second` of an auto-decoder): DeepSDF's latent interpolation."""
    from neuralsurf.evaluation.render import default_view, labelled_row, shade
    from neuralsurf.models import LatentConditioned

    codes = prior.codes.weight.detach()
    view = default_view(UNIT_BOUNDS)
    images, labels = [], []
    for t in np.linspace(0.0, 1.0, steps):
        code = (1 - t) * codes[first] + t * codes[second]
        field = LatentConditioned.from_code(prior.decoder, code.cpu()).to(codes.device).eval()
        with torch.no_grad():
            images.append(shade(extract_unit(field, resolution), view, size, size))
        labels.append(f"t = {t:.2f}")
    path = Path(path)
    labelled_row(images, labels).save(path)
    return path


def noisy_cloud(surface: Tensor, n_points: int, noise: float, seed: int) -> Tensor:
    """`n_points` of `surface` (Float[Tensor, "m 3"]) at random plus N(0, noise^2) on each coordinate."""
    generator = torch.Generator().manual_seed(seed)
    pick = torch.randperm(len(surface), generator=generator)[:n_points]
    return surface[pick] + noise * torch.randn(len(pick), 3, generator=generator, dtype=surface.dtype)


def clipped_to_cube(field: nn.Module, half: float = 0.525):
    """x[..., 3] -> max(field(x), box(x)): the field intersected with the cube [-half, half]^3, inside
    the extraction box. A prior's shapes lie in the unit cube by construction; a field still negative
    at the box's faces (far from any training sample) would leave the mesh open there."""
    from neuralsurf.shapes import csg

    def clipped(x: Tensor) -> Tensor:
        return torch.maximum(field(x), csg.box(x, (0.0, 0.0, 0.0), (half,) * 3).to(x.dtype))

    return clipped


def extract_unit(field: nn.Module, resolution: int) -> Mesh:
    """A prior's shape as a closed mesh: coarse-to-fine marching cubes of the field clipped to the
    cube (`clipped_to_cube`) over the padded unit cube."""
    from neuralsurf.extract import extract_mesh

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        device = next(field.parameters()).device  # the clipped field is a plain function: say where it runs
        return extract_mesh(clipped_to_cube(field), resolution=resolution, bounds=UNIT_BOUNDS, progress=False,
                            device=device)


def score_completions(prior: nn.Module, shapes: list[TestShape], *, n_points: int = 3000, noise: float = 0.005,
                      latent_steps: int = 200, resolution: int = 64, n_samples: int = 20_000, seed: int = 0,
                      device: str = "cpu") -> tuple[dict[str, float], list[dict], Mesh | None]:
    """Complete each shape from `n_points` noisy surface points and score its mesh (`evaluate_mesh`).
    Returns (means of the numeric metrics, with "shapes" and "failed" counts; per-shape metrics; the
    first shape's mesh). A shape without a surface counts with IoU 0 and F-scores 0."""
    from neuralsurf.metrics import evaluate_mesh

    per_shape, first = [], None
    for i, shape in enumerate(shapes):
        cloud = noisy_cloud(shape.surface, n_points, noise, seed + i)
        try:
            mesh = extract_unit(complete_cloud(prior, cloud, latent_steps=latent_steps, seed=seed, device=device),
                                resolution)
            metrics = {k: float(v) for k, v in evaluate_mesh(mesh, shape.mesh, n_samples=n_samples, seed=seed).items()}
            first = mesh if first is None else first
        except NeuralsurfError as error:
            metrics = {"iou": 0.0, "fscore_1%": 0.0, "fscore_0.5%": 0.0, "failed": str(error)[:200]}
        per_shape.append({"shape": shape.name, **metrics})
    return mean_metrics(per_shape), per_shape, first


def mean_metrics(per_shape: list[dict]) -> dict[str, float]:
    """Means of every numeric metric over the shapes that have it (NaN skipped), plus "shapes" and
    "failed" counts."""
    keys = {k for row in per_shape for k, v in row.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    means = {}
    for key in sorted(keys):
        values = [row[key] for row in per_shape if isinstance(row.get(key), (int, float)) and not math.isnan(row[key])]
        means[key] = float(np.mean(values)) if values else math.nan
    return {**means, "shapes": len(per_shape), "failed": sum("failed" in row for row in per_shape)}
