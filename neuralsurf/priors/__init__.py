"""Learned shape priors end to end, without Hydra: DeepSDF auto-decoders and Occupancy Networks over
procedural shape collections.

- `procedural`, `csg`: shape classes with analytic SDFs (chairs, slatted chairs, mugs, lamps) and their
  records; `mesh_folders`: procedural shapes written as folders of damaged mesh files.
- `cache`: per-shape npz caches of training samples (`python -m neuralsurf.priors build`).
- `collection`: the `Collection` protocol; `ShapeCollection`, procedural shapes as plain settings (train.py's
  `data` for the priors); `folders`: `FolderCollection`, shapes from a folder of meshes.
- `observations`: the supervision of priors (`CollectionSDF`, `CollectionOccupancy`, `SDFSampleSet`,
  `LatentPrior`).
- `models`: `deepsdf`, `occupancy_network` sized for a collection; `load_prior` from a checkpoint.
- `training`: `train_prior` (one fit), `trained_prior` (trained once into a folder and reused).
- `completion`: `reconstruct_latent`, `complete_cloud`, `complete_view`, `extract_unit`.
- `refinement`: `Refinement`, `refine_to_view`, `refine_to_cloud`: a completion held to what was observed.
- `scoring`: `score_completions`, `mean_metrics`.
- `scenes`: `shapes_cloud`, `shapes_one_view`, the test shapes as evaluation scenes.

Everything lives in the collection's unit frame (each shape in [-0.5, 0.5]^3, `UNIT_BOUNDS`).
"""

from neuralsurf.priors.cache import CacheRecipe, build_collection
from neuralsurf.priors.collection import Collection, ShapeCollection, TestShape
from neuralsurf.priors.completion import (
    EXTRACTION_BOUNDS,
    clipped_to_cube,
    complete_cloud,
    complete_view,
    extract_unit,
    reconstruct_latent,
)
from neuralsurf.priors.models import deepsdf, load_prior, occupancy_network
from neuralsurf.priors.observations import CollectionOccupancy, CollectionSDF, LatentPrior, SDFSampleSet
from neuralsurf.priors.procedural import (
    SHAPE_CLASSES,
    SPLITS,
    UNIT_BOUNDS,
    Chair,
    Lamp,
    Mug,
    Shape,
    ShapeRecord,
    SlatChair,
    check_shape,
    collection_records,
)
from neuralsurf.priors.refinement import Refinement, ResidualField, refine_to_cloud, refine_to_view
from neuralsurf.priors.scenes import shapes_cloud, shapes_one_view
from neuralsurf.priors.scoring import mean_metrics, score_completions
from neuralsurf.priors.training import train_prior, trained_prior

__all__ = ["EXTRACTION_BOUNDS", "SHAPE_CLASSES", "SPLITS", "UNIT_BOUNDS", "CacheRecipe", "Chair", "Collection", "CollectionOccupancy",
           "CollectionSDF", "Lamp", "LatentPrior", "Mug", "Refinement", "ResidualField", "SDFSampleSet", "Shape", "ShapeCollection", "ShapeRecord",
           "SlatChair", "TestShape", "build_collection", "check_shape", "clipped_to_cube", "collection_records", "complete_cloud",
           "complete_view", "deepsdf", "extract_unit", "load_prior", "mean_metrics", "occupancy_network",
           "reconstruct_latent", "refine_to_cloud", "refine_to_view", "score_completions", "shapes_cloud", "shapes_one_view", "train_prior",
           "trained_prior"]
