"""Per-pixel held-out depth error maps (evaluation.distances) and their place in report.html."""

from __future__ import annotations

import numpy as np

from neuralsurf.evaluation.distances import held_out_error_image
from neuralsurf.evaluation.report import write_html


def test_error_map_colours_behind_in_front_missing_and_unread_pixels():
    measured = np.full((1, 2, 3), 2.0, dtype=np.float32)
    measured[0, 1, 2] = 0.0  # no reading
    rendered = np.array([[[2.1, 1.9, 2.0], [0.0, 2.0, 2.0]]], dtype=np.float32)  # behind, in front, exact; nothing
    image = np.asarray(held_out_error_image(rendered, measured, top=0.2))
    assert image.shape == (2, 9, 3)
    error = image[:, 6:]
    assert tuple(error[0, 0]) == (127, 127, 0)  # 10 cm behind: half red
    assert tuple(error[0, 1]) == (0, 127, 127)  # 10 cm in front: half blue
    assert tuple(error[0, 2]) == (0, 255, 0)
    assert tuple(error[1, 0]) == (0, 0, 0) and tuple(error[1, 2]) == (128, 128, 128)
    assert tuple(image[0, 0]) == (102, 102, 102)  # 2 m of the 0-5 m grey scale


def test_report_shows_the_held_out_maps(tmp_path):
    (tmp_path / "renders").mkdir()
    held_out_error_image(np.ones((1, 4, 4)), np.ones((1, 4, 4))).save(tmp_path / "renders" / "m.png")
    row = {"method": "tsdf", "scene": "room", "status": "ok", "held_out_render": "renders/m.png"}
    text = write_html([row], tmp_path, []).read_text()
    assert "tsdf on room: held-out views" in text and "data:image/png;base64" in text
