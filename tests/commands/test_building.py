"""`mpsim.commands.building`: what instantiating a config node raises becomes one message naming the node; a
model's sizes (from the config or a checkpoint) are planned on the meta device and checked before it is built."""

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from mpsim import memory
from mpsim.commands.building import Shape, build, build_model_for, model_config, planned_model
from mpsim.commands.runtime import Runtime
from mpsim.config import plain_dict
from mpsim.errors import CheckpointError, ConfigError, ResourceError
from tests.helpers import inline_specs


def test_running_out_of_memory_while_building_is_a_resource_error_not_a_traceback():
    """A MemoryError carries no message: it used to end in an IndexError while the message was composed."""
    node = OmegaConf.create({"_target_": "builtins.bytearray", "_args_": [10**16]})
    with pytest.raises(ResourceError, match=r"building system \(builtins.bytearray\) ran out of memory"):
        build(node, "system")


def test_any_other_failure_names_the_node_and_the_last_line_of_its_cause():
    node = OmegaConf.create({"_target_": "builtins.int", "_args_": ["seven"]})
    with pytest.raises(ConfigError, match=r"cannot build solver \(builtins.int\): invalid literal for int"):
        build(node, "solver")


# ---- sizes planned on the meta device before anything is allocated --------------------------------------------
EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "equations"
MODELS = [
    ("mpnode", "lorenz3", ["model.effects=[{_target_: mpsim.effects.LinearDamping, target: x}]"]),
    ("l2s", "lorenz3", []),
    ("node", "lorenz3", []),  # sized from the data at its compatibility check
    ("smnn", "lorenz3", ["model.param_hidden=8", "model.denoiser_hidden=8"]),
    ("mnn_dense", "lorenz3", []),
    ("smnn_forecast", "lorenz3", ["model.whole_state=true", "model.n_nodes=3"]),
    ("constant_velocity", "nbody20", []),
    ("deltagn", "nbody20", []),
    ("hogn", "nbody20", []),
]


def _runtime(tmp_path: Path, device: str = "cpu") -> Runtime:
    return Runtime(torch.device(device), torch.float32, tmp_path, tmp_path / "out", [])


def _system(cfg):
    return build(plain_dict(cfg.system), "system")


def _build(cfg, rt: Runtime, shape: Shape, ckpt, training: bool = False):
    """The model `prepare` builds for `cfg`: the checkpoint's config with the command line's on top."""
    model_cfg = model_config(plain_dict(cfg.model), ckpt, rt.overrides)
    return build_model_for(model_cfg, build(plain_dict(cfg.solver), "solver"), rt, shape, ckpt, training)


def _pieces(cfg_factory, model: str, system: str, extra: list[str]):
    cfg = cfg_factory("train", f"model={model}", f"system={system}", *extra)
    inline_specs(cfg)  # model.spec=<file>: its content, as the command layer passes it
    return cfg, plain_dict(cfg.model), Shape.of(_system(cfg)), build(plain_dict(cfg.solver), "solver")


@pytest.mark.parametrize(("model", "system", "extra"), MODELS, ids=[m[0] for m in MODELS])
def test_every_model_is_planned_on_the_meta_device_with_the_shapes_it_is_built_with(
    model, system, extra, cfg_factory, tmp_path
):
    cfg, model_cfg, shape, solver = _pieces(cfg_factory, model, system, extra)
    plan = planned_model(model_cfg, shape, solver, _runtime(tmp_path), None)
    assert plan is not None
    planned = plan.state_dict()
    assert planned and all(t.device.type == "meta" for t in planned.values())
    built = _build(cfg, _runtime(tmp_path), shape, None)
    assert {k: (t.shape, t.dtype) for k, t in planned.items()} == {
        k: (t.shape, t.dtype) for k, t in built.state_dict().items()
    }


@pytest.mark.parametrize(
    ("model", "extra"), [("physics", []), ("equations", [f"model.spec={EXAMPLES / 'lorenz_network.yaml'}"])]
)
def test_white_box_models_are_not_planned_and_are_checked_once_built(model, extra, cfg_factory, tmp_path):
    """model=physics builds its system (coupling draws) and model=equations tests its spec's values while they are
    constructed: not plannable on the meta device. Their weights are values written in their config."""
    cfg, model_cfg, shape, solver = _pieces(cfg_factory, model, "lorenz3", extra)
    assert planned_model(model_cfg, shape, solver, _runtime(tmp_path), None) is None
    built = _build(cfg, _runtime(tmp_path), shape, None)
    assert sum(p.numel() for p in built.parameters()) > 0


def _checkpoint(cfg, tmp_path, **config_changes):
    """A checkpoint of `cfg`'s model (as `load_checkpoint` returns it), its config changed by `config_changes`."""
    shape = Shape.of(_system(cfg))
    model_cfg = plain_dict(cfg.model)
    model = _build(cfg, _runtime(tmp_path), shape, None)
    return shape, {
        "path": str(tmp_path / "m.ckpt"),
        "model": {
            "config": {**model_cfg, **config_changes},
            "state_dict": model.state_dict(),
            "state_dim": model.state_dim,
            "control_dim": model.control_dim,
        },
        "system": {"system": "lorenz3", "state_names": shape.state_names, "n_nodes": shape.n_nodes},
    }


@pytest.fixture
def allocations(monkeypatch):
    """The element counts of every parameter created with storage (not on the meta device)."""
    sizes: list[int] = []
    real_new = torch.nn.Parameter.__new__

    def spy(cls, data=None, requires_grad=True):
        if data is not None and data.device.type != "meta":
            sizes.append(data.numel())
        return real_new(cls, data, requires_grad)

    monkeypatch.setattr(torch.nn.Parameter, "__new__", staticmethod(spy))
    return sizes


def test_a_checkpoint_whose_config_declares_other_sizes_than_its_weights_is_refused_before_allocation(
    cfg_factory, tmp_path, allocations
):
    cfg = cfg_factory("eval", "system=lorenz3", "model=mpnode")
    shape, ckpt = _checkpoint(cfg, tmp_path, hidden=3000)
    allocations.clear()
    with pytest.raises(CheckpointError, match=r"m.ckpt: its model.config does not describe its weights: .*\[3000, "):
        _build(cfg, _runtime(tmp_path), shape, ckpt)
    assert max(allocations, default=0) < 3000  # nothing of the declared size was allocated


def test_a_checkpoint_too_large_for_memory_is_refused_before_allocation(
    cfg_factory, tmp_path, allocations, monkeypatch
):
    """The weights must fit for eval; training also needs their gradients and Adam's two moments (4x)."""
    cfg = cfg_factory("train", "system=lorenz3", "model=mpnode")
    shape, ckpt = _checkpoint(cfg, tmp_path)
    weights = sum(t.numel() * t.element_size() for t in ckpt["model"]["state_dict"].values())
    monkeypatch.setattr(memory, "available_bytes", lambda device="cpu": 2 * weights)
    allocations.clear()
    with pytest.raises(ResourceError, match=r"m.ckpt\): 1,478 weights with their gradients and optimiser state"):
        _build(cfg, _runtime(tmp_path), shape, ckpt, training=True)
    assert not allocations
    model = _build(cfg, _runtime(tmp_path), shape, ckpt)  # evaluation: the weights alone fit
    assert torch.equal(model.state_dict()["state_std"], ckpt["model"]["state_dict"]["state_std"])
    with pytest.raises(ResourceError, match=r"smaller model.\* sizes, e.g. model.hidden"):
        _build(cfg_factory("train", "system=lorenz3", "model.hidden=4000"), _runtime(tmp_path), shape, None)
    assert max(allocations) < 4000
