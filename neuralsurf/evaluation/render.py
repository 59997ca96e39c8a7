"""Headless renders and charts, in numpy + PIL: meshes ray-cast with Open3D's RaycastingScene
(no OpenGL, no display), Lambert shading of one colour or of the mesh's vertex colours, or a colour
ramp of the distance to the ground truth; viridis without matplotlib; bar charts and scatter plots
drawn with PIL (matplotlib is not a dependency)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from neuralsurf.errors import InputError
from neuralsurf.models import AutoDecoder, LatentConditioned
from neuralsurf.priors import EXTRACTION_BOUNDS, extract_unit
from neuralsurf.structures import Mesh

BACKGROUND = (255, 255, 255)
PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127)]


def default_view(bounds: np.ndarray, azimuth_deg: float = 35.0, elevation_deg: float = 20.0,
                 up=(0.0, 1.0, 0.0), distance: float = 2.2) -> dict:
    """A camera looking at the centre of `bounds` (2, 3) from the given angles (y up)."""
    bounds = np.asarray(bounds, dtype=np.float64)
    center = bounds.mean(0)
    radius = float(np.linalg.norm(bounds[1] - bounds[0])) / 2
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return {"center": center, "eye": center + distance * radius * direction, "up": np.asarray(up, float)}


def raycast(mesh: Mesh, view: dict, width: int = 320, height: int = 320, fov_deg: float = 40.0):
    """Cast one ray per pixel: (hit mask (h, w), world hit points (h, w, 3), unit normals (h, w, 3)
    facing the camera, unit ray directions (h, w, 3))."""
    return _cast(mesh, view, width, height, fov_deg)[:4]


def _cast(mesh: Mesh, view: dict, width: int, height: int, fov_deg: float = 40.0):
    """`raycast`'s four arrays, then the hit face of each pixel (h, w) int64 (0 where nothing is hit)
    and its barycentric coordinates (h, w, 3) (weights of the face's three corners)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.detach().cpu().numpy().astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.cpu().numpy().astype(np.uint32)))
    # Open3D's pinhole rays put `up` towards the last image row: pass -up for an upright image
    rays = scene.create_rays_pinhole(fov_deg, view["center"].tolist(), view["eye"].tolist(),
                                     (-np.asarray(view["up"], float)).tolist(), width, height)
    answer = scene.cast_rays(rays)
    t = answer["t_hit"].numpy()
    hit = np.isfinite(t)
    rays_np = rays.numpy()
    points = rays_np[..., :3] + rays_np[..., 3:] * np.where(hit, t, 0.0)[..., None]
    normals = answer["primitive_normals"].numpy()
    direction = rays_np[..., 3:] / np.linalg.norm(rays_np[..., 3:], axis=-1, keepdims=True)
    # two-sided: face the normal towards the camera (open meshes show their inside)
    normals = np.where((normals * direction).sum(-1, keepdims=True) > 0, -normals, normals)
    faces = np.where(hit, answer["primitive_ids"].numpy().astype(np.int64), 0)
    u, v = np.moveaxis(answer["primitive_uvs"].numpy().astype(np.float64), -1, 0)
    return hit, points, normals, direction, faces, np.stack([1 - u - v, u, v], axis=-1)


def shade(mesh: Mesh, view: dict, width: int = 320, height: int = 320, color=(0.75, 0.78, 0.85), *,
          vertex_colors: bool = False, ambient: float = 0.2) -> np.ndarray:
    """Lambert-shaded image (h, w, 3) uint8 with a head light; white background.

    The surface has `color` (RGB in [0, 1]), or with `vertex_colors` the mesh's own vertex colours
    interpolated across each face. Brightness is ambient + (1 - ambient) * cos(angle to the camera).
    """
    hit, _, normals, direction, faces, weights = _cast(mesh, view, width, height)
    lambert = np.clip(-(normals * direction).sum(-1), 0.0, 1.0)
    intensity = (ambient + (1 - ambient) * lambert)[..., None]
    if vertex_colors:
        if mesh.vertex_colors is None:
            raise InputError("shade(vertex_colors=True) needs a mesh with vertex colours; pass color=... instead")
        corners = mesh.vertex_colors.detach().cpu().double().numpy()[mesh.faces.cpu().numpy()[faces]]
        surface = (weights[..., None] * corners).sum(-2)  # (h, w, 3)
    else:
        surface = np.asarray(color, dtype=np.float64)
    image = np.where(hit[..., None], intensity * surface, 1.0)
    return (np.clip(image, 0, 1) * 255).astype(np.uint8)


def points_image(points: np.ndarray, view: dict, width: int = 320, height: int = 320,
                 fov_deg: float = 40.0) -> np.ndarray:
    """Points (n, 3) seen from `view` as `raycast`'s pinhole camera sees them: 2x2-pixel dots, darker
    nearer, on white; (h, w, 3) uint8 (a method's input beside its meshes)."""
    eye, center = np.asarray(view["eye"], float), np.asarray(view["center"], float)
    forward = (center - eye) / np.linalg.norm(center - eye)
    right = np.cross(forward, np.asarray(view["up"], float))
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = np.asarray(points, float) - eye
    z = relative @ forward
    ahead = z > 1e-9
    focal = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    u = np.round(0.5 * width + focal * (relative[ahead] @ right) / z[ahead]).astype(int)
    v = np.round(0.5 * height - focal * (relative[ahead] @ up) / z[ahead]).astype(int)
    depth = z[ahead]
    grey = (40 + 150 * (depth - depth.min()) / max(float(np.ptp(depth)), 1e-12)).astype(np.uint8) if len(depth) \
        else depth.astype(np.uint8)
    image = np.full((height, width, 3), 255, np.uint8)
    order = np.argsort(-depth)  # far first: the nearer dots are written last and stay on top
    for dv in (0, 1):
        for du in (0, 1):
            row, column = v[order] + dv, u[order] + du
            inside = (row >= 0) & (row < height) & (column >= 0) & (column < width)
            image[row[inside], column[inside]] = grey[order][inside, None]
    return image


def _ramp(stops: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Piecewise-linear colour ramp through `stops` (k, 3) at 0, 1/(k-1), ..., 1: values in [0, 1]
    (any shape, clipped; NaN as 0) -> RGB (..., 3) floats in [0, 1]."""
    x = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64)), 0, 1) * (len(stops) - 1)
    low = np.floor(x).astype(int).clip(0, len(stops) - 2)
    frac = (x - low)[..., None]
    return stops[low] * (1 - frac) + stops[low + 1] * frac


def colormap(values: np.ndarray) -> np.ndarray:
    """A blue -> green -> yellow -> red ramp of values in [0, 1] (n, 3) floats."""
    stops = np.array([[0.19, 0.21, 0.58], [0.13, 0.57, 0.55], [0.48, 0.82, 0.32], [0.99, 0.91, 0.14],
                      [0.85, 0.15, 0.10]])
    return _ramp(stops, values)


VIRIDIS = np.array([[68, 1, 84], [72, 40, 120], [62, 73, 137], [49, 104, 142], [38, 130, 142],
                    [31, 158, 137], [53, 183, 121], [110, 206, 88], [253, 231, 37]]) / 255.0
"""viridis (perceptually uniform, readable in grey and by colour-blind readers) at 0, 1/8, ..., 1."""


def viridis(values: np.ndarray) -> np.ndarray:
    """viridis of values in [0, 1] (any shape, clipped): RGB (..., 3) floats in [0, 1], dark purple at 0,
    yellow at 1."""
    return _ramp(VIRIDIS, values)


def css_gradient(stops: np.ndarray = VIRIDIS) -> str:
    """A CSS linear-gradient, left to right, through the RGB `stops` (k, 3) in [0, 1]."""
    colors = ", ".join("#{:02x}{:02x}{:02x}".format(*np.round(stop * 255).astype(int)) for stop in stops)
    return f"linear-gradient(to right, {colors})"


def distance_image(mesh: Mesh, gt: Mesh, view: dict, max_distance: float, width: int = 320,
                   height: int = 320) -> np.ndarray:
    """`mesh` coloured by the unsigned distance of each visible point to `gt` (0 blue .. max_distance
    and beyond red), lightly shaded; (h, w, 3) uint8."""
    import open3d as o3d

    hit, points, normals, direction = raycast(mesh, view, width, height)
    gt_scene = o3d.t.geometry.RaycastingScene()
    gt_scene.add_triangles(o3d.core.Tensor(gt.vertices.detach().cpu().numpy().astype(np.float32)),
                           o3d.core.Tensor(gt.faces.cpu().numpy().astype(np.uint32)))
    distance = np.zeros(hit.shape, dtype=np.float64)
    if hit.any():
        query = o3d.core.Tensor(points[hit].astype(np.float32))
        distance[hit] = gt_scene.compute_distance(query).numpy()
    lambert = np.clip(-(normals * direction).sum(-1), 0.0, 1.0)
    colors = colormap(distance / max_distance) * (0.5 + 0.5 * lambert)[..., None]
    image = np.where(hit[..., None], colors, 1.0)
    return (np.clip(image, 0, 1) * 255).astype(np.uint8)


def _font(size: int = 14):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def labelled_row(images: list[np.ndarray], labels: list[str]) -> Image.Image:
    """Images side by side, each with a caption above it."""
    h = max(i.shape[0] for i in images)
    band = 22
    canvas = Image.new("RGB", (sum(i.shape[1] for i in images), h + band), BACKGROUND)
    draw, x = ImageDraw.Draw(canvas), 0
    for image, label in zip(images, labels):
        size = max(8, min(14, image.shape[1] // 20))
        chars = max(4, int(image.shape[1] / (0.6 * size)))
        canvas.paste(Image.fromarray(image), (x, band))
        draw.text((x + 4, 3), label if len(label) <= chars else label[: chars - 1] + "…", fill=(0, 0, 0),
                  font=_font(size))
        x += image.shape[1]
    return canvas


def _nice_max(value: float) -> float:
    if not math.isfinite(value) or value <= 0:
        return 1.0
    exponent = 10 ** math.floor(math.log10(value))
    for step in (1, 2, 2.5, 5, 10):
        if value <= step * exponent:
            return step * exponent
    return 10 * exponent


def _fitted(draw: ImageDraw.ImageDraw, text: str, width: float, font) -> str:
    """`text`, cut with an ellipsis to fit `width` pixels."""
    if draw.textlength(text, font=font) <= width:
        return text
    while text and draw.textlength(text + "…", font=font) > width:
        text = text[:-1]
    return text + "…"


def bar_chart(title: str, groups: list[str], series: list[str], values: dict[tuple[str, str], float],
              width: int = 720, height: int = 360, log: bool = False) -> Image.Image:
    """Grouped bars: one group per `groups` entry (scenes), one bar per `series` entry (methods);
    values[(group, series)], missing or NaN values leave a gap. `log` plots log10 (values > 0). The
    chart widens past `width` to give each bar at least 14 pixels and each group label 2 rows of room:
    labels alternate between two rows under the axis and are cut with an ellipsis only beyond that."""
    draw, font = ImageDraw.Draw(Image.new("RGB", (1, 1))), _font(12)
    legend = max([draw.textlength(name, font=font) for name in series] + [60])
    left, right, top, bottom = 70, int(legend) + 44, 30, 56
    width = max(width, left + right + len(groups) * max(14 * len(series) + 12, 60))
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)
    draw.text((left, 8), title, fill=(0, 0, 0), font=_font(15))
    finite = [v for v in values.values() if v is not None and math.isfinite(v) and (v > 0 or not log)]
    if log and finite:
        lo_exp, hi_exp = math.floor(math.log10(min(finite))), math.ceil(math.log10(max(finite)))
        hi_exp = max(hi_exp, lo_exp + 1)
        scale = lambda v: (math.log10(v) - lo_exp) / (hi_exp - lo_exp)
        ticks = [(10.0**e, (e - lo_exp) / (hi_exp - lo_exp)) for e in range(lo_exp, hi_exp + 1)]
    else:
        top_value = _nice_max(max(finite, default=1.0))
        scale = lambda v: v / top_value
        ticks = [(top_value * k / 4, k / 4) for k in range(5)]
    plot_h, plot_w = height - top - bottom, width - left - right
    for value, fraction in ticks:
        y = top + plot_h * (1 - fraction)
        draw.line([(left, y), (left + plot_w, y)], fill=(225, 225, 225))
        draw.text((4, y - 7), f"{value:.3g}", fill=(60, 60, 60), font=font)
    draw.line([(left, top), (left, top + plot_h), (left + plot_w, top + plot_h)], fill=(0, 0, 0))
    group_w = plot_w / max(1, len(groups))
    bar_w = group_w * 0.8 / max(1, len(series))
    for g, group in enumerate(groups):
        x0 = left + g * group_w + group_w * 0.1
        for s, name in enumerate(series):
            value = values.get((group, name))
            if value is None or not math.isfinite(value) or (log and value <= 0):
                continue
            h = plot_h * min(max(scale(value), 0.0), 1.0)
            x = x0 + s * bar_w
            draw.rectangle([x, top + plot_h - h, x + bar_w - 2, top + plot_h], fill=PALETTE[s % len(PALETTE)])
        label = _fitted(draw, group, 2 * group_w - 8, font)
        centre, row = left + (g + 0.5) * group_w, g % 2 if len(groups) > 1 else 0
        draw.line([(centre, top + plot_h), (centre, top + plot_h + 4 + 16 * row)], fill=(150, 150, 150))
        x = min(max(centre - draw.textlength(label, font=font) / 2, 2), width - draw.textlength(label, font=font) - 2)
        draw.text((x, top + plot_h + 6 + 16 * row), label, fill=(0, 0, 0), font=font)
    for s, name in enumerate(series):
        y = top + 4 + 18 * s
        draw.rectangle([width - right + 12, y, width - right + 24, y + 12], fill=PALETTE[s % len(PALETTE)])
        draw.text((width - right + 30, y - 1), name, fill=(0, 0, 0), font=font)
    return image


def _decades(logs: list[float]) -> tuple[int, int]:
    """The whole powers of ten around some log10 values (at least one decade apart)."""
    lo, hi = math.floor(min(logs)), math.ceil(max(logs))
    return lo, max(hi, lo + 1)


def scatter_plot(title: str, x_label: str, y_label: str, points: list[tuple[float, float, str, str]],
                 width: int = 720, height: int = 380) -> Image.Image:
    """Scatter of (x, y, series, label) on log-x and log-y axes (decades); colour by series."""
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw, font = ImageDraw.Draw(image), _font(12)
    left, right, top, bottom = 70, 150, 50, 50
    plot_h, plot_w = height - top - bottom, width - left - right
    draw.text((left, 6), title, fill=(0, 0, 0), font=_font(15))
    points = [p for p in points if all(math.isfinite(v) and v > 0 for v in p[:2])]
    series = sorted({p[2] for p in points})
    draw.line([(left, top), (left, top + plot_h), (left + plot_w, top + plot_h)], fill=(0, 0, 0))
    draw.text((left + plot_w // 2 - 40, height - 20), x_label, fill=(0, 0, 0), font=font)
    draw.text((4, top - 20), y_label, fill=(0, 0, 0), font=font)
    if points:
        logs = [(math.log10(p[0]), math.log10(p[1])) for p in points]
        (x_lo, x_hi), (y_lo, y_hi) = [_decades([xy[axis] for xy in logs]) for axis in (0, 1)]
        to_x = lambda lx: left + plot_w * (lx - x_lo) / (x_hi - x_lo)
        to_y = lambda ly: top + plot_h * (1 - (ly - y_lo) / (y_hi - y_lo))
        for e in range(x_lo, x_hi + 1):
            draw.line([(to_x(e), top), (to_x(e), top + plot_h)], fill=(230, 230, 230))
            draw.text((to_x(e) - 10, top + plot_h + 4), f"{10.0**e:g}", fill=(60, 60, 60), font=font)
        for e in range(y_lo, y_hi + 1):
            draw.line([(left, to_y(e)), (left + plot_w, to_y(e))], fill=(230, 230, 230))
            draw.text((4, to_y(e) - 7), f"{10.0**e:g}", fill=(60, 60, 60), font=font)
        for (_, _, name, label), (lx, ly) in zip(points, logs):
            x, y = to_x(lx), to_y(ly)
            color = PALETTE[series.index(name) % len(PALETTE)]
            draw.ellipse([x - 5, y - 5, x + 5, y + 5], fill=color)
            draw.text((x + 7, y - 7), label[:16], fill=(80, 80, 80), font=font)
    for s, name in enumerate(series):
        y = top + 4 + 18 * s
        draw.rectangle([width - right + 12, y, width - right + 24, y + 12], fill=PALETTE[s % len(PALETTE)])
        draw.text((width - right + 30, y - 1), name, fill=(0, 0, 0), font=font)
    return image


def interpolation_picture(prior: AutoDecoder, first: int, second: int, path: str | Path, steps: int = 5,
                          resolution: int = 64, size: int = 160) -> Path:
    """A PNG of the shapes of codes (1 - t) z_first + t z_second for `steps` values of t in [0, 1]
    (training shapes `first` and `second` of an auto-decoder): DeepSDF's latent interpolation."""
    codes = prior.codes.weight.detach()
    view = default_view(EXTRACTION_BOUNDS)
    images, labels = [], []
    for t in np.linspace(0.0, 1.0, steps):
        code = (1 - t) * codes[first] + t * codes[second]
        field = LatentConditioned.from_code(prior.decoder, code.cpu()).to(codes.device).eval()
        with torch.no_grad():
            images.append(shade(extract_unit(field, resolution), view, size, size))
        labels.append(f"t = {t:.2f}")
    path = Path(path)
    labelled_row(images, labels).save(path)
    return path
