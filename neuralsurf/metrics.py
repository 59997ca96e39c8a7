"""Mesh-versus-mesh metrics: Chamfer (both published definitions), F-score, normal consistency,
Hausdorff and volumetric IoU.

The building blocks are small pure functions on tensors. `evaluate_mesh` composes them and works in
one stated frame: the ground truth's normalised frame (its bounding box centred, longest side 1, see
`Normalization.from_points`), so every length it reports is a fraction of the ground truth's
longest side.

Conventions and where they come from:

- Occupancy Networks (Mescheder et al. 2019, `im2mesh/eval.py`): accuracy and completeness are mean
  nearest-neighbour Euclidean distances between n surface samples of each mesh; Chamfer-L1 is their
  mean, Chamfer-L2 the mean of the two mean squared distances, normal consistency the mean |cos| of
  the face normals at nearest neighbours, averaged both ways.
- DeepSDF / pytorch3d `chamfer_distance`: the *sum* of the two mean squared distances
  (`chamfer_l2_sum`, twice OccNet's Chamfer-L2).
- F-score (Tatarchenko et al. 2019): harmonic mean of precision (share of prediction within the
  threshold of the ground truth) and recall (share of ground truth within the threshold of the
  prediction).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.cameras import render_depth
from neuralsurf.errors import InputError
from neuralsurf.geometry import closest_on_mesh, knn, mesh_contains, sample_mesh_surface
from neuralsurf.structures import Mesh, Normalization, PointCloud

__all__ = [
    "NearestNeighbours",
    "RelativePoseError",
    "absolute_trajectory_error",
    "align_trajectory",
    "box_overlap",
    "chamfer_distances",
    "chamfer_l1",
    "chamfer_l2",
    "chamfer_l2_sum",
    "depth_metrics",
    "evaluate_mesh",
    "evaluate_samples",
    "fscore",
    "fscore_key",
    "hausdorff",
    "iou",
    "json_ready",
    "normal_consistency",
    "relative_pose_error",
]


# ----------------------------------------------------------------------------- nearest neighbours


@dataclass(frozen=True)
class NearestNeighbours:
    """Nearest neighbours between two point sets, both ways."""

    a_to_b: Tensor
    """Float[Tensor, "n"]: Euclidean distance from each point of a to its nearest point of b."""
    b_to_a: Tensor
    """Float[Tensor, "m"]: Euclidean distance from each point of b to its nearest point of a."""
    a_to_b_index: Tensor
    """Int[Tensor, "n"]: index into b of each a point's nearest neighbour."""
    b_to_a_index: Tensor
    """Int[Tensor, "m"]: index into a of each b point's nearest neighbour."""

    @property
    def l1(self) -> Tensor:
        """OccNet Chamfer-L1 (see `chamfer_l1`)."""
        return chamfer_l1(self.a_to_b, self.b_to_a)

    @property
    def l2(self) -> Tensor:
        """OccNet Chamfer-L2 (see `chamfer_l2`)."""
        return chamfer_l2(self.a_to_b, self.b_to_a)

    @property
    def l2_sum(self) -> Tensor:
        """DeepSDF / pytorch3d Chamfer (see `chamfer_l2_sum`)."""
        return chamfer_l2_sum(self.a_to_b, self.b_to_a)


def _check_points(points: Tensor, name: str) -> None:
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"{name} must have shape (n, 3), got {tuple(points.shape)}")
    if len(points) == 0:
        raise InputError(f"{name} is empty; metrics need at least one point on each side")


def chamfer_distances(a_points: Tensor, b_points: Tensor) -> NearestNeighbours:
    """Exact nearest neighbours from a to b and from b to a (k-d tree).

    Args:
        a_points: Float[Tensor, "n 3"].
        b_points: Float[Tensor, "m 3"], same frame.
    Returns:
        `NearestNeighbours` with per-point distances (a_points' dtype) and indices; its `l1`, `l2`
        and `l2_sum` give the Chamfer distances.
    """
    _check_points(a_points, "a_points")
    _check_points(b_points, "b_points")
    a_to_b, a_index = knn(a_points, b_points, 1)
    b_to_a, b_index = knn(b_points, a_points, 1)
    return NearestNeighbours(a_to_b[:, 0], b_to_a[:, 0].to(a_to_b), a_index[:, 0], b_index[:, 0])


