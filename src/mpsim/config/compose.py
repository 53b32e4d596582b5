"""The command line composed before Hydra starts a run: `compose_command` composes it exactly as the run will (no
torch import, no run directory), turns Hydra's composition errors into one line (with a did-you-mean from
`mpsim.config.suggest`), and checks an Optuna search (`validate_search`) and the values (`validate_values`) of
every variant a sweep composes."""

from __future__ import annotations

import re
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from mpsim.config.keys import override_key
from mpsim.config.suggest import unknown_key_message
from mpsim.config.values import validate_values
from mpsim.errors import ConfigError

_FLAGS_WITHOUT_VALUE = ("-m", "--multirun")


MAX_SWEEP_CHECKS = 64


def _sweep_variants(args: list[str]) -> list[list[str]] | None:
    """Override lists that together use every value of every sweep at least once: the first values, then each
    other value of one sweep with the others at their first (None if the sweeps cannot be expanded here)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import IntervalSweep

    parsed = OverridesParser.create().parse_overrides(args)
    values: list[list[str]] = []
    for item in parsed:
        sweep = item.value()
        if isinstance(sweep, IntervalSweep):  # an Optuna search space: its two ends stand for the values it may take
            ends = [int(v) if v is not None and float(v).is_integer() else v for v in (sweep.start, sweep.end)]
            values.append([f"{item.get_key_element()}={v}" for v in ends])
        elif item.is_sweep_override():
            try:
                values.append([f"{item.get_key_element()}={v}" for v in item.sweep_string_iterator()])
            except Exception:  # noqa: BLE001 - glob() and friends need Hydra's config loader
                return None
        else:
            assert item.input_line is not None  # parse_overrides sets it on every override it returns
            values.append([item.input_line])
    first = [v[0] for v in values]
    variants = [first]
    for i, options in enumerate(values):
        for option in options[1:]:
            variants.append([*first[:i], option, *first[i + 1 :]])
    return variants[:MAX_SWEEP_CHECKS]


def _quote_hint(overrides: list[str]) -> str:
    """Advice for the override Hydra could not parse when its value holds a call or an `=`: an inline equation
    `omega: -g*sin(theta)` (Hydra reads `sin(...)` as one of its own functions) or a nested override
    `overrides: [system=lorenz3]`; quoted inside the override, either is a plain string."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for arg in overrides:
        key, _, value = arg.partition("=")
        if "(" not in value and "=" not in value:
            try:
                parser.parse_override(arg)
            except Exception:  # noqa: BLE001 - Hydra raises several kinds for one unparsable override
                return _plain_quote_hint(key, value)
            continue
        try:
            parser.parse_override(arg)
        except Exception:  # noqa: BLE001 - Hydra raises several kinds for one unparsable override
            if "(" in value and not key.lstrip("+~").endswith(("equations", "spec")):
                shown = value.replace('"', "'")
                return f""". In {key}=..., quote the value inside the single quotes: '{key}="{shown}"'"""
            if "(" in value:
                return (
                    f". In {key}=..., quote every expression that calls a function, inside the single quotes: "
                    f"'{key}={{omega: \"-g*sin(theta)\"}}' (or write it in a spec file)"
                )
            return f'. In {key}=..., quote every item that holds "=", inside the single quotes: [..., "system=lorenz3"]'
    return ""


def _plain_quote_hint(key: str, value: str) -> str:
    """Advice for a value Hydra's grammar cannot read as it stands: text with spaces or letters outside ASCII
    (`{q: θ pos}`), or brackets in a file name (`rec[1].csv`). Quoted inside the single quotes, it is a string."""
    if value.startswith("{") and ":" in value:
        inner = ", ".join(
            f'{k.strip()}: "{v.strip()}"' for k, _, v in (item.partition(":") for item in value.strip("{}").split(","))
        )
        return f". In {key}=..., quote each name or column that holds spaces or other letters: '{key}={{{inner}}}'"
    return f""". In {key}=..., quote the value inside the single quotes: '{key}="{value.replace('"', "'")}"'"""


