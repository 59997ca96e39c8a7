"""train.py under torchrun, recording the training shapes this rank reads each step (a test helper):

    torchrun --nproc_per_node 2 tests/torchrun_probe.py <record prefix> <train.py overrides ...>

writes <record prefix>.rank<RANK>.json: per step, the latent-code rows of the shapes whose SDF samples
this rank read from the caches."""

import atexit
import json
import os
import sys
from pathlib import Path

from neuralsurf.cli import train_main
from neuralsurf.priors.cache import SplitArrays

prefix = sys.argv.pop(1)
steps: list[list[int]] = []
take = SplitArrays.take


def recording(self, key, shapes, rows):
    if key == "sdf_values":
        steps.append(shapes.tolist())
    return take(self, key, shapes, rows)


SplitArrays.take = recording
atexit.register(lambda: Path(f"{prefix}.rank{os.environ.get('RANK', '0')}.json").write_text(json.dumps(steps)))
train_main()
