"""Shape collections for learned priors: procedural classes with analytic SDFs, and caches of samples."""

from neuralsurf.shapes.procedural import (
    SHAPE_CLASSES,
    SPLITS,
    Chair,
    Lamp,
    Mug,
    Shape,
    ShapeRecord,
    check_shape,
    collection_records,
)

__all__ = ["SHAPE_CLASSES", "SPLITS", "Chair", "Lamp", "Mug", "Shape", "ShapeRecord", "check_shape",
           "collection_records"]
