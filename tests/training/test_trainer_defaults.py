"""One source of truth for the trainer's defaults: the `Trainer` signature, the `TrainerConf` schema and
`conf/trainer/default.yaml` agree (they disagreed once: 128 / 32 batches, plateau 25 / 10, early stop 100 / 30)."""

import dataclasses
import inspect
from pathlib import Path

import yaml

from mpsim.config import TrainerConf
from mpsim.training.trainer import Trainer

CONF = Path(__file__).resolve().parents[2] / "src" / "mpsim" / "conf" / "trainer" / "default.yaml"


def _signature_defaults() -> dict:
    params = inspect.signature(Trainer.__init__).parameters
    return {k: p.default for k, p in params.items() if k != "self"}


def test_schema_matches_the_trainer_signature():
    schema = {f.name: f.default for f in dataclasses.fields(TrainerConf) if f.name != "_target_"}
    assert schema == _signature_defaults()


def test_default_yaml_matches_the_trainer_signature():
    values = {k: v for k, v in yaml.safe_load(CONF.read_text()).items() if k != "_target_"}
    assert values == _signature_defaults()
