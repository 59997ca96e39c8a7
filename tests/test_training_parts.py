"""The fit's parts on their own: the training step (eager on a CPU, where a CUDA graph cannot be
recorded) against a hand-computed gradient step, and the checkpoint that saves and resumes its state."""

from types import SimpleNamespace

import pytest
import torch
from torch import nn

from neuralsurf.checkpoints import load_checkpoint
from neuralsurf.errors import CheckpointError, NeuralsurfError
from neuralsurf.structures import Normalization
from neuralsurf.training import Checkpoints, FitDiverged, TrainStep, cosine_schedule


class LineSampler:
    """A batch (x[n, 1], y[n]) and one term, mean((model(x) - y)^2), weighted by 2."""

    def __init__(self) -> None:
        self.weights = {"fit": 2.0}

    def losses(self, model: nn.Module, batch) -> dict[str, torch.Tensor]:
        x, y = batch
        return {"fit": ((model(x).squeeze(-1) - y) ** 2).mean()}


def line_step(cuda_graph: bool = True):
    torch.manual_seed(0)
    model = nn.Linear(1, 1).double()
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    step = TrainStep(model, [SimpleNamespace(name="line")], [LineSampler()], optimizer, torch.device("cpu"),
                     cuda_graph=cuda_graph)
    return model, step


def test_a_step_on_a_cpu_runs_eagerly_and_is_one_gradient_step_of_the_weighted_loss():
    model, step = line_step(cuda_graph=True)
    assert step.graphed is None  # no CUDA device: the eager step, whatever cuda_graph says
    x = torch.tensor([[0.0], [1.0], [2.0]], dtype=torch.float64)
    y = torch.tensor([1.0, 3.0, 5.0], dtype=torch.float64)
    w, b = float(model.weight.detach()), float(model.bias.detach())
    residual = w * x.squeeze(-1) + b - y
    # d/dw and d/db of 2 * mean(residual^2)
    grad_w, grad_b = float((4 * residual * x.squeeze(-1)).mean()), float((4 * residual).mean())
    terms, total = step([(x, y)], 0)
    assert list(terms) == ["line/fit"]
    assert float(total.detach()) == pytest.approx(2 * float((residual ** 2).mean()), rel=1e-12)
    assert float(model.weight.detach()) == pytest.approx(w - 0.1 * grad_w, rel=1e-12)
    assert float(model.bias.detach()) == pytest.approx(b - 0.1 * grad_b, rel=1e-12)
    step.scheduled()  # nothing to copy without a graph
    step.check(terms, total, 0)


def test_a_nan_loss_raises_before_the_update():
    model, step = line_step()
    before = [p.detach().clone() for p in model.parameters()]
    x = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    with pytest.raises(FitDiverged, match="diverged: loss became nan at step 7") as error:
        step([(x, torch.tensor([1.0, float("nan")], dtype=torch.float64))], 7)
    assert isinstance(error.value, NeuralsurfError) and "line/fit" in str(error.value)
    assert all(torch.equal(a, p) for a, p in zip(before, model.parameters()))


def training_state(seed: int):
    torch.manual_seed(seed)
    model = nn.Linear(3, 1)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: cosine_schedule(s, 10, 0, 0.1))
    return model, optimizer, scheduler, torch.Generator().manual_seed(seed)


def test_a_checkpoint_resumes_every_part_of_the_state(tmp_path):
    model, optimizer, scheduler, generator = training_state(0)
    for _ in range(3):
        optimizer.zero_grad()
        model(torch.randn(4, 3, generator=generator)).sum().backward()
        optimizer.step()
        scheduler.step()
    normalization = Normalization.from_points(torch.tensor([[0.0, 0, 0], [2, 2, 2]], dtype=torch.float64))
    saver = Checkpoints(tmp_path, model, normalization, 0.05, optimizer, scheduler, generator, {"seed": 0})
    saver.save(3, 1.5, {"total": [1.0, 0.5]})
    expected_draw, expected_rng = torch.rand(5, generator=generator), torch.rand(5)
    torch.manual_seed(123)

    model2, optimizer2, scheduler2, generator2 = training_state(1)
    loader = Checkpoints(tmp_path, model2, normalization, 0.05, optimizer2, scheduler2, generator2)
    assert loader.resume(steps=10) == (3, 1.5, {"total": [1.0, 0.5]})
    assert torch.equal(torch.rand(5, generator=generator2), expected_draw)
    assert torch.equal(torch.rand(5), expected_rng)  # torch's global RNG as it was when saved
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), model2.state_dict().values()))
    assert scheduler2.last_epoch == 3 and optimizer2.param_groups[0]["lr"] == optimizer.param_groups[0]["lr"]
    assert torch.equal(optimizer2.state_dict()["state"][0]["exp_avg"], optimizer.state_dict()["state"][0]["exp_avg"])
    state = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert state["config"] == {"seed": 0} and state["step"] == 3 and state["margin"] == 0.05
    with pytest.warns(UserWarning, match="already holds 3 >= 2 steps"):
        loader.resume(steps=2)


def test_a_checkpoint_without_a_run_directory_or_off_rank_0_writes_nothing(tmp_path):
    model, optimizer, scheduler, generator = training_state(0)
    normalization = Normalization.from_points(torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=torch.float64))
    nowhere = Checkpoints(None, model, normalization, 0.05, optimizer, scheduler, generator)
    nowhere.save(1, 0.1, {})
    assert nowhere.resume(steps=5) == (0, 0.0, {})
    Checkpoints(tmp_path, model, normalization, 0.05, optimizer, scheduler, generator, writes=False).save(1, 0.1, {})
    assert not (tmp_path / "checkpoints").exists()


def test_resuming_into_another_model_names_the_file(tmp_path):
    model, optimizer, scheduler, generator = training_state(0)
    normalization = Normalization.from_points(torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=torch.float64))
    Checkpoints(tmp_path, model, normalization, 0.05, optimizer, scheduler, generator).save(1, 0.1, {})
    other = nn.Linear(4, 1)
    other_optimizer = torch.optim.Adam(other.parameters())
    loader = Checkpoints(tmp_path, other, normalization, 0.05, other_optimizer,
                         torch.optim.lr_scheduler.LambdaLR(other_optimizer, lambda s: 1.0), torch.Generator())
    with pytest.raises(CheckpointError, match="last.pt does not match this model"):
        loader.resume(steps=5)
