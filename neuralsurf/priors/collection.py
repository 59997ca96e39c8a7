"""Shape collections: the `Collection` protocol every collection a prior trains on follows, and
`ShapeCollection`, procedural shapes as plain settings (train.py's `data` for the prior experiments):
`ShapeCollection.build()` writes its caches (or finds them) under `root`, by default
`<cache>/shapes/<hash of the settings>`; `test_shapes()` reads the held-out shapes back.
(`neuralsurf.priors.folders.FolderCollection` is the other collection: shapes from a folder of meshes.)
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from neuralsurf.data import cache_dir
from neuralsurf.errors import ConfigError
from neuralsurf.priors.cache import CacheRecipe, build_collection, cache_path, load_cache, read_manifest
from neuralsurf.priors.procedural import ShapeRecord, collection_records
from neuralsurf.structures import Mesh


@dataclass(frozen=True)
class TestShape:
    """One held-out shape: its name, ground-truth mesh and exact surface samples (unit frame)."""

    name: str
    mesh: Mesh
    surface: Tensor
    """Float[Tensor, "n 3"]: points on the analytic surface."""

    @classmethod
    def from_cache(cls, name: str, arrays: dict) -> TestShape:
        """The shape from the arrays of its cache (`priors.cache.load_cache`)."""
        mesh = Mesh(torch.from_numpy(arrays["mesh_vertices"]).double(), torch.from_numpy(arrays["mesh_faces"]))
        return cls(name, mesh, torch.from_numpy(arrays["surface_points"]).double())


@runtime_checkable
class Collection(Protocol):
    """What a prior's training, scoring and scenes use of a shape collection (train.py's `data` when the
    model is a prior). A collection is plain settings: nothing is read or written until `build`."""

    name: str

    @property
    def description(self) -> str:
        """One line for logs and reports: the classes and the shapes per split."""

    @property
    def folder(self) -> Path:
        """Where `build` writes the shapes' caches (`priors.cache`) and `collection.json`."""

    @property
    def recipe(self) -> CacheRecipe:
        """The samples cached per shape."""

    def records(self, split: str | None = None) -> list[ShapeRecord]:
        """The shapes of `split` ("train", "val", "test"; all when None), in latent-code order."""

    def count(self, split: str) -> int:
        """The number of shapes of `split`."""

    def build(self, progress: bool = True) -> Path:
        """Write every missing cache (resumable); returns `folder`."""

    def check_prior(self, observations: dict[str, dict]) -> bool:
        """Before building: ConfigError for observations (name -> config as a plain dict) the collection
        cannot serve; returns whether a prior trained on it can be scored on its test shapes."""

    def test_shapes(self, limit: int | None = None) -> list[TestShape]:
        """The first `limit` held-out shapes (all when None), read from the built caches."""


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
        key = {k: v for k, v in asdict(self).items() if k not in ("root", "workers", "name")}
        digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
        return cache_dir() / "shapes" / digest

    def records(self, split: str | None = None) -> list[ShapeRecord]:
        """The shapes of `split` (all when None), in latent-code order."""
        records = collection_records(self.classes, self.n_train, self.n_val, self.n_test, self.seed)
        return [r for r in records if split is None or r.split == split]

    def count(self, split: str) -> int:
        return len(self.records(split))

    def check_prior(self, observations: dict[str, dict]) -> bool:
        """Procedural shapes have meshes for every observation, and their test shapes are scored."""
        return True

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
            shapes.append(TestShape.from_cache(record.name, load_cache(cache_path(self.folder, record))))
        if not shapes:
            raise ConfigError(f"{self.description}: no test shapes; set n_test >= 1")
        return shapes