def chamfer_l1(a_to_b: Tensor, b_to_a: Tensor) -> Tensor:
    """OccNet Chamfer-L1: `0.5 * (mean(a_to_b) + mean(b_to_a))` of (unsquared) Euclidean distances.

    Args:
        a_to_b: Float[Tensor, "n"]; b_to_a: Float[Tensor, "m"], non-negative distances.
    Returns:
        Float[Tensor, ""].
    """
    return 0.5 * (a_to_b.mean() + b_to_a.mean())


def chamfer_l2(a_to_b: Tensor, b_to_a: Tensor) -> Tensor:
    """OccNet Chamfer-L2: `0.5 * (mean(a_to_b**2) + mean(b_to_a**2))`.

    Args:
        a_to_b: Float[Tensor, "n"]; b_to_a: Float[Tensor, "m"], non-negative distances.
    Returns:
        Float[Tensor, ""].
    """
    return 0.5 * (a_to_b.square().mean() + b_to_a.square().mean())


def chamfer_l2_sum(a_to_b: Tensor, b_to_a: Tensor) -> Tensor:
    """DeepSDF / pytorch3d Chamfer: `mean(a_to_b**2) + mean(b_to_a**2)` (twice `chamfer_l2`).

    Args:
        a_to_b: Float[Tensor, "n"]; b_to_a: Float[Tensor, "m"], non-negative distances.
    Returns:
        Float[Tensor, ""].
    """
    return a_to_b.square().mean() + b_to_a.square().mean()


# ----------------------------------------------------------------------------- other metrics


def fscore(dist_pred_to_gt: Tensor, dist_gt_to_pred: Tensor, threshold: float) -> Tensor:
    """F-score at `threshold`: `2 P R / (P + R)`, 0 when both are 0.

    Precision P is the share of `dist_pred_to_gt <= threshold`, recall R the share of
    `dist_gt_to_pred <= threshold` (`<=` as in the Convolutional Occupancy Networks code).

    Args:
        dist_pred_to_gt: Float[Tensor, "n"], distance of each prediction sample to the ground truth.
        dist_gt_to_pred: Float[Tensor, "m"], distance of each ground-truth sample to the prediction.
        threshold: distance, in the distances' units, > 0.
    Returns:
        Float[Tensor, ""] in [0, 1].
    """
    if not threshold > 0:
        raise InputError(f"fscore threshold must be > 0, got {threshold}")
    precision = (dist_pred_to_gt <= threshold).to(dist_pred_to_gt.dtype).mean()
    recall = (dist_gt_to_pred <= threshold).to(dist_pred_to_gt.dtype).mean()
    total = precision + recall
    return torch.where(total > 0, 2 * precision * recall / total.clamp(min=1e-300), torch.zeros_like(total))


def fscore_key(threshold: float) -> str:
    """The result key of an F-score threshold given as a fraction: 0.005 -> "fscore_0.5%"."""
    return f"fscore_{100 * threshold:g}%"


def normal_consistency(
    a_normals: Tensor, b_normals: Tensor, a_to_b_index: Tensor, b_to_a_index: Tensor
) -> Tensor:
    """OccNet normal consistency: mean |cos| between normals at nearest neighbours, both ways.

    `0.5 * (mean_i |n_a[i] . n_b[a_to_b_index[i]]| + mean_j |n_b[j] . n_a[b_to_a_index[j]]|)`,
    normals normalised first (orientation does not matter). 1 for perfect agreement.

    Args:
        a_normals: Float[Tensor, "n 3"]; b_normals: Float[Tensor, "m 3"].
        a_to_b_index: Int[Tensor, "n"] into b; b_to_a_index: Int[Tensor, "m"] into a.
    Returns:
        Float[Tensor, ""] in [0, 1].
    """
    b_normals = b_normals.to(a_normals)
    a_side = mean_abs_cosine(a_normals, b_normals[a_to_b_index])
    return 0.5 * (a_side + mean_abs_cosine(b_normals, a_normals[b_to_a_index]))


