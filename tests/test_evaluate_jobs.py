"""evaluate.py's rows as units of work: each row stored as soon as it is done, a killed run resumed
without recomputing its finished rows, a changed setting rerunning only its row, the rows run as
Hydra multirun jobs (joblib; submitit's local executor) into one results folder with one report."""

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from neuralsurf.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
TINY = ["suite=tiny", "methods=[neural_sdf,poisson,tsdf]"]
"""Three rows on the sphere: a 5-step neural fit, Poisson, TSDF (skipped: no depth frames)."""
METRICS = ["chamfer_l1", "chamfer_l1_exact", "normal_consistency", "fscore_1%", "hausdorff", "iou"]

CRASHING = """
import os, signal, sys
import neuralsurf.evaluation.methods as methods

def crash(scene, **_):
    os.kill(os.getpid(), signal.SIGKILL)  # the machine goes down in the middle of this row

methods.{method} = crash
from neuralsurf.cli import evaluate_main
evaluate_main()
"""
"""evaluate.py whose `method` kills its own process with SIGKILL: everything before it must be kept."""


def evaluate_py(args: list[str], script: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """`python evaluate.py ARGS` (or `python SCRIPT ARGS`) from the repository; stdout and stderr captured."""
    command = [sys.executable, str(script or REPO / "evaluate.py"), *args]
    env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
    return subprocess.run(command, check=False, cwd=REPO, capture_output=True, text=True, timeout=timeout, env=env)


def stored(results_dir: Path) -> dict[tuple[str, str], dict]:
    """(scene, method) -> the full record of each row file ({"key", "settings", "final", "row"})."""
    records = [json.loads(p.read_text()) for p in sorted((results_dir / "rows").glob("*.json"))]
    return {(r["row"]["scene"], r["row"]["method"]): r for r in records}


def report_rows(results_dir: Path) -> dict[tuple[str, str], dict]:
    rows = json.loads((results_dir / "results.json").read_text())["rows"]
    return {(r["scene"], r["method"]): r for r in rows}


def assert_same_results(rows: dict, reference: dict) -> None:
    """Same rows, same status; Poisson's metrics bit-identical, the neural fit's within 1e-6."""
    assert set(rows) == set(reference)
    for pair, row in rows.items():
        assert row["status"] == reference[pair]["status"], pair
        for name in (m for m in METRICS if m in reference[pair]):
            if pair[1] == "poisson":
                assert row[name] == reference[pair][name], (pair, name)
            else:
                assert row[name] == pytest.approx(reference[pair][name], abs=1e-6), (pair, name)


@pytest.fixture(scope="module")
def sequential(tmp_path_factory) -> Path:
    """The three tiny rows run one after another in one process: the reference."""
    folder = tmp_path_factory.mktemp("sequential")
    out = evaluate_py([*TINY, f"hydra.run.dir={folder}"])
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return folder


@pytest.mark.subprocess
@pytest.mark.slow
def test_a_killed_run_keeps_its_finished_rows_and_a_rerun_computes_only_the_rest(tmp_path, sequential):
    script = tmp_path / "crashing_evaluate.py"
    script.write_text(CRASHING.format(method="poisson"))
    run = tmp_path / "run"
    killed = evaluate_py([*TINY, f"hydra.run.dir={run}"], script=script)
    assert killed.returncode == -signal.SIGKILL
    first = stored(run)
    assert set(first) == {("sphere", "neural_sdf")} and first["sphere", "neural_sdf"]["row"]["status"] == "ok"
    assert set(report_rows(run)) == {("sphere", "neural_sdf")}  # the report was rebuilt after that row
    assert not list((run / "rows").glob(".*"))  # no temporary file left as a row

    again = evaluate_py([*TINY, f"hydra.run.dir={run}"])
    assert again.returncode == 0, again.stderr[-3000:]
    log = (run / "evaluate.log").read_text()
    assert "neural_sdf on sphere: reused" in log
    assert "poisson on sphere: chamfer_l1" in log and "poisson on sphere: reused" not in log
    assert "(2 computed, 1 reused)" in log
    second = stored(run)
    assert second["sphere", "neural_sdf"] == first["sphere", "neural_sdf"]  # kept as it was, bit for bit
    assert_same_results(report_rows(run), report_rows(sequential))


@pytest.mark.subprocess
def test_the_report_is_rebuilt_from_the_stored_rows_alone(tmp_path, sequential):
    from neuralsurf.cli import evaluate

    folder = tmp_path / "copy"
    for name in ("rows", "renders"):
        (folder / name).mkdir(parents=True)
        for path in (sequential / name).glob("*"):
            (folder / name / path.name).write_bytes(path.read_bytes())
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=[f"report={folder}"])
    rows = evaluate(cfg)
    assert {(r["scene"], r["method"]) for r in rows} == set(report_rows(sequential))
    assert report_rows(folder) == report_rows(sequential)
    assert (folder / "results.csv").read_text() == (sequential / "results.csv").read_text()
    html = (folder / "report.html").read_text()
    plots = list((folder / "plots").glob("*.png"))
    assert len(plots) >= 6 and html.count("<img ") == len(plots) + 2  # the charts, the two reconstructions' renders


