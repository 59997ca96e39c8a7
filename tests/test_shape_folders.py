"""Shape-collection folders: meshes by class subfolder, and Occupancy Networks' preprocessed layout."""

import numpy as np
import pytest
import torch
import trimesh

from neuralsurf.errors import FileFormatError, InputError
from neuralsurf.io import read_mesh
from neuralsurf.io.shape_folders import (
    folder_layout,
    list_mesh_folder,
    list_occupancy_folder,
    read_occupancy_shape,
    unpack_occupancies,
)


def write_mesh_folder(root):
    box, ball = trimesh.creation.box((1.0, 0.5, 0.25)), trimesh.creation.icosphere(1)
    (root / "chair").mkdir(parents=True)
    box.export(root / "chair" / "a.obj")
    ball.export(root / "chair" / "b.PLY")
    box.export(root / "chair" / "notes.txt", file_type="off")  # not a mesh extension: ignored
    (root / "cup" / "c1" / "models").mkdir(parents=True)
    ball.export(root / "cup" / "c1" / "models" / "model_normalized.obj")  # ShapeNet-like shape folder
    box.export(root / "cup" / "d.off")
    box.export(root / "cup" / "e.glb")
    (root / "cup" / "train.lst").write_text("c1\nd\n")
    (root / "cup" / "test.lst").write_text("e\n")
    return box, ball


def test_mesh_folder_lists_classes_shapes_and_splits(tmp_path):
    box, ball = write_mesh_folder(tmp_path)
    entries = list_mesh_folder(tmp_path)
    assert [(e.category, e.name, e.split) for e in entries] == [
        ("chair", "a", None), ("chair", "b", None), ("cup", "c1", "train"), ("cup", "d", "train"),
        ("cup", "e", "test")]
    assert entries[2].path.name == "model_normalized.obj"
    assert folder_layout(tmp_path) == "meshes"
    for entry in entries:  # each entry reads back as the mesh written
        mesh = read_mesh(entry.path)
        expected = ball if entry.name in ("b", "c1") else box
        assert np.allclose(sorted(mesh.vertices.numpy().tolist()), sorted(np.asarray(expected.vertices).tolist()))


