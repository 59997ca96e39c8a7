"""python -m neuralsurf {train,evaluate,score,data,view} [arguments]"""

import sys

from neuralsurf import data, view
from neuralsurf.cli import evaluate_main, score_main, train_main


def data_main() -> int:
    """``python -m neuralsurf data {list,fetch}``: `neuralsurf.data.main`'s exit status."""
    return data.main(sys.argv[1:])


def view_main() -> int:
    """``python -m neuralsurf view PATH ...``: `neuralsurf.view.main`'s exit status."""
    return view.main(sys.argv[1:])


COMMANDS = {"train": train_main, "evaluate": evaluate_main, "score": score_main, "data": data_main, "view": view_main}

if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        sys.exit(f"usage: python -m neuralsurf {{{','.join(COMMANDS)}}} [arguments]  "
                 f"(train/evaluate take Hydra overrides, e.g. experiment=bunny_sdf; data: list or fetch data sets; "
                 f"view: meshes in the browser)")
    command = COMMANDS[sys.argv.pop(1)]
    sys.argv[0] = f"neuralsurf-{command.__name__.split('_')[0]}"
    sys.exit(command())  # score and data return their status; train and evaluate None (0)