def test_a_report_of_a_folder_without_rows_names_what_to_give(tmp_path):
    from neuralsurf.cli import evaluate

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=[f"report={tmp_path}"])
    with pytest.raises(ConfigError, match="no stored rows.*hydra.run.dir"):
        evaluate(cfg)


def tiny_in_process(run_dir: Path, overrides: list[str]) -> list[dict]:
    from neuralsurf.cli import evaluate

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["suite=tiny", "methods=[poisson,neural_sdf]",
                                                         "render=false", *overrides])
    OmegaConf.set_struct(cfg, False)
    cfg.run_dir = str(run_dir)
    return evaluate(cfg)


def test_a_changed_setting_reruns_only_its_row(tmp_path, caplog):
    tiny_in_process(tmp_path, [])
    before = stored(tmp_path)
    caplog.clear()
    with caplog.at_level("INFO", logger="neuralsurf"):
        rows = tiny_in_process(tmp_path, ["method.poisson.depth=6"])
    after = stored(tmp_path)
    assert "neural_sdf on sphere: reused" in caplog.text and "poisson on sphere: reused" not in caplog.text
    assert after["sphere", "neural_sdf"] == before["sphere", "neural_sdf"]
    assert after["sphere", "poisson"]["key"] != before["sphere", "poisson"]["key"]
    assert after["sphere", "poisson"]["settings"]["method"]["depth"] == 6
    assert after["sphere", "poisson"]["row"]["n_faces"] != before["sphere", "poisson"]["row"]["n_faces"]
    assert {r["method"]: r["n_faces"] for r in rows} == {m: after["sphere", m]["row"]["n_faces"]
                                                          for m in ("poisson", "neural_sdf")}
    caplog.clear()
    with caplog.at_level("INFO", logger="neuralsurf"):
        tiny_in_process(tmp_path, ["n_samples=1000"])  # a run-wide setting: every row again
    assert "on sphere: reused" not in caplog.text and "(2 computed, 0 reused)" in caplog.text
    assert all(r["settings"]["n_samples"] == 1000 for r in stored(tmp_path).values())


@pytest.mark.subprocess
@pytest.mark.slow
def test_joblib_jobs_give_the_rows_of_the_sequential_run_and_one_report(tmp_path, sequential):
    sweep = tmp_path / "sweep"
    out = evaluate_py(["-m", *TINY[:1], "methods=[neural_sdf],[poisson,tsdf]", "hydra/launcher=joblib",
                       "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}"])
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    logs = sorted(sweep.glob("[0-9]*/evaluate.log"))
    assert len(logs) == 2 and all("1 threads" in log.read_text() for log in logs)  # 2 cores, 2 jobs
    assert set(stored(sweep)) == set(stored(sequential))
    assert_same_results(report_rows(sweep), report_rows(sequential))
    html = (sweep / "report.html").read_text()
    assert all(f"<td>{m}</td>" in html for m in ("neural_sdf", "poisson")) and "<b>tsdf on sphere</b>" in html


@pytest.mark.subprocess
@pytest.mark.slow
def test_submitit_local_jobs_write_one_results_folder(tmp_path, sequential):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install neuralsurf[cluster]")
    sweep = tmp_path / "sweep"
    out = evaluate_py(["-m", *TINY, "hydra/launcher=submitit_local", "shard=range(2)", "shards=2",
                       "hydra.launcher.timeout_min=10", f"hydra.sweep.dir={sweep}"])
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert (sweep / ".submitit").is_dir() and len(list(sweep.glob("[0-9]*/evaluate.log"))) == 2
    assert_same_results(report_rows(sweep), report_rows(sequential))
    assert json.loads((sweep / "results.json").read_text())["methods"] == ["neural_sdf", "poisson", "tsdf"]


def test_shards_cover_every_row_once_in_consecutive_parts():
    from neuralsurf.evaluation.jobs import shard_pairs

    scenes, methods = ["a", "b", "c"], ["x", "y"]
    every = [(s, m) for s in scenes for m in methods]
    for shards in range(1, 8):
        parts = [shard_pairs(scenes, methods, shard, shards) for shard in range(shards)]
        assert [pair for part in parts for pair in part] == every
        assert max(map(len, parts)) - min(map(len, parts)) <= 1
    with pytest.raises(ConfigError, match="shard"):
        shard_pairs(scenes, methods, 2, 2)


