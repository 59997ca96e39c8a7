"""What a results row says about the machine (neuralsurf.evaluation.runner.environment)."""

import platform

from neuralsurf.evaluation.runner import environment


def test_no_hostname_in_results_unless_asked(monkeypatch):
    monkeypatch.setattr(platform, "node", lambda: "alice-laptop-7f3a")
    env = environment()
    assert not any("alice-laptop-7f3a" in value for value in env.values()), env
    assert "host" not in env
    assert {"torch", "open3d", "numpy", "python", "machine", "cpu_threads", "gpu"} <= set(env)
    assert environment(include_host=True)["host"] == "alice-laptop-7f3a"
