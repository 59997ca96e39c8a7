"""Real RGB-D captures found by their folder under the data root: any sequence `neuralsurf.io.read_rgbd_folder`
reads (7-Scenes, TUM RGB-D, Redwood), as a depth scene scored on held-out frames."""

from __future__ import annotations

from neuralsurf.scenes.recipes import Scene, _unavailable, data_path, rgbd_scene


def rgbd_capture(name: str, folder: str, root: str | None = None, stride: int = 1, max_frames: int | None = None,
                 hold_out_every: int = 10, cloud_stride: int = 4, near_distance: float | None = 0.05) -> Scene:
    """The RGB-D sequence in `folder` under `root`, $NEURALSURF_DATA or the fetch cache (`data_path`): every
    `stride`-th frame (at most `max_frames`), every `hold_out_every`-th of those held out for scoring
    (`rgbd_scene`). Raises SceneUnavailable naming the command that fetches it when the folder is absent."""
    path = data_path(root, folder)
    if not path.is_dir():
        raise _unavailable(path, folder)
    return rgbd_scene(str(path), name, stride, max_frames, hold_out_every, cloud_stride, near_distance=near_distance)