def test_mesh_folder_errors_name_the_problem(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        list_mesh_folder(tmp_path / "absent")
    with pytest.raises(InputError, match="no class subfolders"):
        list_mesh_folder(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.warns(UserWarning, match="holds no meshes"), pytest.raises(InputError, match="holds no meshes"):
        list_mesh_folder(tmp_path)
    (tmp_path / "mug" / "m" / "parts").mkdir(parents=True)
    trimesh.creation.box().export(tmp_path / "mug" / "m" / "one.obj")
    trimesh.creation.box().export(tmp_path / "mug" / "m" / "parts" / "two.obj")
    (tmp_path / "empty").rmdir()
    with pytest.raises(InputError, match="must hold one mesh"):
        list_mesh_folder(tmp_path)


def test_split_lists_warn_about_missing_and_unlisted_shapes(tmp_path):
    (tmp_path / "lamp").mkdir()
    for name in ("p", "q"):
        trimesh.creation.box().export(tmp_path / "lamp" / f"{name}.obj")
    (tmp_path / "lamp" / "train.lst").write_text("p\nghost\n")
    with pytest.warns(UserWarning) as record:
        entries = list_mesh_folder(tmp_path)
    messages = " ".join(str(w.message) for w in record)
    assert "missing" in messages and "'ghost'" in messages and "in no .lst file" in messages and "'q'" in messages
    assert [(e.name, e.split) for e in entries] == [("p", "train")]
    (tmp_path / "lamp" / "test.lst").write_text("p\n")
    with pytest.raises(InputError, match="both train.lst and test.lst"):
        list_mesh_folder(tmp_path)


def write_occupancy_shape(folder, n=1001, seed=0, packed=True):
    """A sphere of radius 0.4 in Occupancy Networks' files: float16 points, packed occupancies."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.55, 0.55, (n, 3)).astype(np.float16)
    inside = np.linalg.norm(points.astype(np.float64), axis=1) < 0.4
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    folder.mkdir(parents=True)
    np.savez(folder / "points.npz", points=points, occupancies=np.packbits(inside) if packed else inside,
             loc=np.zeros(3), scale=np.float64(1))
    np.savez(folder / "pointcloud.npz", points=(0.4 * normals).astype(np.float16),
             normals=normals.astype(np.float16), loc=np.zeros(3), scale=np.float64(1))
    return points, inside


def test_occupancy_layout_reads_packed_and_plain_occupancies(tmp_path):
    points, inside = write_occupancy_shape(tmp_path / "02691156" / "s1")
    assert points.dtype == np.float16  # as Occupancy Networks store them
    write_occupancy_shape(tmp_path / "02691156" / "s2", seed=1, packed=False)
    (tmp_path / "02691156" / "val.lst").write_text("s2\n")
    (tmp_path / "02691156" / "train.lst").write_text("s1\n")
    assert folder_layout(tmp_path) == "occupancy"
    entries = list_occupancy_folder(tmp_path)
    assert [(e.category, e.name, e.split) for e in entries] == [("02691156", "s1", "train"), ("02691156", "s2", "val")]
    shape = read_occupancy_shape(entries[0].path)
    assert shape.points.dtype == torch.float32 and shape.occupancies.dtype == torch.bool
    assert torch.equal(shape.occupancies, torch.from_numpy(inside))
    assert torch.equal(shape.occupancies, shape.points.double().norm(dim=1) < 0.4)  # the sphere oracle
    assert torch.allclose(shape.surface.double().norm(dim=1), torch.full((500,), 0.4, dtype=torch.float64), atol=1e-3)
    second = read_occupancy_shape(entries[1].path)
    assert torch.equal(second.occupancies, second.points.double().norm(dim=1) < 0.4)


def test_occupancy_files_that_do_not_fit_are_named(tmp_path):
    folder = tmp_path / "c" / "s"
    write_occupancy_shape(folder)
    np.savez(folder / "points.npz", points=np.zeros((10, 3)), occupancies=np.zeros(3, np.uint8))
    with pytest.raises(FileFormatError, match="3 occupancies .* for 10 points"):
        read_occupancy_shape(folder)
    np.savez(folder / "points.npz", points=np.zeros((10, 3)))
    with pytest.raises(FileFormatError, match="lacks \\['occupancies'\\]"):
        read_occupancy_shape(folder)
    (folder / "pointcloud.npz").unlink()
    np.savez(folder / "points.npz", points=np.zeros((10, 3)), occupancies=np.zeros(10, bool))
    with pytest.raises(FileFormatError, match="pointcloud.npz not found"):
        read_occupancy_shape(folder)
    with pytest.raises(InputError, match="not Occupancy Networks' layout"), pytest.warns(UserWarning):
        list_occupancy_folder(tmp_path / "c" / "s" / "..")
    assert unpack_occupancies(np.packbits([1, 0, 1]), 3).tolist() == [True, False, True]


# ----------------------------------------------------------------------------- priors from folders


def write_spheres(root, damaged=False):
    """Two classes of three spheres each (radius 0.5 in the unit frame once normalised), as files."""
    from neuralsurf.io import write_mesh
    from neuralsurf.priors.mesh_folders import damage_mesh
    from neuralsurf.structures import Mesh

    ball = trimesh.creation.icosphere(2)
    for category, scale in (("small", 0.2), ("large", 30.0)):
        for i in range(3):
            mesh = Mesh(torch.tensor(ball.vertices) * scale + i, torch.tensor(ball.faces))
            if damaged:
                mesh = damage_mesh(mesh, holes=2, duplicated=1, inner=1, flipped=0.3, radius=0.05, inset=0.02,
                                   seed=i).mesh
            write_mesh(root / category / f"s{i}.obj", mesh)


def sphere_collection(root, source):
    from neuralsurf.priors.folders import FolderCollection

    return FolderCollection(str(source), n_sdf=1000, n_occ=300, n_surface=300, root=str(root), test_fraction=0.34)


@pytest.mark.parametrize("damaged", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_folder_collection_signs_match_the_sphere(tmp_path, damaged):
    from neuralsurf.priors import CollectionSDF
    from neuralsurf.priors.cache import read_manifest

    write_spheres(tmp_path / "meshes", damaged)
    collection = sphere_collection(tmp_path / "cache", tmp_path / "meshes")
    assert (collection.count("train"), collection.count("test")) == (4, 2)
    collection.build(progress=False)
    records, _ = read_manifest(collection.folder)
    assert [r.kind for r in records] == ["large", "large", "small", "small", "large", "small"]
    for path in CollectionSDF(collection.folder).paths:
        with np.load(path) as data:
            points, values = torch.from_numpy(data["sdf_points"]).double(), torch.from_numpy(data["sdf_values"]).double()
            truth = points.norm(dim=1) - 0.5  # every sphere normalised to radius 0.5 at the origin
            clear = truth.abs() > 0.03  # beyond the icosphere's chord error (and the holes' reach in damaged ones)
            assert (torch.sign(values[clear]) == torch.sign(truth[clear])).double().mean() > (0.97 if damaged else 0.9999)
            assert (values - truth).abs().median() < 0.02
            radius = np.linalg.norm(data["occ_uniform_points"], axis=1)
            clear = np.abs(radius - 0.5) > 0.03
            assert (data["occ_uniform_inside"][clear] == (radius[clear] < 0.5)).mean() > (0.97 if damaged else 0.9999)
    shapes = collection.test_shapes()  # same-sized, y-up spheres: no frame warning
    assert len(shapes) == 2 and all(abs(float(s.surface.norm(dim=1).mean()) - 0.5) < 0.02 for s in shapes)


def test_frame_check_warns_about_turned_and_oversized_shapes():
    from neuralsurf.priors.folders import FrameStats, check_frame

    generator = torch.Generator().manual_seed(0)

    def box(extents):  # surface-like points of a box, more of them low down (a chair's legs)
        points = (torch.rand(2000, 3, dtype=torch.float64, generator=generator) - 0.5) * torch.tensor(extents)
        low = points[:, 1] < 0
        return torch.cat([points, points[low]])

    training = [box((0.5 + 0.05 * i, 1.0, 0.4 + 0.03 * i)) for i in range(6)]
    stats = FrameStats.from_shapes(training, [1.0 + 0.1 * i for i in range(6)])
    assert check_frame(box((0.52, 1.0, 0.42)), stats, "upright", size=1.1) is None
    turned = box((0.52, 1.0, 0.42))[:, [0, 2, 1]]  # z up in its file
    with pytest.warns(UserWarning, match=r"up axis looks like \+z"):
        check_frame(turned, stats, "turned", size=1.1)
    with pytest.warns(UserWarning, match="other units"):
        check_frame(box((0.52, 1.0, 0.42)), stats, "millimetres", size=1100.0)
    with pytest.warns(UserWarning, match="outside the unit frame"):
        check_frame(2 * box((0.52, 1.0, 0.42)), stats, "unnormalised")


def test_occupancy_layout_becomes_a_collection(tmp_path):
    from neuralsurf.errors import ConfigError

    for i in range(3):
        write_occupancy_shape(tmp_path / "occ" / "c" / f"s{i}", n=4001, seed=i)
    collection = sphere_collection(tmp_path / "cache", tmp_path / "occ")
    collection = type(collection)(collection.source, n_sdf=2000, n_occ=500, n_surface=400, root=collection.root,
                                  normalize=False, test_fraction=0.0)
    assert collection.layout == "occupancy" and collection.count("train") == 3
    collection.build(progress=False)
    with np.load(collection.folder / "train" / "c_train_0000.npz") as data:
        truth = np.linalg.norm(data["sdf_points"], axis=1) - 0.4
        clear = np.abs(truth) > 0.02
        assert (np.sign(data["sdf_values"][clear]) == np.sign(truth[clear])).mean() > 0.99
        assert np.array_equal(data["occ_uniform_inside"], np.linalg.norm(data["occ_uniform_points"], axis=1) < 0.4)
    with pytest.raises(ConfigError, match="no meshes to score"):
        collection.test_shapes()
    with pytest.warns(UserWarning, match="trained and kept"):  # train.py trains it, then keeps it unscored
        assert not collection.check_prior({"sdf": {}})


def test_both_kinds_of_collection_follow_the_collection_protocol(tmp_path):
    from neuralsurf.priors import Collection, ShapeCollection
    from neuralsurf.priors.folders import FolderCollection
    from neuralsurf.scenes import analytic_scene

    procedural = ShapeCollection(classes=("mug",), n_train=1, n_test=1)
    assert isinstance(procedural, Collection) and procedural.check_prior({"sdf": {}})
    write_mesh_folder(tmp_path / "meshes")
    folder = FolderCollection(source=str(tmp_path / "meshes"), root=str(tmp_path / "cache"))
    assert isinstance(folder, Collection) and folder.check_prior({"sdf": {}})  # a mesh folder with test shapes
    assert not isinstance(analytic_scene("sphere", n_points=100), Collection)


def test_suite_priors_folder_sets_one_collection_for_scenes_and_priors(tmp_path):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from neuralsurf.cli import without_feeds
    from neuralsurf.priors.folders import FolderCollection

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = without_feeds(compose(config_name="evaluate", overrides=["suite=priors_folder",
                                                                       f"folder.source={tmp_path}", "folder.n_train=5"]))
    nodes = [cfg.scene.shapes_cloud.collection, cfg.scene.shapes_one_view.collection,
             cfg.method.deepsdf.collection, cfg.method.occupancy_network.collection]
    collections = [instantiate(node) for node in nodes]
    assert all(isinstance(c, FolderCollection) for c in collections)
    assert len({c.folder for c in collections}) == 1 and collections[0].source == str(tmp_path)
    assert collections[0].n_train == 5 and list(cfg.scenes) == ["shapes_cloud", "shapes_one_view"]


@pytest.mark.parametrize("experiment", ["shapes_deepsdf_tiny", "shapes_onet_tiny"])
def test_tiny_experiments_take_a_shape_folder_with_their_sizes(tmp_path, experiment):
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from neuralsurf.cli import without_feeds
    from neuralsurf.priors import ShapeCollection
    from neuralsurf.priors.folders import FolderCollection

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        procedural = compose(config_name="train", overrides=[f"experiment={experiment}"])
        folder = compose(config_name="train", overrides=[f"experiment={experiment}", "data=shape_folder",
                                                         f"data.source={tmp_path}"])
    shapes = instantiate(without_feeds(procedural).data)
    assert isinstance(shapes, ShapeCollection) and shapes.mesh_resolution == 64 and shapes.n_train == 2
    collection = instantiate(without_feeds(folder).data)  # no mesh_resolution: its meshes come from the files
    assert isinstance(collection, FolderCollection) and collection.source == str(tmp_path)
    assert (collection.n_train, collection.n_test, collection.n_sdf) == (2, 1, procedural.data.n_sdf)


@pytest.mark.parametrize("kind", ["chair", pytest.param("mug", marks=pytest.mark.slow),
                                  pytest.param("lamp", marks=pytest.mark.slow)])
def test_damaged_procedural_meshes_keep_the_clean_meshes_labels(kind):
    """Oracle: the clean mesh's exact inside (ray parity of the watertight mesh). A procedural shape
    damaged as the real-priors benchmark damages its training meshes (holes through thin legs, coincident
    and inner sheets, 30% reversed faces) must give a cache whose labels are the clean ones, where ray
    parity on the damaged mesh gets many wrong."""
    from neuralsurf.geometry import mesh_contains
    from neuralsurf.priors import Shape, collection_records
    from neuralsurf.priors.cache import CacheRecipe
    from neuralsurf.priors.folders import mesh_samples, sign_errors
    from neuralsurf.priors.mesh_folders import damage_mesh

    record = collection_records((kind,), 1, 0, 0, seed=1)[0]
    clean = Shape.from_record(record).mesh(32)  # unit frame, watertight; legs 2-3 voxels wide
    damaged = damage_mesh(clean, holes=3, duplicated=2, inner=2, inset=0.01, flipped=0.3, radius=0.04, seed=0).mesh
    assert clean.is_watertight and not damaged.is_watertight
    recipe = CacheRecipe(n_sdf=6000, n_occ=1000, n_surface=500)
    arrays = mesh_samples(damaged, recipe, seed=0)
    errors = sign_errors(arrays, clean, recipe)
    assert max(errors.values()) < 0.003, errors  # measured: at most 0.15%
    parity = {**arrays, "sdf_values": np.where(mesh_contains(torch.from_numpy(arrays["sdf_points"]), damaged), -1.0, 1.0)}
    assert sign_errors(parity, clean, recipe)["sdf_near"] > 0.01  # measured: 1.1-2.5%
