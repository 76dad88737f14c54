"""The depth and joint runs' learning-rate decay every --lr-step epochs, at a step other than 1 (mutation audit)."""

import json

import pytest

from models.train import main
from tests.test_train_cli import FRAME, args


def test_the_rate_decays_after_every_lr_step_epochs_not_one_sooner_or_later(tmp_path):
    """--lr-step 2: epochs 1 and 2 train at the rate given, 3 at a tenth of it; the log gives each epoch the rate
    it trained at."""
    split = tmp_path / "one.txt"
    split.write_text(f"{FRAME}\n")
    out = tmp_path / "run"
    assert main(args("depth", out, split, "--epochs", "3", "--lr", "0.001", "--lr-step", "2", "--lr-gamma",
                     "0.1", "--no-progress")) == 0
    rates = [json.loads(line)["lr"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert rates == pytest.approx([1e-3, 1e-3, 1e-4])