def mean_abs_cosine(a: Tensor, b: Tensor) -> Tensor:
    """Mean |cos| of the angles between paired directions (normalised first; orientation does not
    matter). a, b: Float[Tensor, "n 3"]. Returns Float[Tensor, ""] in [0, 1]."""
    a = torch.nn.functional.normalize(a, dim=-1)
    return (a * torch.nn.functional.normalize(b.to(a), dim=-1)).sum(-1).abs().mean()


def hausdorff(dist_pred_to_gt: Tensor, dist_gt_to_pred: Tensor) -> Tensor:
    """Symmetric Hausdorff distance: the larger of the two directed maxima.

    Args:
        dist_pred_to_gt: Float[Tensor, "n"]; dist_gt_to_pred: Float[Tensor, "m"].
    Returns:
        Float[Tensor, ""].
    """
    return torch.maximum(dist_pred_to_gt.max(), dist_gt_to_pred.max().to(dist_pred_to_gt))


def _volume_iou(pred: Mesh, gt: Mesh, n: int, seed: int) -> float:
    vertices = torch.cat([pred.vertices.detach().cpu().double(), gt.vertices.detach().cpu().double()])
    lo, hi = vertices.min(0).values, vertices.max(0).values
    generator = torch.Generator().manual_seed(seed)
    points = lo + (hi - lo) * torch.rand(n, 3, dtype=torch.float64, generator=generator)
    inside_pred = mesh_contains(points, pred)
    inside_gt = mesh_contains(points, gt)
    union = int((inside_pred | inside_gt).sum())
    if union == 0:
        raise InputError(
            f"none of the {n} IoU samples lies inside either mesh; the meshes enclose no volume "
            f"(flat or degenerate) or n={n} is too small"
        )
    return int((inside_pred & inside_gt).sum()) / union


def iou(pred: Mesh, gt: Mesh, n: int = 100_000, seed: int = 0) -> float:
    """Volumetric IoU |pred ∩ gt| / |pred ∪ gt| of two watertight meshes, by Monte Carlo.

    `n` points uniform in the union of the two bounding boxes' bounding box are classified by ray
    parity (`geometry.mesh_contains`); the ratio of counts estimates the ratio of volumes (standard
    error about sqrt(IoU (1 - IoU) / n_union)). Frame-invariant; deterministic for a fixed `seed`.

    Raises:
        InputError: a mesh is empty or not watertight (`Mesh.is_watertight`), or no sample is inside.
    """
    if n < 1:
        raise InputError(f"iou needs n >= 1 samples, got {n}")
    for name, mesh in (("pred", pred), ("gt", gt)):
        if not mesh.is_watertight:
            raise InputError(
                f"iou needs watertight meshes, but {name} is {'empty' if mesh.is_empty else 'open'}; "
                f"close it (e.g. trimesh.repair.fill_holes) or skip IoU"
            )
    return _volume_iou(pred, gt, n, seed)


# ----------------------------------------------------------------------------- entry points


def _check_mesh(mesh: Mesh, name: str) -> None:
    if mesh.is_empty:
        raise InputError(
            f"{name} mesh is empty ({len(mesh.vertices)} vertices, no faces); there is no surface to "
            f"evaluate. Decide in the caller what an empty reconstruction scores (e.g. skip or inf)"
        )
    if not float(mesh.face_areas().double().sum()) > 0:
        raise InputError(f"{name} mesh has {len(mesh.faces)} faces but zero total area; all are degenerate")


