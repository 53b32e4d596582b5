"""Every config option composes and instantiates; typos and wrong types fail at start with a clear message."""

from pathlib import Path

import pytest
import yaml
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf

import mpsim
from mpsim.cli import COMMANDS
from mpsim.config import check_targets
from mpsim.errors import ConfigError
from mpsim.models.base import Model
from mpsim.systems.base import System
from tests.helpers import inline_specs

CONF = Path(mpsim.__file__).parent / "conf"
EXAMPLE_SPEC = Path(__file__).resolve().parents[1] / "examples" / "equations" / "pendulums_linear_spring.yaml"


def _options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("name", _options("system"))
def test_every_system_builds(cfg_factory, name):
    spec = [f"system.spec={EXAMPLE_SPEC}", "system.name=equations"] if name == "equations" else []
    cfg = cfg_factory("train", f"system={name}", *spec)
    inline_specs(cfg)
    check_targets(cfg)
    system = instantiate(cfg.system)
    assert isinstance(system, System) and system.name == name
    assert system.rhs is not None and system.n_nodes >= 1


@pytest.mark.parametrize("name", _options("model"))
def test_every_model_builds(cfg_factory, name):
    cfg = cfg_factory("train", f"model={name}", *([f"model.spec={EXAMPLE_SPEC}"] if name == "equations" else []))
    inline_specs(cfg)
    solver = instantiate(cfg.solver)
    assert isinstance(instantiate(cfg.model, state_dim=2, control_dim=0, solver=solver), Model)


@pytest.mark.parametrize("group", ["solver", "trainer", "mode", "experiment"])
def test_every_option_of_the_other_groups_composes(cfg_factory, group):
    default = OmegaConf.to_container(cfg_factory("train"))
    names = _options(group)
    assert len(names) >= 2, names
    for name in names:
        cfg = cfg_factory("train", f"{group}={name}")
        if group == "experiment":  # a global-package option: it must change the default job
            assert OmegaConf.to_container(cfg) != default, name
            continue
        own = yaml.safe_load((CONF / group / f"{name}.yaml").read_text())
        scalars = {k: v for k, v in own.items() if k != "defaults" and not isinstance(v, dict | list)}
        assert scalars and {k: cfg[group][k] for k in scalars} == scalars, name  # this option, composed
        if "_target_" in cfg[group]:
            built = instantiate(cfg[group])
            assert f"{type(built).__module__}.{type(built).__qualname__}" == cfg[group]._target_, name


def test_every_command_has_a_primary_config():
    assert {p.stem for p in CONF.glob("*.yaml")} >= set(COMMANDS)


@pytest.mark.parametrize("command", list(COMMANDS))
def test_primary_configs_compose(cfg_factory, command):
    extra = ["init=x.ckpt"] if command in ("eval", "diagnose") else []
    cfg = cfg_factory(command, *extra)
    assert cfg.task == command and cfg.paths.output_root.endswith("/outputs")
    if extra:
        assert cfg.init == "x.ckpt"


def test_typo_in_a_target_node_suggests_the_right_key(cfg_factory):
    with pytest.raises((ConfigError, ConfigCompositionException), match="n_nodes"):
        cfg = cfg_factory("train", "system=lorenz3", "+system.n_node=4")
        check_targets(cfg)


def test_wrong_type_in_a_target_node(cfg_factory):
    cfg = cfg_factory("train", "system=lorenz3", "system.coupling=strong")
    with pytest.raises(ConfigError, match=r"system.coupling='strong' has the wrong type: .* expects float"):
        check_targets(cfg)


def test_typed_schema_rejects_typos_and_wrong_types(cfg_factory):
    with pytest.raises(ConfigCompositionException, match="trainer.lrr"):
        cfg_factory("train", "trainer.lrr=0.1")
    with pytest.raises(ConfigCompositionException, match="max_epochs"):
        cfg_factory("train", "trainer.max_epochs=many")
    with pytest.raises(ConfigCompositionException, match="n_train"):
        cfg_factory("train", "data.n_train=1.5")


def test_unknown_system_lists_the_options(cfg_factory):
    with pytest.raises(ConfigCompositionException, match="Could not find 'system/lorenz4'"):
        cfg_factory("train", "system=lorenz4")


