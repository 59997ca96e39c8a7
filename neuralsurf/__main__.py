"""python -m neuralsurf {train,evaluate,score,export,data,view} [arguments]"""

import sys

from neuralsurf import data, export, view
from neuralsurf.cli import evaluate_main, score_main, train_main


def data_main() -> int:
    """``python -m neuralsurf data {list,fetch}``: `neuralsurf.data.main`'s exit status."""
    return data.main(sys.argv[1:])


def export_main() -> int:
    """``python -m neuralsurf export RUN_DIR ...``: `neuralsurf.export.main`'s exit status."""
    return export.main(sys.argv[1:])


def view_main() -> int:
    """``python -m neuralsurf view PATH ...``: `neuralsurf.view.main`'s exit status."""
    return view.main(sys.argv[1:])


COMMANDS = {"train": train_main, "evaluate": evaluate_main, "score": score_main, "export": export_main,
            "data": data_main, "view": view_main}
USAGE = (f"usage: python -m neuralsurf {{{','.join(COMMANDS)}}} [arguments]  (train/evaluate take Hydra overrides, "
         f"e.g. experiment=bunny_sdf; score: two meshes; export: a finished run's mesh again; data: list or fetch "
         f"data sets; view: meshes in the browser; <command> --help for each)")

if __name__ == "__main__":
    if len(sys.argv) == 2 and sys.argv[1] in ("-h", "--help"):
        print(USAGE)
        sys.exit(0)
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        sys.exit(USAGE)
    command = COMMANDS[sys.argv.pop(1)]
    sys.argv[0] = f"neuralsurf-{command.__name__.split('_')[0]}"
    sys.exit(command())  # score and data return their status; train and evaluate None (0)
