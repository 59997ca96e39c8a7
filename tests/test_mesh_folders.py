"""Procedural shapes written as a folder of damaged mesh files, built by separate jobs in shards."""

import pytest

from neuralsurf.errors import ConfigError
from neuralsurf.io import read_mesh
from neuralsurf.priors.cache import cache_path, load_cache
from neuralsurf.priors.folders import FolderCollection, shard_part, sign_errors
from neuralsurf.priors.mesh_folders import cad_damage, write_procedural_folder
from neuralsurf.priors.procedural import collection_records
from neuralsurf.structures import Normalization


def test_shard_parts_cover_every_item_once():
    items = list(range(11))
    parts = [shard_part(items, k, 3) for k in range(3)]
    assert [i for part in parts for i in part] == items and [len(p) for p in parts] == [3, 4, 4]
    with pytest.raises(ConfigError, match="shard"):
        shard_part(items, 3, 3)


def test_damage_is_drawn_per_shape():
    records = collection_records(("mug",), 6, 0, 0)
    drawn = [cad_damage(r) for r in records]
    assert len({(d["holes"], d["radius"], d["flipped"]) for d in drawn}) == len(records)
    assert all(d["holes"] >= 1 for d in drawn)


def test_damaged_folder_is_resumable_and_builds_in_shards(tmp_path):
    classes = ("slat_chair", "mug")
    assert write_procedural_folder(tmp_path, classes, n_train=1, n_test=1, resolution=28) == {"written": 4, "kept": 0}
    assert write_procedural_folder(tmp_path, classes, n_train=1, n_test=1, resolution=28) == {"written": 0, "kept": 4}
    assert (tmp_path / "damaged" / "mug" / "test.lst").read_text() == "mug_test_0000\n"
    clean = read_mesh(tmp_path / "clean" / "mug" / "mug_train_0000.ply")
    damaged = read_mesh(tmp_path / "damaged" / "mug" / "mug_train_0000.ply")
    assert clean.is_watertight and not damaged.is_watertight

    collection = FolderCollection(str(tmp_path / "damaged"), n_sdf=2000, n_occ=500, n_surface=500,
                                  root=str(tmp_path / "cache"))
    records = collection.records()
    assert [r.split for r in records] == ["train"] * 2 + ["test"] * 2
    collection.build(progress=False, shard=0, shards=2)
    assert [collection.is_cached(r) for r in records] == [True] * 2 + [False] * 2
    assert not (tmp_path / "cache" / "collection.json").exists()  # written once every part is there
    collection.build(progress=False, shard=1, shards=2)
    assert (tmp_path / "cache" / "collection.json").is_file()
    written = {r: cache_path(collection.folder, r).stat().st_mtime_ns for r in records}
    collection.build(progress=False)  # the whole: every shape a cache hit
    assert {r: cache_path(collection.folder, r).stat().st_mtime_ns for r in records} == written
    assert len(collection.test_shapes()) == 2
    # the labels against the clean meshes' exact inside: wrong only where a hole cuts a thin part
    for record, entry in zip(records, collection.sources()):
        frame = Normalization.from_points(read_mesh(entry.path).vertices.double())
        reference = frame.mesh_to_unit(read_mesh(tmp_path / "clean" / record.kind / f"{entry.name}.ply"))
        shares = sign_errors(load_cache(cache_path(collection.folder, record)), reference, collection.recipe)
        assert max(shares.values()) < 0.02, (record.name, shares)
    with pytest.raises(ConfigError, match="shard"):
        collection.build(progress=False, shard=2, shards=2)