@pytest.mark.parametrize(
    "args, match",
    [
        (["system.n_node=4"], "system.n_node is not a config key. Did you mean system.n_nodes?"),
        (["trainer.lrr=1"], "Did you mean trainer.lr?"),
        (["data.n_tran=5"], "Did you mean data.n_train"),
        (["eval.horizon=[1]"], "Did you mean eval.horizons?"),
        (["traner.lr=1"], "traner is not a config section. Did you mean trainer?"),
        (["system=nbody", "system.mass=2"], "add it with +system.mass=<value>"),
        (["-m", "seed=0,1", "trainer.batch_sise=4"], "Did you mean trainer.batch_size"),
        (["ckpt=a.ckpt"], "ckpt is not a config key. Did you mean init?"),  # other tools' word for it
        (["epochs=5"], "Did you mean trainer.max_epochs?"),
    ],
)
def test_command_line_typos_get_a_did_you_mean(args, match):
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    with pytest.raises(ConfigError) as err:
        compose_command("train", args, str(CONF))
    assert match in str(err.value) and "To append" not in str(err.value)
    if "mass" not in match:
        assert "+" not in str(err.value)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["hydra.sweeper.n_trials=0"], "hydra.sweeper.n_trials=0: must be a whole number >= 1"),
        (["hydra.sweeper.n_jobs=-1"], "hydra.sweeper.n_jobs=-1: must be a whole number >= 1"),
        (["hydra.sweeper.direction=up"], "hydra.sweeper.direction=up: must be minimize or maximize"),
        (["trainer.lr=tag(log,interval(0,1e-2))"], "a log-scale interval needs a low end > 0"),
        (["trainer.lr=interval(1e-2,1e-3)"], r"interval\(0.01, 0.001\): the low end must not exceed the high end"),
        (["model.hidden=interval(8,12)"], "model.hidden is a whole number, .* write range\\(8, 12\\)"),
        (["hydra.sweeper.params.trainer.lr='tag(log, interval(1e-4, 1e-2))'"], "given on the key itself"),
        (["hydra.sweeper.n_trial=3"], "Did you mean hydra.sweeper.n_trials?"),
    ],
)
def test_an_optuna_search_is_checked_before_the_study_starts(args, match):
    # each of these was a traceback from Optuna (after the study was created) or a wrong "hydra is not a config
    # section"; they must be one message, before any trial
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    with pytest.raises(ConfigError, match=match):
        compose_command("train", ["hparams_search=mpnode_lorenz10", *args], str(CONF))
    good = ["hparams_search=mpnode_lorenz10", "model.hidden=range(8,12)", "trainer.lr=tag(log, interval(1e-4, 1e-2))"]
    assert compose_command("train", good, str(CONF)) is not None


@pytest.mark.parametrize(
    "direction",
    [
        [],  # the sweeper's own default, the enum Direction.minimize (hydra/sweeper=optuna, as Hydra documents it)
        ["hydra.sweeper.direction=maximize"],
        ["hydra.sweeper.direction=[minimize]"],  # a list: one direction per objective
    ],
)
def test_hydra_sweeper_optuna_takes_the_enum_or_a_string_direction(direction):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    args = ["-m", "hydra/sweeper=optuna", "trainer.lr=interval(1e-3,1e-2)", *direction]
    assert compose_command("train", args, str(CONF)) is not None


def test_an_optuna_search_gets_one_direction_per_objective():
    # the sweeper takes a list of directions for several objectives; mpsim train returns one
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    args = ["-m", "hydra/sweeper=optuna", "hydra.sweeper.direction=[minimize,maximize]"]
    with pytest.raises(ConfigError, match=r"one direction per objective.*hydra.sweeper.direction=minimize"):
        compose_command("train", args, str(CONF))


def test_an_interval_without_an_optuna_search_says_what_a_sweep_takes():
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    with pytest.raises(ConfigError, match="an interval is a search space.*e.g. trainer.lr=1e-3,3e-3,1e-2"):
        compose_command("train", ["-m", "trainer.lr=interval(1e-3,1e-2)"], str(CONF))


