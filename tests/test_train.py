"""Training through composed configs: fast_dev_run, a tiny real epoch (checkpoint, logs, export), bad inputs."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import ROOT, compose
from hydra.utils import instantiate

from ruslam import load_extractor
from ruslam.models.export import export_weights, load_uwnet
from ruslam.train import train
from ruslam.training.common import format_report, load_initial_weights
from ruslam.training.module import NonFiniteLossError

TINY = ["model=uwnet", "data.num_images=6", "data.height=64", "data.width=96", "datamodule.image_size=null",
        "datamodule.val_size=2", "datamodule.batch_size=2", "datamodule.num_workers=0",
        "teacher.global_head.fit_images=4", "model.net.head_channels=16", "trainer.enable_progress_bar=false",
        "~callbacks.progress_bar"]


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("teacher_cache")


def _cfg(tmp_path, cache_root, extra=()):
    return compose("train", [f"out_dir={tmp_path}", f"datamodule.cache_root={cache_root}", *TINY, *extra])


def test_fast_dev_run_through_composed_config(tmp_path, cache_root):
    loss = train(_cfg(tmp_path, cache_root, ["+trainer.fast_dev_run=true"]))
    assert loss is not None and loss == loss  # finite float from the held-out set
    assert load_extractor(tmp_path / "uwnet.pt").extract(torch.rand(64, 96).numpy())["descriptors"].shape[1] == 64


def test_repeatability_term_is_trained_and_reported(tmp_path, cache_root, capsys):
    train(_cfg(tmp_path, cache_root, ["+trainer.fast_dev_run=true", "+model.repeatability_weight=1.0"]))
    assert "repeatability (1 - correlation)" in capsys.readouterr().out


def test_init_weights_starts_from_trained_weights_and_refuses_another_architecture(tmp_path, cache_root, capsys):
    cfg = _cfg(tmp_path, cache_root)
    torch.manual_seed(1)
    start = export_weights(instantiate(cfg.model.net), tmp_path / "start.pt")
    net = instantiate(cfg.model.net)  # another random draw
    load_initial_weights(net, start)
    for (k, va), vb in zip(load_uwnet(start).state_dict().items(), net.state_dict().values(), strict=True):
        assert torch.equal(va, vb), k
    train(_cfg(tmp_path / "ft", cache_root, ["+trainer.fast_dev_run=true", f"init_weights={start}"]))
    assert "initial" in capsys.readouterr().out
    other = export_weights(instantiate(cfg.model.net, head_channels=32), tmp_path / "other.pt")
    with pytest.raises(ValueError, match="head_channels=32"):
        train(_cfg(tmp_path / "bad", cache_root, ["+trainer.fast_dev_run=true", f"init_weights={other}"]))


@pytest.mark.slow
def test_one_epoch_writes_checkpoint_logs_every_term_and_resumes(tmp_path, cache_root, capsys):
    extra = ["trainer.max_epochs=1", "trainer.log_every_n_steps=1", "trainer.check_val_every_n_epoch=1"]
    train(_cfg(tmp_path, cache_root, extra))
    printed = capsys.readouterr().out
    assert "untrained" in printed and "detector (L3, soft CE)" in printed and "local descriptors (L2)" in printed
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert last.is_file()
    metrics = next((tmp_path / "csv").rglob("metrics.csv"))
    header = next(csv.reader(metrics.open()))
    for key in ("train/global", "train/local", "train/detector", "train/alpha", "train/beta", "train/gamma",
                "val/detector", "val/local"):
        assert key in header, key
    # Weights exported from the Lightning checkpoint equal the trained network.
    exported = export_weights(last, tmp_path / "from_ckpt.pt")
    a, b = load_uwnet(exported), load_uwnet(tmp_path / "uwnet.pt")
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert ka == kb and torch.equal(va, vb), ka
    # Resume from the checkpoint for one more epoch.
    train(_cfg(tmp_path / "resume", cache_root, ["trainer.max_epochs=2", f"ckpt_path={last}"]))
    assert (tmp_path / "resume" / "checkpoints" / "epoch001.ckpt").is_file()


def test_nan_loss_stops_training_with_a_clear_message(tmp_path, cache_root):
    cfg = _cfg(tmp_path, cache_root, ["trainer.max_epochs=1"])
    module = instantiate(cfg.model)
    with torch.no_grad():
        module.net.reduce.weight.fill_(float("nan"))
    datamodule = instantiate(cfg.datamodule, source=cfg.data, teacher=cfg.teacher)
    trainer = instantiate(cfg.trainer, logger=False, callbacks=[], enable_checkpointing=False)
    with pytest.raises(NonFiniteLossError, match="Training stopped at epoch 0, step 0: the distillation loss is nan"):
        trainer.fit(module, datamodule=datamodule)


def test_student_width_must_match_the_teacher(tmp_path, cache_root):
    with pytest.raises(ValueError, match="64-d local descriptors but the student is built with descriptor_dim=256"):
        train(_cfg(tmp_path, cache_root, ["model.net.descriptor_dim=256", "+trainer.fast_dev_run=true"]))


def test_missing_lightning_checkpoint_is_one_sentence(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        export_weights(tmp_path / "missing.ckpt", tmp_path / "out.pt")


def test_report_lists_before_and_after():
    text = format_report({"val/detector": 4.0, "val/local": 2.0}, {"val/detector": 3.0, "val/local": 0.5})
    assert "4.0000" in text and "3.0000" in text and "0.5000" in text


def test_paper_experiment_composes():
    cfg = compose("train", ["experiment=paper", "out_dir=x"])
    assert cfg.trainer.max_epochs == 150 and cfg.datamodule.batch_size == 16
    assert cfg.datamodule.val_overrides.split == "test" and cfg.data.num_test == 200 and cfg.data.split == "train"
    assert cfg.model.optimizer.lr == 0.003 and "nyu" in cfg.data._target_.lower()


@pytest.mark.slow
def test_two_process_cpu_ddp(tmp_path, cache_root):
    cmd = [sys.executable, "train.py", "trainer=ddp", "trainer.devices=2", "trainer.max_epochs=1",
           f"hydra.run.dir={tmp_path}", f"datamodule.cache_root={cache_root}", *TINY]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "trained" in done.stdout
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()


def test_slurm_launcher_config_composes():
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = hydra_compose("train", ["hydra/launcher=submitit_slurm", "out_dir=x"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher") and cfg.hydra.launcher.timeout_min == 1440


@pytest.mark.parametrize(("logger", "cls"), [("csv", "CSVLogger"), ("tensorboard", "TensorBoardLogger"),
                                             ("wandb", "WandbLogger")])
def test_logger_configs_build_offline(tmp_path, logger, cls):
    cfg = compose("train", [f"logger={logger}", f"out_dir={tmp_path}"])
    (built,) = [instantiate(c) for c in cfg.logger.values()]
    assert type(built).__name__ == cls
    if logger == "wandb":
        assert cfg.logger.wandb.offline is True