def evaluate_samples(
    pred: Mesh,
    gt: Mesh,
    pred_samples: PointCloud,
    gt_samples: PointCloud,
    thresholds: Sequence[float] = (0.005, 0.01),
) -> dict[str, float]:
    """Every sample-based metric of `evaluate_mesh`, from given surface samples, in their frame.

    No normalisation happens here: meshes and samples must share one frame and distances are in
    its units. Use it to evaluate against precomputed ground-truth samples (as OccNet does).

    Args:
        pred, gt: non-empty meshes.
        pred_samples: points on pred's surface with their normals (n >= 1).
        gt_samples: points on gt's surface with their normals (m >= 1).
        thresholds: F-score distances.
    Returns:
        the keys accuracy, completeness, chamfer_l1, chamfer_l2, chamfer_l2_sum, normal_consistency,
        normal_consistency_exact, accuracy_exact, completeness_exact, chamfer_l1_exact, hausdorff and one fscore key per
        threshold (see `evaluate_mesh`).
    """
    _check_mesh(pred, "pred")
    _check_mesh(gt, "gt")
    for name, samples in (("pred_samples", pred_samples), ("gt_samples", gt_samples)):
        if not samples.has_normals:
            raise InputError(f"{name} need normals for normal consistency; sample with normals")
    pred_points, gt_points = pred_samples.points.double(), gt_samples.points.double()
    nn = chamfer_distances(pred_points, gt_points)
    pred_to_gt, gt_faces = closest_on_mesh(pred_points, gt)
    gt_to_pred, pred_faces = closest_on_mesh(gt_points, pred)
    pred_normals, gt_normals = pred_samples.normals.double(), gt_samples.normals.double()
    # sample-free normal consistency: each sample's normal against the other mesh's face at its closest point
    exact_consistency = 0.5 * (mean_abs_cosine(pred_normals, gt.face_normals().double()[gt_faces])
                               + mean_abs_cosine(gt_normals, pred.face_normals().double()[pred_faces]))
    metrics = {
        "accuracy": nn.a_to_b.mean(),
        "completeness": nn.b_to_a.mean(),
        "chamfer_l1": nn.l1,
        "chamfer_l2": nn.l2,
        "chamfer_l2_sum": nn.l2_sum,
        "normal_consistency": normal_consistency(pred_normals, gt_normals, nn.a_to_b_index, nn.b_to_a_index),
        "normal_consistency_exact": exact_consistency,
        "accuracy_exact": pred_to_gt.mean(),
        "completeness_exact": gt_to_pred.mean(),
        "chamfer_l1_exact": chamfer_l1(pred_to_gt, gt_to_pred),
        "hausdorff": hausdorff(pred_to_gt, gt_to_pred),
    }
    for threshold in thresholds:
        metrics[fscore_key(threshold)] = fscore(pred_to_gt, gt_to_pred, threshold)
    return {key: float(value) for key, value in metrics.items()}