def compose_command(command: str, args: list[str], config_dir: str) -> DictConfig | None:
    """Compose `command`'s config from its command-line `args` exactly as the run will, and check it.

    Runs before Hydra creates a run directory, without importing torch, so a typo or a bad value answers at
    once and leaves nothing behind. Returns None when the arguments hold options this check leaves to Hydra
    (``--cfg``, ``--help``, ``--config-dir``, ...).

    Raises:
        ConfigError: unknown key (with a did-you-mean instead of Hydra's "+key" advice), unknown option of a
            config group, a value of the wrong type, or a value out of range (`validate_values`).
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import OverrideParseException

    if any(a.startswith("-") and a not in _FLAGS_WITHOUT_VALUE for a in args):
        return None
    overrides = [a for a in args if a not in _FLAGS_WITHOUT_VALUE]
    try:
        variants = _sweep_variants(overrides)
    except OverrideParseException as err:
        raise ConfigError(f"cannot parse the command line: {one_line(err)}{_quote_hint(overrides)}") from None
    if variants is None:
        return None

    def _compose(items: list[str], hydra: bool = False) -> DictConfig:
        with initialize_config_dir(config_dir=config_dir, version_base="1.3", job_name=command):
            return compose(config_name=command, overrides=items, return_hydra_config=hydra)

    first = _compose_one(variants[0], _compose, config_dir)
    if any("sweeper" in a or a.startswith("hparams_search") or "interval(" in a for a in overrides):
        validate_search(_compose(variants[0], hydra=True).hydra.sweeper, overrides, first)
    validate_values(first)
    for items in variants[1:]:
        validate_values(_compose_one(items, _compose, config_dir))
    return first


def validate_search(sweeper: DictConfig, overrides: list[str], cfg: DictConfig) -> None:
    """Check an Optuna search (hparams_search=... or hydra/sweeper=optuna) before its first trial: the trial
    count, the direction, and every search space (`hydra.sweeper.params` and `key=interval(...)` /
    `choice(...)` on the command line) as Optuna will read it, so a typo is one message instead of a traceback after the study was created. `cfg`
    (the composed run config) tells which keys hold whole numbers: their intervals need the `int` tag."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import IntervalSweep

    intervals = [a for a in overrides if "interval(" in a and not a.startswith("hydra.")]
    if "optuna" not in str(sweeper.get("_target_", "")).lower():
        if intervals:
            key = intervals[0].split("=", 1)[0]
            raise ConfigError(
                f"{intervals[0]}: an interval is a search space, for an Optuna search (hparams_search=<file> or -m "
                f"hydra/sweeper=optuna); a -m sweep takes a list of values, e.g. {key}=1e-3,3e-3,1e-2."
            )
        return
    for key in ("n_trials", "n_jobs"):
        value = sweeper.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ConfigError(f"hydra.sweeper.{key}={value}: must be a whole number >= 1.")
    _check_direction(sweeper.get("direction"))
    parser = OverridesParser.create()
    spaces = [(f"hydra.sweeper.params.{k}", f"{k}={v}") for k, v in (sweeper.get("params") or {}).items()]
    spaces += [(a.split("=", 1)[0], a) for a in intervals]
    for where, text in spaces:
        try:
            sweep = parser.parse_override(text).value()
        except Exception as err:  # noqa: BLE001 - Hydra raises several kinds for one unparsable override
            raise ConfigError(
                f"{where}: cannot read the search space {text.split('=', 1)[1]!r}: {one_line(err)}"
            ) from None
        if isinstance(sweep, IntervalSweep):
            low, high = sweep.start, sweep.end
            if low is None or high is None or not low <= high:
                raise ConfigError(f"{where}=interval({low}, {high}): the low end must not exceed the high end.")
            key = text.split("=", 1)[0]
            if isinstance(OmegaConf.select(cfg, key), int):  # Hydra reads interval ends as floats: always fractions
                raise ConfigError(
                    f"{where}=interval({low:g}, {high:g}): {key} is a whole number, and Optuna draws fractions "
                    f"from an interval; write range({low:g}, {high:g}) (whole numbers, both ends included) or "
                    "choice(...)."
                )
            if "log" in sweep.tags and low <= 0:
                raise ConfigError(
                    f"{where}=tag(log, interval({low}, {high})): a log-scale interval needs a low end > 0, "
                    f"e.g. interval({high / 100:g}, {high:g})."
                )


def _check_direction(direction: Any) -> None:
    """`hydra.sweeper.direction` as the Optuna sweeper reads it: its own default, the enum `Direction.minimize`
    (`hydra/sweeper=optuna`), the string `minimize` or `maximize` (a yaml file or an override), or a list of them,
    one per objective. mpsim returns one objective (`objective=`), so a list holds one direction."""
    items = list(direction) if isinstance(direction, ListConfig | list | tuple) else [direction]
    names = [getattr(d, "name", d) for d in items]  # an Enum member -> its name
    if not names or any(n not in ("minimize", "maximize") for n in names):
        raise ConfigError(
            f"hydra.sweeper.direction={direction}: must be minimize or maximize (mpsim's objective "
            "is an error: minimize)."
        )
    if len(names) > 1:
        raise ConfigError(
            f"hydra.sweeper.direction={direction}: one direction per objective, and mpsim train returns one "
            "objective (objective=<summary entry>); give one: hydra.sweeper.direction=minimize."
        )


def _compose_one(firsts: list[str], _compose: Any, config_dir: str) -> DictConfig:
    """Compose one override list, turning Hydra's composition errors into `ConfigError`."""
    from hydra.errors import ConfigCompositionException, HydraException, MissingConfigException

    try:
        return _compose(firsts)
    except MissingConfigException as err:
        raise ConfigError(one_line(err)) from None
    except ConfigCompositionException as err:
        text = str(err)
        match = re.match(r"Could not override '([^']+)'", text)
        if match:
            raise ConfigError(
                unknown_key_message(
                    match.group(1), [a for a in firsts if override_key(a) != match.group(1)], _compose, config_dir
                )
            ) from None
        cause = f": {one_line(err.__cause__)}" if err.__cause__ is not None else ""
        raise ConfigError(f"{one_line(err)}{cause}") from None
    except HydraException as err:
        raise ConfigError(one_line(err)) from None
    except AssertionError as err:  # Hydra asserts on some overrides it cannot place (hydra.sweeper.params.<x>=...)
        keys = [override_key(a) for a in firsts]
        key = next((k for k in keys if k.startswith("hydra.sweeper.params.")), None)
        if key is not None:
            raise ConfigError(unknown_key_message(key, [], _compose, config_dir)) from None
        raise ConfigError(
            f"Hydra could not compose the command line ({one_line(err) or 'an internal check failed'})."
        ) from None


def one_line(err: BaseException) -> str:
    """An exception's message on one line (Hydra's option listings joined with commas)."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "reference_type=", "To append"))]
    if not lines:
        return type(err).__name__
    head, rest = lines[0], lines[1:]
    if rest and rest[0].startswith("Available options"):
        options = [ln for ln in rest[1:] if not ln.startswith(("Config search path", "provider="))]
        return f"{head.rstrip('.')}. {rest[0]} {', '.join(options)}."
    return " ".join([head, *rest[:2]])
