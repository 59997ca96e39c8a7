"""Metrics against brute-force references (torch.cdist, naive point-to-triangle) and analytic cases."""

import math

import pytest
import torch

from neuralsurf.errors import InputError
from neuralsurf.geometry import closest_on_mesh, cloud_from_mesh, point_to_mesh_distance
from neuralsurf.metrics import (
    box_overlap,
    chamfer_distances,
    chamfer_l1,
    chamfer_l2,
    chamfer_l2_sum,
    evaluate_mesh,
    evaluate_samples,
    fscore,
    fscore_key,
    hausdorff,
    iou,
    json_ready,
    normal_consistency,
)
from neuralsurf.scenes.analytic import Box, Sphere, Torus
from neuralsurf.structures import Mesh

# ----------------------------------------------------------------------------- naive references


def naive_nearest(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Brute-force nearest neighbour of each a point among b: (distance, index)."""
    d = torch.cdist(a.double(), b.double())
    return d.min(dim=1)


def naive_point_to_triangles(points: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Exact distance of each point (p, 3) to the closest of `triangles` (t, 3, 3), float64."""
    return naive_distances_to_each_triangle(points, triangles).amin(dim=1)


def naive_distances_to_each_triangle(points: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Exact distance of each point (p, 3) to each of `triangles` (t, 3, 3): (p, t), float64.

    The closest point of a triangle is either the projection onto its plane, when that lies inside,
    or the closest point of one of its three edges: take the minimum over all those candidates.
    """
    p = points.double()[:, None, :]  # (p, 1, 3)
    a, b, c = triangles.double().unbind(1)  # (t, 3) each
    normal = torch.linalg.cross(b - a, c - a)
    unit = normal / normal.norm(dim=-1, keepdim=True)
    height = ((p - a) * unit).sum(-1)  # (p, t)
    foot = p - height[..., None] * unit
    inside = torch.ones_like(height, dtype=torch.bool)
    for x, y in ((a, b), (b, c), (c, a)):
        inside &= (torch.linalg.cross((y - x).expand_as(foot), foot - x) * normal).sum(-1) >= 0
    candidates = [torch.where(inside, height.abs(), torch.full_like(height, math.inf))]
    for x, y in ((a, b), (b, c), (c, a)):
        edge = y - x
        t = (((p - x) * edge).sum(-1) / (edge * edge).sum(-1)).clamp(0, 1)
        candidates.append((p - (x + t[..., None] * edge)).norm(dim=-1))
    return torch.stack(candidates).amin(dim=0)


def naive_fscore(d_pred: torch.Tensor, d_gt: torch.Tensor, threshold: float) -> float:
    precision = sum(float(x) <= threshold for x in d_pred) / len(d_pred)
    recall = sum(float(x) <= threshold for x in d_gt) / len(d_gt)
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def longest_side(mesh: Mesh) -> float:
    lo, hi = mesh.bounds
    return float((hi - lo).max())


# ----------------------------------------------------------------------------- pure functions


def test_chamfer_distances_match_brute_force():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(300, 3, dtype=torch.float64, generator=g)
    b = torch.rand(257, 3, dtype=torch.float64, generator=g) + 0.1
    nn = chamfer_distances(a, b)
    ab, ab_index = naive_nearest(a, b)
    ba, ba_index = naive_nearest(b, a)
    torch.testing.assert_close(nn.a_to_b, ab, rtol=0, atol=1e-12)
    torch.testing.assert_close(nn.b_to_a, ba, rtol=0, atol=1e-12)
    assert torch.equal(nn.a_to_b_index, ab_index) and torch.equal(nn.b_to_a_index, ba_index)
    assert float(nn.l1) == pytest.approx(0.5 * (float(ab.mean()) + float(ba.mean())), rel=1e-12)
    assert float(nn.l2) == pytest.approx(0.5 * (float((ab**2).mean()) + float((ba**2).mean())), rel=1e-12)
    assert float(nn.l2_sum) == pytest.approx(float((ab**2).mean()) + float((ba**2).mean()), rel=1e-12)
    assert float(chamfer_l2_sum(ab, ba)) == pytest.approx(2 * float(chamfer_l2(ab, ba)), rel=1e-12)
    assert float(chamfer_l1(ab, ba)) == pytest.approx(float(nn.l1), rel=1e-12)


def test_chamfer_of_a_set_with_itself_is_zero_and_rejects_empty_sets():
    a = torch.rand(50, 3, dtype=torch.float64)
    assert float(chamfer_distances(a, a).l1) == 0.0
    with pytest.raises(InputError, match="empty"):
        chamfer_distances(a, torch.zeros(0, 3, dtype=torch.float64))
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        chamfer_distances(a, torch.zeros(5, 2, dtype=torch.float64))


@pytest.mark.parametrize("threshold", [0.05, 0.1, 0.2])
def test_fscore_matches_brute_force(threshold):
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(200, 3, dtype=torch.float64, generator=g)
    gt = torch.rand(150, 3, dtype=torch.float64, generator=g) * 1.3
    d_pred, _ = naive_nearest(pred, gt)
    d_gt, _ = naive_nearest(gt, pred)
    nn = chamfer_distances(pred, gt)
    expected = naive_fscore(d_pred, d_gt, threshold)
    assert 0 < expected < 1
    assert float(fscore(nn.a_to_b, nn.b_to_a, threshold)) == pytest.approx(expected, abs=1e-12)


def test_fscore_edge_cases():
    far = torch.full((10,), 1.0, dtype=torch.float64)
    near = torch.zeros(10, dtype=torch.float64)
    assert float(fscore(far, far, 0.5)) == 0.0
    assert float(fscore(near, near, 0.5)) == 1.0
    assert float(fscore(near, far, 0.5)) == 0.0  # perfect precision, zero recall
    with pytest.raises(InputError, match="threshold"):
        fscore(near, near, 0.0)
    assert fscore_key(0.005) == "fscore_0.5%" and fscore_key(0.01) == "fscore_1%"


def test_normal_consistency_matches_brute_force():
    g = torch.Generator().manual_seed(2)
    a = torch.rand(120, 3, dtype=torch.float64, generator=g)
    b = torch.rand(90, 3, dtype=torch.float64, generator=g)
    na = torch.randn(120, 3, dtype=torch.float64, generator=g)
    nb = torch.randn(90, 3, dtype=torch.float64, generator=g)
    nn = chamfer_distances(a, b)
    value = float(normal_consistency(na, nb, nn.a_to_b_index, nn.b_to_a_index))
    _, ab = naive_nearest(a, b)
    _, ba = naive_nearest(b, a)
    cos = lambda u, v: abs(float(u @ v) / float(u.norm() * v.norm()))  # noqa: E731
    expected = 0.5 * (
        sum(cos(na[i], nb[ab[i]]) for i in range(len(a))) / len(a)
        + sum(cos(nb[j], na[ba[j]]) for j in range(len(b))) / len(b)
    )
    assert value == pytest.approx(expected, rel=1e-12)
    # orientation does not matter, and equal normals give 1
    assert float(normal_consistency(-na, nb, nn.a_to_b_index, nn.b_to_a_index)) == pytest.approx(value)
    assert float(normal_consistency(na, na, torch.arange(120), torch.arange(120))) == pytest.approx(1.0)


def test_hausdorff_matches_brute_force():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(80, 3, dtype=torch.float64, generator=g)
    b = torch.rand(70, 3, dtype=torch.float64, generator=g)
    nn = chamfer_distances(a, b)
    d = torch.cdist(a, b)
    expected = max(float(d.min(1).values.max()), float(d.min(0).values.max()))
    assert float(hausdorff(nn.a_to_b, nn.b_to_a)) == pytest.approx(expected, rel=1e-12)


# ----------------------------------------------------------------------------- exact distances


@pytest.mark.parametrize("mesh", [Torus(center=(0.1, 0.0, 0.05)).mesh(sections=12), Box().mesh()])
def test_point_to_mesh_distance_matches_naive_point_to_triangle(mesh):
    g = torch.Generator().manual_seed(4)
    far = (torch.rand(400, 3, dtype=torch.float64, generator=g) - 0.5) * 1.5
    near = cloud_from_mesh(mesh, 200, noise=0.01, seed=5).points
    points = torch.cat([far, near])
    expected = naive_point_to_triangles(points, mesh.vertices[mesh.faces])
    assert expected.max() > 0.2 and expected.min() < 1e-2  # both regimes are covered
    torch.testing.assert_close(point_to_mesh_distance(points, mesh), expected, rtol=0, atol=2e-6)


@pytest.mark.parametrize("mesh", [Torus(center=(0.1, 0.0, 0.05)).mesh(sections=12), Box().mesh()])
def test_closest_faces_match_naive_point_to_triangle(mesh):
    g = torch.Generator().manual_seed(8)
    points = torch.cat([(torch.rand(300, 3, dtype=torch.float64, generator=g) - 0.5) * 1.5,
                        cloud_from_mesh(mesh, 200, noise=0.01, seed=9).points])
    distances = naive_distances_to_each_triangle(points, mesh.vertices[mesh.faces])
    two = distances.topk(2, dim=1, largest=False)
    unique = (two.values[:, 1] - two.values[:, 0]) > 1e-5  # points whose closest face is not a tie
    assert unique.sum() > 100
    assert torch.equal(closest_on_mesh(points, mesh)[1][unique], two.indices[unique, 0])


def test_exact_normal_consistency_of_two_planes_is_the_cosine_of_their_angle():
    square = Mesh(torch.tensor([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]), torch.tensor([[0, 1, 2], [0, 2, 3]]))
    angle = 0.3
    c, s = math.cos(angle), math.sin(angle)
    tilted = Mesh(square.vertices @ torch.tensor([[1.0, 0, 0], [0, c, s], [0, -s, c]]).T, square.faces)
    result = evaluate_samples(tilted, square, cloud_from_mesh(tilted, 500, seed=1), cloud_from_mesh(square, 500, seed=2))
    assert result["normal_consistency_exact"] == pytest.approx(c, abs=1e-6)
    assert result["normal_consistency"] == pytest.approx(c, abs=1e-6)  # flat: every sample has the same normal


def test_evaluate_samples_matches_naive_reference():
    pred = Torus(center=(0.05, 0.0, 0.02), major=0.3, minor=0.12).mesh(sections=12)
    gt = Sphere(radius=0.35).mesh(subdivisions=1)
    pred_samples, gt_samples = cloud_from_mesh(pred, 400, seed=6), cloud_from_mesh(gt, 300, seed=7)
    thresholds = (0.03, 0.1)
    result = evaluate_samples(pred, gt, pred_samples, gt_samples, thresholds)

    p, q = pred_samples.points, gt_samples.points
    ab, ab_index = naive_nearest(p, q)
    ba, ba_index = naive_nearest(q, p)
    exact_pg = naive_point_to_triangles(p, gt.vertices[gt.faces])
    exact_gp = naive_point_to_triangles(q, pred.vertices[pred.faces])
    np_, ng = pred_samples.normals, gt_samples.normals
    expected = {
        "accuracy": float(ab.mean()),
        "completeness": float(ba.mean()),
        "chamfer_l1": 0.5 * float(ab.mean() + ba.mean()),
        "chamfer_l2": 0.5 * float((ab**2).mean() + (ba**2).mean()),
        "chamfer_l2_sum": float((ab**2).mean() + (ba**2).mean()),
        "normal_consistency": 0.5
        * float((np_ * ng[ab_index]).sum(-1).abs().mean() + (ng * np_[ba_index]).sum(-1).abs().mean()),
        "accuracy_exact": float(exact_pg.mean()),
        "completeness_exact": float(exact_gp.mean()),
        "chamfer_l1_exact": 0.5 * float(exact_pg.mean() + exact_gp.mean()),
        "hausdorff": max(float(exact_pg.max()), float(exact_gp.max())),
        # the closest faces themselves are checked against the naive search in their own test (ties aside)
        "normal_consistency_exact": 0.5 * float(
            (np_ * gt.face_normals()[closest_on_mesh(p, gt)[1]]).sum(-1).abs().mean()
            + (ng * pred.face_normals()[closest_on_mesh(q, pred)[1]]).sum(-1).abs().mean()
        ),
    }
    for t in thresholds:
        expected[fscore_key(t)] = naive_fscore(exact_pg, exact_gp, t)
    assert set(result) == set(expected)
    for key, value in expected.items():
        assert result[key] == pytest.approx(value, rel=1e-9, abs=2e-6), key
    assert 0 < expected["fscore_3%"] < expected["fscore_10%"] < 1  # thresholds actually discriminate


# ----------------------------------------------------------------------------- evaluate_mesh: analytic cases

KEYS = {
    "accuracy", "completeness", "chamfer_l1", "chamfer_l2", "chamfer_l2_sum", "normal_consistency", "normal_consistency_exact",
    "accuracy_exact", "completeness_exact", "chamfer_l1_exact", "fscore_0.5%", "fscore_1%", "hausdorff",
    "iou", "pred_watertight", "gt_watertight", "n_vertices", "n_faces",
}  # fmt: skip


def test_identical_meshes_score_perfectly():
    mesh = Sphere(center=(1.0, -2.0, 0.5), radius=2.0).mesh(subdivisions=4)
    result = evaluate_mesh(mesh, mesh, n_samples=20_000)
    assert set(result) == KEYS
    assert result["chamfer_l1_exact"] < 1e-6 and result["hausdorff"] < 1e-6
    assert result["fscore_0.5%"] == 1.0 and result["fscore_1%"] == 1.0
    assert result["iou"] == 1.0 and result["pred_watertight"] == 1.0 and result["gt_watertight"] == 1.0
    assert result["normal_consistency"] > 0.99 and result["normal_consistency_exact"] > 1 - 1e-6
    # the sampled Chamfer has a floor (independent samples), of the order of the sample spacing
    assert 0 < result["chamfer_l1"] < 0.01
    assert result["n_vertices"] == len(mesh.vertices) and result["n_faces"] == len(mesh.faces)


def test_concentric_spheres_have_chamfer_equal_to_the_radius_gap():
    r, d = 0.35, 0.03
    gt, pred = Sphere(radius=r).mesh(subdivisions=4), Sphere(radius=r + d).mesh(subdivisions=4)
    result = evaluate_mesh(pred, gt, n_samples=30_000, thresholds=(0.005, 0.05))
    gap = d / longest_side(gt)  # in gt's normalised frame
    for key in ("accuracy_exact", "completeness_exact", "chamfer_l1_exact", "hausdorff"):
        assert result[key] == pytest.approx(gap, rel=3e-3), key
    # sampled nearest neighbours see the same gap, slightly more (lateral sample spacing)
    assert result["chamfer_l1"] == pytest.approx(gap, rel=2e-2)
    assert result["chamfer_l1"] >= result["chamfer_l1_exact"]
    assert result["chamfer_l2"] == pytest.approx(gap**2, rel=4e-2)
    assert result["chamfer_l2_sum"] == pytest.approx(2 * result["chamfer_l2"], rel=1e-12)
    assert result["fscore_0.5%"] == 0.0 and result["fscore_5%"] == 1.0
    assert result["normal_consistency"] > 0.99
    # nested spheres: IoU is the volume ratio (r / (r + d))^3, up to faceting and Monte Carlo
    assert result["iou"] == pytest.approx((r / (r + d)) ** 3, abs=1e-2)


def test_shifted_sphere_has_hausdorff_equal_to_the_shift_and_chamfer_half_of_it():
    r, d = 0.35, 0.05
    gt = Sphere(radius=r).mesh(subdivisions=5)
    pred = Sphere(center=(d, 0.0, 0.0), radius=r).mesh(subdivisions=5)
    result = evaluate_mesh(pred, gt, n_samples=50_000)
    shift = d / longest_side(gt)
    assert result["hausdorff"] == pytest.approx(shift, rel=3e-3)
    # mean distance of a sphere shifted by d <= r to the original is exactly d / 2:
    # (1 / 2rd) * integral over s in [r-d, r+d] of |s - r| s ds = d / 2
    assert result["chamfer_l1_exact"] == pytest.approx(shift / 2, rel=1e-2)
    assert result["chamfer_l1"] > result["chamfer_l1_exact"]


def test_metrics_live_in_the_ground_truths_normalised_frame():
    pred, gt = Torus(major=0.3, minor=0.1).mesh(sections=48), Sphere(radius=0.35).mesh(subdivisions=3)
    base = evaluate_mesh(pred, gt, n_samples=5_000)
    similarity = torch.eye(4, dtype=torch.float64)
    similarity[:3, :3] *= 7.0
    similarity[:3, 3] = torch.tensor([3.0, -1.0, 2.0])
    moved = evaluate_mesh(pred.transformed(similarity), gt.transformed(similarity), n_samples=5_000)
    for key in KEYS - {"iou"}:
        assert moved[key] == pytest.approx(base[key], rel=1e-5, abs=1e-7), key
    assert moved["iou"] == pytest.approx(base["iou"], abs=1e-3)
    # and the lengths are relative to gt's longest side, not to the world
    assert base["chamfer_l1_exact"] > 0.05  # a torus against a sphere is far from zero


def test_evaluate_mesh_is_deterministic_for_a_fixed_seed():
    pred, gt = Torus(major=0.3, minor=0.1).mesh(sections=32), Box().mesh()
    first, second = evaluate_mesh(pred, gt, n_samples=5_000), evaluate_mesh(pred, gt, n_samples=5_000)
    for key in KEYS:
        assert second[key] == pytest.approx(first[key], rel=0, abs=1e-6), key
    other = evaluate_mesh(pred, gt, n_samples=5_000, seed=1)
    assert other["chamfer_l1"] != first["chamfer_l1"]


# ----------------------------------------------------------------------------- IoU


def test_iou_of_overlapping_boxes_matches_the_overlap_volume():
    a = Box(half_extents=(0.3, 0.2, 0.25))
    b = Box(center=(0.2, 0.1, 0.05), half_extents=(0.3, 0.2, 0.25))
    inter = 0.4 * 0.3 * 0.45
    expected = inter / (a.volume + b.volume - inter)
    assert iou(a.mesh(), b.mesh(), n=100_000) == pytest.approx(expected, abs=1e-2)
    assert evaluate_mesh(b.mesh(), a.mesh(), n_samples=50_000)["iou"] == pytest.approx(expected, abs=1e-2)
    assert iou(a.mesh(), a.mesh(), n=10_000) == 1.0
    far = Box(center=(2.0, 0.0, 0.0))
    assert iou(a.mesh(), far.mesh(), n=10_000) == 0.0


def test_iou_is_nan_when_a_mesh_is_open():
    box = Box().mesh()
    open_box = Mesh(box.vertices, box.faces[1:])
    result = evaluate_mesh(open_box, box, n_samples=5_000)
    assert math.isnan(result["iou"]) and result["pred_watertight"] == 0.0 and result["gt_watertight"] == 1.0
    assert math.isfinite(result["chamfer_l1"])
    assert math.isnan(evaluate_mesh(box, open_box, n_samples=5_000)["iou"])
    with pytest.raises(InputError, match="watertight"):
        iou(open_box, box, n=1_000)


def test_duplicated_vertices_still_count_as_watertight():
    box = Box().mesh()
    soup = Mesh(box.vertices[box.faces].reshape(-1, 3), torch.arange(3 * len(box.faces)).reshape(-1, 3))
    assert soup.is_watertight
    flipped = Mesh(box.vertices, torch.cat([box.faces[:1].flip(-1), box.faces[1:]]))
    assert not flipped.is_watertight  # closed, but one face winds the wrong way
    assert evaluate_mesh(soup, box, n_samples=5_000)["iou"] == 1.0


# ----------------------------------------------------------------------------- bad input


def test_empty_or_degenerate_meshes_raise_input_error():
    gt = Box().mesh()
    empty = Mesh(torch.zeros(4, 3), torch.zeros(0, 3, dtype=torch.int64))
    with pytest.raises(InputError, match="pred mesh is empty"):
        evaluate_mesh(empty, gt, n_samples=100)
    with pytest.raises(InputError, match="gt mesh is empty"):
        evaluate_mesh(gt, empty, n_samples=100)
    flat = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), torch.tensor([[0, 1, 2]]))
    with pytest.raises(InputError, match="zero total area"):
        evaluate_mesh(flat, gt, n_samples=100)
    with pytest.raises(InputError, match="n_samples"):
        evaluate_mesh(gt, gt, n_samples=0)


def test_json_ready_writes_nan_as_null_with_its_reason():
    import json

    metrics = {"iou": math.nan, "chamfer_l1": 0.5, "per_shape": [{"depth_error_mean": float("inf"), "n": 3}],
               "count": torch.tensor(2.0)}
    ready = json_ready(metrics)
    text = json.dumps(ready, allow_nan=False)  # raises on a bare NaN
    assert json.loads(text) == {"iou": None, "chamfer_l1": 0.5, "per_shape": [{"depth_error_mean": None, "n": 3}],
                                "count": 2.0, "undefined": ready["undefined"]}
    assert "watertight" in ready["undefined"]["iou"] and "held-out" in ready["undefined"]["depth_error_mean"]
    assert json_ready({"a": 1.0}) == {"a": 1.0}  # nothing undefined: no extra key


def test_box_overlap_is_one_for_nested_boxes_and_zero_for_boxes_apart():
    box = Box(half_extents=(0.3, 0.2, 0.25)).mesh()

    def moved(mesh, shift):
        return Mesh(mesh.vertices + torch.tensor(shift, dtype=mesh.vertices.dtype), mesh.faces)

    assert box_overlap(box, Box(half_extents=(0.1, 0.1, 0.1)).mesh()) == pytest.approx(1.0)
    assert box_overlap(box, moved(box, [0.3, 0.0, 0.0])) == pytest.approx(0.5)  # half of x shared
    assert box_overlap(box, moved(box, [2.0, 0.0, 0.0])) == 0.0


def test_faces_beyond_multinomials_limit_are_drawn_in_proportion_to_their_area(monkeypatch):
    """A mesh with more faces than torch.multinomial takes (a 1,024^3 extraction subdivided) is sampled by the
    areas' cumulative sum: each face in proportion to its area, a face of no area never."""
    from neuralsurf import geometry

    areas = torch.tensor([1.0, 0.0, 3.0, 4.0], dtype=torch.float64)
    monkeypatch.setattr(geometry, "MULTINOMIAL_CATEGORIES", 3)
    faces = geometry.area_weighted_faces(areas, 80_000, torch.Generator().manual_seed(0))
    share = faces.bincount(minlength=4).double() / len(faces)
    assert torch.allclose(share, areas / areas.sum(), atol=0.01) and share[1] == 0
    square = Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2], [0, 2, 3]]))
    monkeypatch.setattr(geometry, "MULTINOMIAL_CATEGORIES", 1)
    points, normals = geometry.sample_mesh_surface(square, 20_000, torch.Generator().manual_seed(1))
    assert points[:, 2].abs().max() == 0 and abs(float(points[:, 0].mean()) - 0.5) < 0.01
    assert torch.allclose(normals, torch.tensor([0.0, 0, 1]).expand_as(normals))