def evaluate_mesh(
    pred: Mesh,
    gt: Mesh,
    n_samples: int = 100_000,
    seed: int = 0,
    thresholds: Sequence[float] = (0.005, 0.01),
) -> dict[str, float]:
    """Compare a reconstructed mesh with the ground truth, in the ground truth's normalised frame.

    Both meshes are mapped by `Normalization.from_points(gt.vertices)` (gt's bounding box centred,
    longest side 1), so every distance below is a fraction of gt's longest side. Each mesh gets
    `n_samples` area-uniform surface samples with their face normals (gt from seed `seed`, pred from
    `seed + 1`, so a fixed gt is sampled identically for every prediction). Deterministic for a
    fixed seed.

    Returns:
        A dict of floats:

        - ``accuracy``: mean distance from each pred sample to its nearest gt sample (OccNet).
        - ``completeness``: mean distance from each gt sample to its nearest pred sample (OccNet).
        - ``chamfer_l1``: OccNet Chamfer-L1, ``0.5 * (accuracy + completeness)``. Has a sampling
          floor: about 0.003 for identical unit-size meshes at 100k samples.
        - ``chamfer_l2``: OccNet Chamfer-L2, 0.5 * (mean squared NN distance pred->gt + gt->pred).
        - ``chamfer_l2_sum``: DeepSDF / pytorch3d Chamfer, the *sum* of the two mean squared NN
          distances (= 2 * chamfer_l2).
        - ``normal_consistency``: OccNet, mean |cos| between the face normals of nearest-neighbour
          samples, averaged over both directions; 1 is best. Has a sampling floor: 0.9960 for the
          bunny against itself at 100k samples.
        - ``normal_consistency_exact``: the same with each sample's normal compared to the other
          mesh's face normal at the sample's closest point on it (no sampling floor: 1 for identical
          meshes, cos(a) for planes a apart in angle).
        - ``accuracy_exact``: mean exact distance from pred samples to gt's triangles.
        - ``completeness_exact``: mean exact distance from gt samples to pred's triangles.
        - ``chamfer_l1_exact``: ``0.5 * (accuracy_exact + completeness_exact)``; no sampling floor
          (0 for identical meshes, d for concentric spheres d apart).
        - ``fscore_<t>%`` for each threshold t in `thresholds` (fraction of gt's longest side,
          printed in percent: 0.005 -> ``fscore_0.5%``, 0.01 -> ``fscore_1%``): F-score from the
          exact distances above, i.e. the share of pred's area within t of gt and of gt's area
          within t of pred (the many-sample limit of Tatarchenko et al.; the sampled
          nearest-neighbour version would score identical meshes ~0.92 at 0.5% with 100k samples).
        - ``hausdorff``: max over both sample sets of the exact distance to the other mesh.
        - ``iou``: volumetric IoU from `n_samples` points in the union bounding box (`iou`), only
          when both meshes are watertight (`Mesh.is_watertight`); otherwise NaN.
        - ``pred_watertight``, ``gt_watertight``: 1.0 or 0.0 (why ``iou`` may be NaN).
        - ``n_vertices``, ``n_faces``: size of pred.

    Raises:
        InputError: pred or gt is empty (no faces) or has zero area; the caller decides what an
            empty reconstruction scores. Also for n_samples < 1 or a non-positive threshold.
    """
    if n_samples < 1:
        raise InputError(f"n_samples must be >= 1, got {n_samples}")
    _check_mesh(pred, "pred")
    _check_mesh(gt, "gt")
    norm = Normalization.from_points(gt.vertices)
    pred_unit = norm.mesh_to_unit(Mesh(pred.vertices.detach().cpu().double(), pred.faces.cpu()))
    gt_unit = norm.mesh_to_unit(Mesh(gt.vertices.detach().cpu().double(), gt.faces.cpu()))
    gt_samples = PointCloud(*sample_mesh_surface(gt_unit, n_samples, torch.Generator().manual_seed(seed)))
    pred_samples = PointCloud(
        *sample_mesh_surface(pred_unit, n_samples, torch.Generator().manual_seed(seed + 1))
    )
    metrics = evaluate_samples(pred_unit, gt_unit, pred_samples, gt_samples, thresholds)
    pred_watertight, gt_watertight = pred_unit.is_watertight, gt_unit.is_watertight
    both_closed = pred_watertight and gt_watertight
    metrics["iou"] = _volume_iou(pred_unit, gt_unit, n_samples, seed + 2) if both_closed else math.nan
    metrics["pred_watertight"] = float(pred_watertight)
    metrics["gt_watertight"] = float(gt_watertight)
    metrics["n_vertices"] = float(len(pred.vertices))
    metrics["n_faces"] = float(len(pred.faces))
    return metrics


def watertight(mesh: Mesh, metrics: dict[str, float]) -> bool:
    """Whether `mesh` is watertight: read from its `evaluate_mesh` `metrics` where they hold it
    (`pred_watertight`), else `Mesh.is_watertight` (each takes about 0.5 s on a 1.5M-face mesh)."""
    return bool(metrics["pred_watertight"]) if "pred_watertight" in metrics else mesh.is_watertight


DEPTH_THRESHOLDS = (0.01, 0.02, 0.05)
"""Metres within which a rendered held-out depth agrees with the reading (precision, recall, F-score)."""


def held_out_errors(mesh: Mesh, frames) -> Tensor:
    """Float[Tensor, "n h w"]: rendered - measured z-depth (metres) of `mesh` ray-cast from held-out `frames`
    (DepthFrames), NaN where the frame has no reading or the mesh shows nothing; negative where the mesh stands
    in front of the reading."""
    measured = frames.depth.cpu()
    rendered, _ = render_depth(mesh, frames.K.cpu(), frames.cam_to_world.cpu(), frames.width, frames.height)
    seen = (measured > 0) & (rendered > 0)
    return torch.where(seen, rendered - measured, torch.full_like(measured, math.nan))