def test_threads_per_job_share_the_cores_among_the_launchers_jobs():
    from neuralsurf.evaluation.jobs import job_threads

    assert job_threads(None, {"n_jobs": 2}, cpus=8) == 4
    assert job_threads(None, {"n_jobs": -1}, cpus=8) == 1
    assert job_threads(None, {"n_jobs": 16}, cpus=8) == 1
    assert job_threads(None, {"cpus_per_task": 3}, cpus=8) == 3
    assert job_threads(None, {}, cpus=8) is None
    assert job_threads(2, {"n_jobs": 8}, cpus=8) == 2
    with pytest.raises(ConfigError, match="threads"):
        job_threads(0, {}, cpus=8)


def _count_under_lock(path: str, times: int) -> None:
    from neuralsurf.locks import file_lock

    counter = Path(path)
    for _ in range(times):
        with file_lock(counter.with_suffix(".lock")):
            value = int(counter.read_text())
            time.sleep(0.01)  # another process would read the same value here without the lock
            counter.write_text(str(value + 1))


def test_a_file_lock_lets_one_process_in_at_a_time(tmp_path):
    counter = tmp_path / "counter.txt"
    counter.write_text("0")
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_count_under_lock, args=(str(counter), 10)) for _ in range(3)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(60)
    assert [w.exitcode for w in workers] == [0, 0, 0]
    assert counter.read_text() == "30"


def _build_collection(root: str, out: str, start) -> None:
    from neuralsurf.priors import ShapeCollection
    from neuralsurf.priors.cache import build_collection

    collection = ShapeCollection(classes=("lamp",), n_train=1, n_test=1, n_sdf=500, n_occ=100, n_surface=500,
                                 mesh_resolution=24, workers=0, root=root)
    start.wait(120)  # both processes ask at the same moment
    counts = build_collection(collection.folder, collection.records(), collection.recipe, progress=False)
    Path(out).write_text(json.dumps(counts))


def test_jobs_building_one_shape_collection_together_build_each_shape_once(tmp_path):
    context = multiprocessing.get_context("spawn")
    outs, start = [tmp_path / f"counts_{i}.json" for i in range(2)], context.Barrier(2)
    workers = [context.Process(target=_build_collection, args=(str(tmp_path / "shapes"), str(out), start))
               for out in outs]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(300)
    assert [w.exitcode for w in workers] == [0, 0]
    counts = [json.loads(out.read_text()) for out in outs]
    assert sorted(c["built"] for c in counts) == [0, 2]  # one process built both shapes ...
    assert sorted(c["cached"] for c in counts) == [0, 2]  # ... the other found them cached


def _train_prior(folder: str, start) -> None:
    """trained_prior into `folder`, with fit wrapped to append a line to `<folder>.fits` each time it runs."""
    import functools

    from neuralsurf.priors import CollectionSDF, ShapeCollection, deepsdf, trained_prior, training

    real_fit = training.fit

    def counted_fit(*args, **kwargs):
        with open(f"{folder}.fits", "a") as handle:
            handle.write("fit\n")
        return real_fit(*args, **kwargs)

    training.fit = counted_fit
    collection = ShapeCollection(classes=("lamp",), n_train=2, n_test=0, n_sdf=500, n_occ=100, n_surface=500,
                                 mesh_resolution=24, workers=0, root=f"{folder}_shapes")
    start.wait(120)
    trained_prior(folder, collection, functools.partial(deepsdf, latent_dim=8, width=32, depth=2, skip_layers=()),
                  [functools.partial(CollectionSDF.from_collection, shapes_per_batch=2, samples_per_shape=64)],
                  trainer={"steps": 3, "checkpoint_every": 3, "log_every": 3})


def test_jobs_asking_for_one_prior_together_train_it_once(tmp_path):
    from neuralsurf.models import AutoDecoder
    from neuralsurf.priors import load_prior

    context = multiprocessing.get_context("spawn")
    folder, start = tmp_path / "prior_abc", context.Barrier(2)
    workers = [context.Process(target=_train_prior, args=(str(folder), start)) for _ in range(2)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(300)
    assert [w.exitcode for w in workers] == [0, 0]
    assert Path(f"{folder}.fits").read_text() == "fit\n"  # the second process reused the first one's prior
    assert isinstance(load_prior(folder / "checkpoints" / "last.pt"), AutoDecoder)


def test_a_scene_is_built_once_and_read_back_by_later_jobs(tmp_path):
    import torch

    from neuralsurf.evaluation.store import cached_scene
    from neuralsurf.scenes import analytic_scene

    built = []

    def build():
        built.append(1)
        return analytic_scene(n_points=300)

    first = cached_scene(tmp_path, "sphere", "k1", build)
    second = cached_scene(tmp_path, "sphere", "k1", build)
    assert len(built) == 1 and second is not first
    assert torch.equal(first.cloud.points, second.cloud.points)
    assert torch.equal(first.ground_truth.faces, second.ground_truth.faces)
    cached_scene(tmp_path, "sphere", "k2", build)  # other settings: built again
    assert len(built) == 2