def test_an_unquoted_call_or_nested_override_gets_the_quoting_advice():
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    args = ["system=pendulum2", "model=equations", "model.states=[theta,omega]", "model.params={g: 9.0}"]
    for bad in ("model.equations={theta: omega, omega: -g*sin(theta)}", "model.equations={omega: log(theta)}"):
        with pytest.raises(ConfigError, match=r"cannot parse.*In model.equations=\.\.\., quote every expression"):
            compose_command("train", [*args, bad], str(CONF))
    cfg = compose_command("train", [*args, 'model.equations={theta: omega, omega: "-g*sin(theta)"}'], str(CONF))
    assert cfg is not None and cfg.model.equations.omega == "-g*sin(theta)"  # the advice given works
    with pytest.raises(ConfigError, match=r'In bench.cases=\.\.\., quote every item that holds "="'):
        compose_command(
            "bench", ["bench=epoch_time", "bench.cases=[{name: x, overrides: [system=lorenz3]}]"], str(CONF)
        )
    nested = compose_command(
        "bench", ["bench=epoch_time", "bench.cases=[{name: x, overrides: ['system=lorenz3']}]"], str(CONF)
    )
    assert nested is not None and list(nested.bench.cases[0].overrides) == ["system=lorenz3"]
    with pytest.raises(ConfigError) as err:  # a parse error elsewhere gets no quoting advice
        compose_command("train", ["trainer.lr=[1,"], str(CONF))
    assert "quote every expression" not in str(err.value)
    # a call in any other value (a shell command substitution typed into a title) gets the plain quoting advice
    with pytest.raises(ConfigError, match=r"In title=\.\.\., quote the value inside the single quotes") as err:
        compose_command("report", ["title=$(touch x)"], str(CONF))
    assert "sin(theta)" not in str(err.value)
    titled = compose_command("report", ['title="$(touch x)"'], str(CONF))
    assert titled is not None and titled.title == "$(touch x)"  # the advice given works: a plain string


def test_a_key_with_no_close_match_lists_each_key_once():
    # a top-level name is also looked up among the config groups, most of which are keys already
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    with pytest.raises(ConfigError) as err:
        compose_command("eval", ["zzz=1"], str(CONF))
    text = str(err.value)
    assert "zzz is not a config key; the config has: " in text
    listing = text.split("has: ", 1)[1].rstrip(".").split(", ")
    assert {"init", "model", "system"} <= set(listing) and len(listing) == len(set(listing))


@pytest.mark.parametrize(
    "args, match",
    [
        (["device=tpu"], "device=tpu is not supported"),
        (["threads=-2"], "threads=-2"),
        (["system=lorenz3", "system.sigma=nan"], "system.sigma=nan is not a finite number"),
        (["data.noise_std=-1"], "data.noise_std=-1.0"),
        (["trainer.early_stop_patience=-1"], "trainer.early_stop_patience=-1: must be >= 0"),
        (["trainer.log_every_s=-5"], "trainer.log_every_s=-5.0: must be >= 0 seconds"),
        (["trainer.log_every=-1"], "trainer.log_every=-1: must be >= 0 epochs"),
        (["eval.horizons=[0]"], "horizons are numbers of steps >= 1"),
        (["-m", "data.n_train=4,0"], "data.n_train=0"),  # every sweep value is checked, not only the first
    ],
)
def test_values_out_of_range_are_refused_before_the_run(args, match):
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    with pytest.raises(ConfigError, match=match.replace("[", r"\[").replace("+", r"\+")):
        compose_command("train", args, str(CONF))


def test_valid_command_lines_compose():
    from mpsim.config import compose_command, register_schemas

    register_schemas()
    cfg = compose_command("train", ["-m", "system=lorenz3,lorenz10", "trainer.lr=1e-3"], str(CONF))
    assert cfg.system.name == "lorenz3" and cfg.trainer.lr == 1e-3
    assert compose_command("train", ["--cfg", "job"], str(CONF)) is None  # left to Hydra


def test_a_runs_overrides_record_is_read_as_data_and_a_damaged_one_is_named(tmp_path):
    from mpsim.config import read_overrides_file
    from mpsim.errors import DataError

    assert read_overrides_file(tmp_path) is None  # the run kept no record
    record = tmp_path / ".hydra" / "overrides.yaml"
    record.parent.mkdir()
    record.write_text("- seed=1\n- trainer.lr=0.01\n")
    assert read_overrides_file(tmp_path) == ["seed=1", "trainer.lr=0.01"]
    record.write_text("")
    assert read_overrides_file(tmp_path) == []  # Hydra writes [] for no overrides; an empty file is the same
    record.write_text("- seed=1\n- {data: 2}\n")
    with pytest.raises(DataError, match="must be a list of key=value overrides; got a list with nested values"):
        read_overrides_file(tmp_path)
    record.write_bytes(b"- seed=\xff\n")
    with pytest.raises(DataError, match="overrides.yaml is not valid YAML"):
        read_overrides_file(tmp_path)