def depth_metrics(mesh: Mesh, frames, threshold: float = 0.05, errors: Tensor | None = None) -> dict[str, float]:
    """Scores that need no ground-truth mesh: the reconstruction ray-cast from held-out depth frames.

    Args:
        mesh: the reconstruction (world frame); frames: DepthFrames held out from fitting;
        threshold: metres within which a held-out reading counts as covered; errors: `held_out_errors(mesh,
        frames)` when already computed.
    Returns:
        depth_error_mean / depth_error_median: |rendered - measured| z-depth (metres) over the held-out
        valid pixels where the reconstruction is seen; depth_error_front / depth_error_behind: the parts of
        that mean from pixels where the mesh stands in front of / behind the reading (they sum to it);
        depth_completeness: the fraction of held-out valid pixels whose rendered depth lies within
        `threshold` of the reading; for t of DEPTH_THRESHOLDS, depth_precision_<t> (the share of the seen
        pixels within t), depth_recall_<t> (the share of the valid pixels within t) and depth_fscore_<t>.
    """
    errors = held_out_errors(mesh, frames) if errors is None else errors
    valid = int((frames.depth > 0).sum())
    signed = errors[torch.isfinite(errors)]
    error = signed.abs()
    n = len(error)
    metrics = {
        "depth_error_mean": float(error.mean()) if n else math.nan,
        "depth_error_median": float(error.median()) if n else math.nan,
        "depth_error_front": float(error[signed < 0].sum() / n) if n else math.nan,
        "depth_error_behind": float(error[signed > 0].sum() / n) if n else math.nan,
        "depth_completeness": float((error < threshold).sum() / max(valid, 1)),
    }
    for t in DEPTH_THRESHOLDS:
        name = f"{round(100 * t)}cm"
        within = int((error < t).sum())
        precision, recall = within / max(n, 1), within / max(valid, 1)
        metrics[f"depth_precision_{name}"], metrics[f"depth_recall_{name}"] = precision, recall
        metrics[f"depth_fscore_{name}"] = 2 * precision * recall / (precision + recall) if within else 0.0
    return metrics


def common_pixel_errors(errors: dict[str, Tensor]) -> dict[str, float]:
    """The mean |error| of each entry of `errors` (name -> `held_out_errors` of one scene's held-out frames, one
    shape) over the pixels that every entry shows: no mesh is punished for covering more than another."""
    shapes = {tuple(e.shape) for e in errors.values()}
    if len(shapes) > 1:
        raise InputError(f"common_pixel_errors needs error maps of one shape (one scene's held-out frames), got {shapes}")
    common = torch.stack([torch.isfinite(e) for e in errors.values()]).all(0) if errors else None
    return {name: float(e[common].abs().mean()) if common.any() else math.nan for name, e in errors.items()}


def box_overlap(a: Mesh, b: Mesh) -> float:
    """How much the bounding boxes of two meshes overlap: the product over the axes of the length of
    their common interval over the shorter of the two intervals (1 when one box holds the other, 0 when
    they are apart). Meshes in different frames or units score near 0."""
    share = 1.0
    for lo_a, hi_a, lo_b, hi_b in zip(*a.vertices.double().aminmax(dim=0), *b.vertices.double().aminmax(dim=0)):
        shorter = min(float(hi_a - lo_a), float(hi_b - lo_b))
        common = max(0.0, min(float(hi_a), float(hi_b)) - max(float(lo_a), float(lo_b)))
        longest = max(float(hi_a), float(hi_b)) - min(float(lo_a), float(lo_b))
        if shorter > 1e-9 * max(longest, 1e-30):  # a flat axis: its intervals touch or they do not
            share *= min(common / shorter, 1.0)
        elif common == 0.0 and longest > 0.0:
            return 0.0
    return share


UNDEFINED_REASONS = {
    "iou": "volumetric IoU needs two watertight meshes (see pred_watertight, gt_watertight)",
    "depth_error_mean": "the mesh is seen at no valid pixel of the held-out frames",
    "depth_error_median": "the mesh is seen at no valid pixel of the held-out frames",
}
"""Why a metric of `evaluate_mesh` or `depth_metrics` can be NaN."""


def json_ready(metrics: dict) -> dict:
    """`metrics` with only valid JSON numbers: each NaN or infinite float becomes None and its name
    is listed with the reason under "undefined" ({name: reason}); nested dicts and lists likewise."""
    undefined: dict[str, str] = {}

    def clean(value, name: str):
        if isinstance(value, dict):
            return {key: clean(item, key) for key, item in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(item, name) for item in value]
        if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # a numpy or torch scalar
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            undefined[name] = UNDEFINED_REASONS.get(name, f"not a finite number ({value})")
            return None
        return value

    cleaned = clean(dict(metrics), "")
    return {**cleaned, "undefined": undefined} if undefined else cleaned


