"""Checkpoints (safetensors + JSON, no pickle), and the loop's resume / NaN / best bookkeeping.

The loop tests use a small regression model defined here (anything with ``losses(batch)``
trains), so they run in a second; the real models go through tests/test_train_cli.py.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace

import pytest
import torch
from torch.utils.data import Dataset

from msdnet.runtime.errors import MsdnetError
from msdnet.training.config import MODEL_PRESETS, TRAIN_PRESETS, ModelConfig, TrainConfig
from msdnet.training.recipe.checkpoint import (
    META_FILE,
    MODEL_FILE,
    TRAINING_FILE,
    CheckpointState,
    config_to_dict,
    dataclass_from_dict,
    join_tensors,
    load_training_state,
    load_weights,
    read_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
    split_tensors,
)
from msdnet.training.recipe.loop import NonFiniteLoss, RunSpec, train


class ToyData(Dataset):
    """(x (4,), y (2,)) pairs of a fixed random linear map plus noise."""

    def __init__(self, n: int, seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, 4, generator=g)
        self.y = self.x @ torch.randn(4, 2, generator=g) + 0.1 * torch.randn(n, 2, generator=g)

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.x[i], self.y[i]


class ToyBatch:
    def __init__(self, samples: list[tuple[torch.Tensor, torch.Tensor]]) -> None:
        self.x = torch.stack([s[0] for s in samples])
        self.y = torch.stack([s[1] for s in samples])
        self.batch_size = len(samples)


class ToyModel(torch.nn.Module):
    """Linear map + dropout (so the per-step reseeding matters); loss terms mse and l1."""

    def __init__(self, nan_at_call: int | None = None) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(4, 2)
        self.drop = torch.nn.Dropout(0.2)
        self.nan_at_call = nan_at_call
        self.calls = 0

    def losses(self, batch: ToyBatch) -> dict[str, torch.Tensor]:
        self.calls += self.training  # training calls only (validation runs in eval mode)
        pred = self.lin(self.drop(batch.x))
        mse = ((pred - batch.y) ** 2).mean()
        l1 = (pred - batch.y).abs().mean()
        if self.nan_at_call is not None and self.calls >= self.nan_at_call:
            l1 = l1 * float("nan")
        return {"loss": mse + 0.1 * l1, "mse": mse, "l1": l1}


CFG = MODEL_PRESETS["tiny"]
TCFG = replace(TRAIN_PRESETS["tiny"], batch_size=3, lr=0.05)


def _run(out, epochs=3, **kw) -> tuple[ToyModel, CheckpointState]:
    torch.manual_seed(TCFG.seed)
    model = ToyModel(kw.pop("nan_at_call", None))
    spec = RunSpec(kind="teacher", out=out, epochs=epochs, **kw)
    state = train(model, CFG, TCFG, ToyData(20, 1), ToyData(6, 2), spec, collate_fn=ToyBatch)
    return model, state


@pytest.mark.parametrize("name", sorted(MODEL_PRESETS))
def test_model_config_round_trips_through_json(name):
    cfg = replace(MODEL_PRESETS[name], radar_columns=("x", "y", "z", "v_r", "mag"), radar_feature_norm=())
    back = dataclass_from_dict(ModelConfig, json.loads(json.dumps(config_to_dict(cfg))))
    assert back == cfg
    assert isinstance(back.grid.point_range, tuple) and isinstance(back.radar_feature_norm[0], tuple)
    assert dataclass_from_dict(TrainConfig, config_to_dict(TCFG)) == TCFG


def test_config_from_json_rejects_unknown_and_mistyped_fields():
    d = config_to_dict(CFG)
    with pytest.raises(MsdnetError, match="unknown ModelConfig fields"):
        dataclass_from_dict(ModelConfig, {**d, "bogus": 1})
    with pytest.raises(MsdnetError, match="grid.voxel_size: expected 3 values"):
        dataclass_from_dict(ModelConfig, {**d, "grid": {**d["grid"], "voxel_size": [0.1, 0.1]}})
    with pytest.raises(MsdnetError, match="vfe_channels: expected int"):
        dataclass_from_dict(ModelConfig, {**d, "vfe_channels": "8"})


def test_optimizer_state_round_trips_without_pickle():
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    sch = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=1e-2, total_steps=5)
    model(torch.randn(4, 3)).sum().backward()
    opt.step()
    sch.step()
    tensors: dict[str, torch.Tensor] = {}
    tree = json.loads(json.dumps(split_tensors(opt.state_dict(), tensors, "opt")))
    back = join_tensors(tree, tensors)
    ref = opt.state_dict()
    assert back["param_groups"] == ref["param_groups"]  # tuples (betas) and int keys restored
    assert set(back["state"]) == {0, 1}
    for i in (0, 1):
        for k, v in ref["state"][i].items():
            assert torch.equal(back["state"][i][k], v)
    sch_tree = json.loads(json.dumps(split_tensors(sch.state_dict(), tensors, "sch")))
    assert join_tensors(sch_tree, tensors) == sch.state_dict()
    with pytest.raises(TypeError, match="without pickle"):
        split_tensors({"f": object()}, {}, "x")


def test_save_and_load_checkpoint_files(tmp_path):
    model = ToyModel()
    opt = torch.optim.Adam(model.parameters())
    state = CheckpointState(kind="teacher", train=TCFG, epochs=4, epoch=2, step=14, history=[{"a": 1.0}])
    folder = save_checkpoint(tmp_path / "last", model, CFG, state, opt)
    assert sorted(p.name for p in folder.iterdir()) == sorted([MODEL_FILE, TRAINING_FILE, META_FILE])
    meta = json.loads((folder / META_FILE).read_text())
    assert meta["model_config"]["grid"]["voxel_size"] == [0.4, 0.4, 0.6]
    assert meta["versions"]["torch"] == torch.__version__ and meta["seed"] == TCFG.seed
    _, cfg, back = read_checkpoint(folder / META_FILE)  # a file inside the folder works too
    assert cfg == CFG and back == state
    other = ToyModel()
    load_weights(other, folder / MODEL_FILE)
    assert torch.equal(other.lin.weight, model.lin.weight)
    load_training_state(folder, torch.optim.Adam(other.parameters()))

    # A swap killed between its two renames leaves only last.old: it is found and kept.
    (tmp_path / "last").rename(tmp_path / "last.old")
    assert resolve_checkpoint(tmp_path / "last") == tmp_path / "last.old"
    save_checkpoint(tmp_path / "last", model, CFG, replace(state, epoch=3), opt)
    assert read_checkpoint(tmp_path / "last")[2].epoch == 3
    assert not (tmp_path / "last.old").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["last"]  # no temporary folders left

    # Tampering and wrong shapes are named errors, not tracebacks.
    with pytest.raises(MsdnetError, match="weights do not fit the model"):
        load_weights(torch.nn.Linear(4, 2), folder / MODEL_FILE)
    (folder / MODEL_FILE).write_bytes((folder / MODEL_FILE).read_bytes()[:-4] + b"\0\0\0\0")
    with pytest.raises(MsdnetError, match="sha256 differs"):
        read_checkpoint(folder)
    with pytest.raises(MsdnetError, match="no such checkpoint"):
        read_checkpoint(tmp_path / "nowhere")


def test_resume_after_stop_matches_uninterrupted_run(tmp_path):
    full, full_state = _run(tmp_path / "full", epochs=3)
    _, first = _run(tmp_path / "cut", epochs=3, stop_after=1)
    assert first.epoch == 1 and first.step == 7  # ceil(20 / 3) steps per epoch
    resumed, state = _run(tmp_path / "cut", epochs=3, resume=True)
    assert (state.epoch, state.step) == (full_state.epoch, full_state.step) == (3, 21)
    assert torch.equal(resumed.lin.weight, full.lin.weight)  # bit for bit
    assert [h["val_loss"] for h in state.history] == [h["val_loss"] for h in full_state.history]
    log = [json.loads(line) for line in (tmp_path / "cut" / "log.jsonl").read_text().splitlines()]
    assert [e["epoch"] for e in log if e["event"] == "epoch"] == [1, 2, 3]
    assert [e["resume"] for e in log if e["event"] == "start"] == [False, True]
    best = read_checkpoint(tmp_path / "cut" / "best")[2]
    assert best.best_val_loss == min(h["val_loss"] for h in state.history)


def test_resume_mid_epoch_matches_uninterrupted_run(tmp_path):
    full, _ = _run(tmp_path / "full", epochs=2)
    # A NaN at training call 11 stops the run right after step 10 saved ``last`` mid-epoch 2.
    with pytest.raises(NonFiniteLoss):
        _run(tmp_path / "cut", epochs=2, save_every=10, nan_at_call=11)
    _, _, mid = read_checkpoint(tmp_path / "cut" / "last")
    assert (mid.epoch, mid.batch_in_epoch, mid.step) == (1, 3, 10)
    resumed, state = _run(tmp_path / "cut", epochs=2, resume=True)
    assert (state.epoch, state.step, state.batch_in_epoch) == (2, 14, 0)
    assert torch.equal(resumed.lin.weight, full.lin.weight)


def test_nan_loss_stops_with_the_term_named(tmp_path):
    with pytest.raises(NonFiniteLoss, match=r"at epoch 1, step 4: l1=nan \(") as err:
        _run(tmp_path, epochs=2, nan_at_call=4)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "last").exists()  # nothing half-trained was saved as a checkpoint
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert log[-1]["event"] == "stop" and "l1=nan" in log[-1]["error"]


def test_resume_refuses_a_different_run(tmp_path, monkeypatch):
    _run(tmp_path, epochs=2, stop_after=1)
    with pytest.raises(MsdnetError, match="run planned 2 epochs, not 3"):
        _run(tmp_path, epochs=3, resume=True)
    monkeypatch.setattr(sys.modules[__name__], "TCFG", replace(TCFG, lr=0.1, num_workers=1))
    with pytest.raises(MsdnetError, match=r"train config differs: lr 0.05 \(now 0.1\)$"):
        _run(tmp_path, epochs=2, resume=True)
    assert math.isfinite(read_checkpoint(tmp_path / "last")[2].history[0]["val_loss"])
