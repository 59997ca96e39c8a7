"""The method x scene harness behind evaluate.py: scene recipes, methods, the runner, the report."""

from neuralsurf.evaluation.methods import NotApplicable, neural_sdf, poisson, tsdf
from neuralsurf.evaluation.report import markdown_table, write_report
from neuralsurf.evaluation.runner import run_benchmark
from neuralsurf.scenes import SceneUnavailable

__all__ = ["NotApplicable", "SceneUnavailable", "markdown_table", "neural_sdf",
           "poisson", "run_benchmark", "tsdf", "write_report"]