# ----------------------------------------------------------------------------- camera trajectories
#
# As the TUM RGB-D benchmark defines them (Sturm et al. 2012, evaluate_ate.py / evaluate_rpe.py).


def _check_trajectories(estimated: Tensor, reference: Tensor) -> tuple[Tensor, Tensor]:
    estimated, reference = torch.as_tensor(estimated).double().cpu(), torch.as_tensor(reference).double().cpu()
    if estimated.ndim != 3 or estimated.shape[1:] != (4, 4) or estimated.shape != reference.shape:
        raise InputError(f"trajectories are (n, 4, 4) camera-to-world poses of the same frames, got "
                         f"{tuple(estimated.shape)} and {tuple(reference.shape)}")
    if len(estimated) < 2 or not (torch.isfinite(estimated).all() and torch.isfinite(reference).all()):
        raise InputError(f"trajectories need at least 2 finite poses, got {len(estimated)}")
    return estimated, reference


def align_trajectory(estimated: Tensor, reference: Tensor) -> Tensor:
    """Float64[Tensor, "4 4"]: the rigid motion S minimising sum_i |S c_i - d_i|^2 between the camera
    centres c_i of `estimated` and d_i of `reference` (Float[Tensor, "n 4 4"] each; Horn / Umeyama
    without scale, reflections excluded)."""
    estimated, reference = _check_trajectories(estimated, reference)
    c, d = estimated[:, :3, 3], reference[:, :3, 3]
    mu_c, mu_d = c.mean(0), d.mean(0)
    u, _, vt = torch.linalg.svd((d - mu_d).T @ (c - mu_c))
    sign = torch.ones(3, dtype=torch.float64)
    sign[2] = torch.sign(torch.linalg.det(u @ vt)) or 1.0
    rotation = u @ torch.diag(sign) @ vt
    transform = torch.eye(4, dtype=torch.float64)
    transform[:3, :3], transform[:3, 3] = rotation, mu_d - rotation @ mu_c
    return transform


def absolute_trajectory_error(estimated: Tensor, reference: Tensor) -> float:
    """ATE (metres): RMSE of the camera centres of `estimated` after `align_trajectory` onto `reference`
    (Float[Tensor, "n 4 4"] camera-to-world each, frame i of one matching frame i of the other)."""
    estimated, reference = _check_trajectories(estimated, reference)
    aligned = align_trajectory(estimated, reference) @ estimated
    return float((aligned[:, :3, 3] - reference[:, :3, 3]).norm(dim=1).square().mean().sqrt())


@dataclass(frozen=True)
class RelativePoseError:
    """Drift over a fixed number of frames (TUM's RPE), as RMSEs over the frame pairs."""

    translation: float
    """Metres: RMSE of |translation of E_i|, E_i = (Q_i^-1 Q_i+d)^-1 (P_i^-1 P_i+d)."""
    rotation: float
    """Degrees: RMSE of the rotation angle of E_i."""


def relative_pose_error(estimated: Tensor, reference: Tensor, delta: int = 1) -> RelativePoseError:
    """RPE of `estimated` poses P against `reference` poses Q (Float[Tensor, "n 4 4"] camera-to-world each)
    over pairs of frames `delta` apart: per frame for delta=1, per second for delta = the frame rate."""
    estimated, reference = _check_trajectories(estimated, reference)
    if not (isinstance(delta, int) and 1 <= delta < len(estimated)):
        raise InputError(f"delta must be a frame count from 1 to {len(estimated) - 1}, got {delta!r}")
    motion = lambda poses: torch.linalg.inv(poses[:-delta]) @ poses[delta:]
    error = torch.linalg.inv(motion(reference)) @ motion(estimated)
    cosine = ((error[:, :3, :3].diagonal(dim1=1, dim2=2).sum(1) - 1) / 2).clamp(-1, 1)
    return RelativePoseError(
        float(error[:, :3, 3].norm(dim=1).square().mean().sqrt()),
        float(torch.rad2deg(torch.arccos(cosine)).square().mean().sqrt()),
    )
